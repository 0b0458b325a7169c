"""The run's last line says what the run ended with and what to do next (#30 item 16)."""

from __future__ import annotations

from types import SimpleNamespace

from rlexp.run.next_steps import done_message


def _trainer(**kw):
    base = dict(
        global_step=1_003_520,
        cfg=SimpleNamespace(best_metric="eval/success_rate"),
        last_eval={"eval/success_rate": 0.625, "eval/episode_return": 12.5},
        best_metric=0.875,
        last_checkpoint="/r/checkpoints/a_step_000001003520.pt",
    )
    return SimpleNamespace(**{**base, **kw})


def test_done_names_the_final_and_best_eval_of_the_runs_metric_and_the_next_commands(tmp_path):
    run_dir = tmp_path / "run with space"
    (run_dir / "tensorboard").mkdir(parents=True)
    first, second = done_message(_trainer(), run_dir).split("\n")
    assert first == (
        "done: 1,003,520 env steps; final eval eval/success_rate=0.625 (best 0.875); "
        "checkpoint /r/checkpoints/a_step_000001003520.pt"
    )
    assert second == (
        f"next: rlexp eval '{run_dir}'  |  tensorboard --logdir '{run_dir}/tensorboard'  |  rlexp runs"
    )


def test_without_evaluation_or_tensorboard_it_says_only_what_there_is(tmp_path):
    text = done_message(_trainer(last_eval={}, best_metric=-float("inf")), tmp_path)
    assert text.split("\n")[0] == (
        "done: 1,003,520 env steps; checkpoint /r/checkpoints/a_step_000001003520.pt"
    )
    assert "tensorboard" not in text and text.endswith(
        f"next: rlexp eval {tmp_path}  |  rlexp runs"
    )
