"""Trainer hooks: the points fire in order with the right data; stop_at ends a run early with a
final checkpoint; a schedule changes the optimiser's learning rate as logged; resume with a schedule
is bit-exact; both ranks of a two-rank run stop at the same iteration; bad hook configs fail in one
line before the run dir is written."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from conftest import compose, run_train
from rlexp.checkpoints.files import latest_checkpoint, load_checkpoint
from rlexp.config.validate import ConfigError, to_root_config
from rlexp.hooks import HookControl, HookState, register_hook

TINY = [
    "env=inverted_pendulum",
    "trainer.frames_per_batch=256",
    "trainer.eval_episodes=2",
    "algorithm.num_epochs=1",
    "logger=none",
    "trainer.progress=false",
]

SEEN: list[tuple[str, dict]] = []


@register_hook("test_recorder")
class Recorder:
    """Records every point it sees (registered for all points) and logs one scalar."""

    def __call__(self, state: HookState, control: HookControl) -> None:
        data = {"step": state.global_step, "iteration": state.iteration}
        if state.point == "train_start":
            data["resumed"] = state.resumed
        elif state.point == "rollout_end":
            data["batch"] = tuple(state.batch.batch_size)
        elif state.point == "update_end":
            data["losses"] = sorted(state.losses)
        elif state.point == "log":
            data["metrics"] = "perf/sps" in state.metrics
            control.log("custom/value", 7.0)
        elif state.point == "eval_end":
            data["eval"] = "eval/episode_return" in state.eval_metrics
        elif state.point == "checkpoint":
            data["checkpoint"] = state.checkpoint.is_file()
        elif state.point == "train_end":
            data["status"] = state.status
        with pytest.raises(TypeError):
            state.metrics["x"] = 1.0  # read-only
        SEEN.append((state.point, data))


def _trainer(tmp_path: Path, overrides: list[str]):
    from rlexp.run.metrics import MetricLogger, make_logger
    from rlexp.training.build import build

    config = to_root_config(compose([*TINY, *overrides]))
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    objects = build(config, run_dir, "cpu", config.trainer.total_frames)
    logger = (
        make_logger(config.logger, run_dir, "t", {}) if config.logger.jsonl else MetricLogger([])
    )
    return objects.trainer(logger, {}, {}), config, run_dir


def test_every_hook_point_fires_in_order_with_its_data(tmp_path):
    SEEN.clear()
    trainer, config, run_dir = _trainer(
        tmp_path,
        ["trainer.total_frames=512", "trainer.eval_every=512", "trainer.save_every=512",
         "logger.jsonl=true", "+hooks.rec.func=test_recorder"],
    )  # fmt: skip
    try:
        trainer.train(config.trainer.total_frames)
    finally:
        trainer.close()
    points = [p for p, _ in SEEN]
    iteration = ["rollout_end", "update_end", "log"]
    assert points == [
        "train_start",
        *iteration,
        *iteration,
        "eval_end",
        "checkpoint",
        "train_end",
    ], points
    data = dict(SEEN)  # the last of each point
    assert SEEN[0][1] == {"step": 0, "iteration": 0, "resumed": False}
    assert SEEN[1][1]["batch"] == (1, 256) and SEEN[1][1]["iteration"] == 0
    assert "loss/policy" in SEEN[2][1]["losses"] and SEEN[2][1]["iteration"] == 1
    assert data["log"]["metrics"] and data["eval_end"]["eval"] and data["checkpoint"]["checkpoint"]
    assert data["train_end"] == {"step": 512, "iteration": 2, "status": "finished"}
    rows = [json.loads(x) for x in (run_dir / "metrics.jsonl").read_text().splitlines()]
    assert [r["custom/value"] for r in rows if "custom/value" in r] == [7.0, 7.0]


def test_control_refuses_a_hyperparameter_that_is_not_mutable():
    control = HookControl({"lr": 3e-4, "clip_epsilon": 0.2})
    control.where = "hooks.x"
    with pytest.raises(ValueError, match=r"'lmbda' is not a mutable hyperparameter; choose from"):
        control.set("lmbda", 0.9)
    with pytest.raises(ValueError, match="did you mean 'lr'"):
        control.set("lrr", 0.1)


def test_stop_at_ends_a_real_run_early_with_a_checkpoint_and_status(tmp_path):
    run_dir = tmp_path / "run"
    proc = run_train(
        [*TINY, "trainer.total_frames=20480", "trainer.eval_every=1024", "trainer.save_every=0",
         "+hooks.stop.func=stop_at", "+hooks.stop.params.threshold=-1",
         "+hooks.stop.params.times=2", f"hydra.run.dir={run_dir}"],
        cwd=tmp_path,
    )  # fmt: skip
    status = json.loads((run_dir / "status.json").read_text())
    assert status["state"] == "stopped_early", status
    assert status["global_step"] == 2048  # the second eval in a row at or past the threshold
    assert "eval/episode_return=" in status["reason"] and "(2 in a row)" in status["reason"]
    assert "hooks.stop" in status["reason"]
    assert load_checkpoint(latest_checkpoint(run_dir / "checkpoints"))["global_step"] == 2048
    assert "stopping early at step 2048" in proc.stdout + proc.stderr
    # A re-run of the same command (a sweep re-run) does not train on.
    again = run_train([*TINY, "trainer.total_frames=20480", f"hydra.run.dir={run_dir}",
                       "+hooks.stop.func=stop_at", "+hooks.stop.params.threshold=-1",
                       "+hooks.stop.params.times=2", "trainer.eval_every=1024",
                       "trainer.save_every=0"], cwd=tmp_path)  # fmt: skip
    assert "already stopped early" in again.stdout + again.stderr


def test_a_schedule_sets_the_optimisers_learning_rate_as_logged(tmp_path):
    trainer, config, run_dir = _trainer(
        tmp_path,
        ["trainer.total_frames=1024", "trainer.eval_every=0", "trainer.save_every=0",
         "logger.jsonl=true", "hooks=lr_anneal", "algorithm.lr=1e-3"],
    )  # fmt: skip
    seen = []
    update = trainer.algorithm.update

    def spy(batch):
        out = update(batch)
        seen.append(trainer.algorithm.optimizer.param_groups[0]["lr"])
        return out

    trainer.algorithm.update = spy
    try:
        trainer.train(config.trainer.total_frames)
    finally:
        trainer.close()
    expected = [1e-3 * (1 - s / 1024) for s in (256, 512, 768, 1024)]
    assert seen == pytest.approx(expected)
    rows = [json.loads(x) for x in (run_dir / "metrics.jsonl").read_text().splitlines()]
    assert [r["loss/learning_rate"] for r in rows] == pytest.approx(expected)
    assert [r["hparams/lr"] for r in rows] == pytest.approx(expected)


def test_entropy_and_clip_schedules_reach_the_ppo_loss(tmp_path):
    trainer, config, _ = _trainer(
        tmp_path,
        ["trainer.total_frames=512", "trainer.eval_every=0", "trainer.save_every=0",
         "hooks=entropy_anneal", "+hooks.clip.func=schedule", "+hooks.clip.params.name=clip_epsilon",
         "+hooks.clip.params.start=0.3", "+hooks.clip.params.end=0.1"],
    )  # fmt: skip
    try:
        seen = []  # the loss's coefficient at each update, as the schedule set it
        update = trainer.algorithm.update
        trainer.algorithm.update = lambda batch: (
            seen.append(float(trainer.algorithm.loss.entropy_coeff)),
            update(batch),
        )[1]
        trainer.train(config.trainer.total_frames)
        loss = trainer.algorithm.loss
        assert seen[0] > 0.0 and seen == sorted(seen, reverse=True)  # the hook's annealing
        assert float(loss.entropy_coeff) == pytest.approx(0.0)  # annealed to 0 at the budget
        assert float(loss.clip_epsilon) == pytest.approx(0.1)
        assert trainer.algorithm.hyperparameters()["clip_epsilon"] == pytest.approx(0.1)
    finally:
        trainer.close()


def test_sigkill_and_resume_with_a_schedule_is_bit_identical(tmp_path):
    from test_resume import _assert_resume_is_exact

    _assert_resume_is_exact(
        tmp_path,
        "inverted_pendulum",
        frames=512,
        batch=256,
        extra=["hooks=[lr_anneal,entropy_anneal,early_stop]", "logger=none"],
        eval_every=256,
    )
    a = load_checkpoint(latest_checkpoint(tmp_path / "whole" / "checkpoints"))
    b = load_checkpoint(latest_checkpoint(tmp_path / "broken" / "checkpoints"))
    assert a["algorithm"]["hyperparameters"] == b["algorithm"]["hyperparameters"]
    assert a["algorithm"]["hyperparameters"]["lr"] == 0.0  # annealed to 0 at the end
    assert a["hooks"] == b["hooks"] and "hooks.early_stop" in a["hooks"]


def test_both_ranks_stop_at_the_same_iteration(tmp_path):
    """Only rank 0 evaluates, so only its stop_at sees the eval metric: rank 1 must stop with it."""
    from test_distributed import _two_ranks

    run_dir = tmp_path / "run"
    args = [*TINY, "trainer.total_frames=4096", "trainer.eval_every=1024", "trainer.save_every=0",
            "+hooks.stop.func=stop_at", "+hooks.stop.params.threshold=-1",
            "trainer.resume=never", f"hydra.run.dir={run_dir}"]  # fmt: skip
    ranks = _two_ranks(args, [], cwd=tmp_path)
    out = "\n".join(f"--- rank {r}:\n{p.stdout[-3000:]}" for r, p in enumerate(ranks))
    for proc in ranks:
        assert proc.returncode == 0, out
        assert "stopping early at step 1024" in proc.stdout, out
    assert "parameters identical on all 2 ranks" in ranks[0].stdout, out
    status = json.loads((run_dir / "status.json").read_text())
    assert status["state"] == "stopped_early" and status["global_step"] == 1024, status


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (["+hooks.s.func=stop_att"], "hooks.s.func='stop_att' is not a known hook"),
        (["+hooks.s.func=stop_at"], "hooks.s.params: stop_at needs parameter(s) ['threshold']"),
        (["+hooks.s.func=stop_at", "+hooks.s.params.treshold=3"], "did you mean 'threshold'"),
        (["+hooks.s.fun=stop_at"], "hooks.s.fun is not a hook key"),
        (
            ["+hooks.s.func=schedule", "+hooks.s.params.name=lmbda"],
            "hooks.s.params.name='lmbda' is not a mutable hyperparameter of algorithm=ppo",
        ),
        (["hooks=lr_anneal", "algorithm.anneal_lr=true"], "anneals the learning rate twice"),
        (["+hooks.s.func=os.system"], "dotted paths must be inside"),
    ],
    ids=["unknown", "required", "param", "key", "not-mutable", "twice", "import"],
)
def test_a_bad_hook_is_one_line_and_exit_2_before_the_run_dir(tmp_path, overrides, message):
    run_dir = tmp_path / "run"
    proc = subprocess.run(
        [sys.executable, str(Path(__file__).parents[1] / "train.py"), *TINY, *overrides,
         f"hydra.run.dir={run_dir}"],
        cwd=tmp_path, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert proc.returncode == 2, proc.stderr[-2000:]
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], proc.stderr
    assert not run_dir.exists()


def test_the_hook_presets_compose():
    from conftest import CONF_DIR

    for path in sorted((CONF_DIR / "hooks").glob("*.yaml")):
        config = to_root_config(compose([f"hooks={path.stem}"]))
        assert isinstance(config.hooks, dict)
    with pytest.raises(ConfigError, match="hooks.median_stop.params.warmup=2"):
        to_root_config(compose(["hooks=median_stop", "hooks.median_stop.params.warmup=2"]))


def test_hooks_in_the_json_format_rlexp_section(tmp_path):
    import shutil

    from conftest import SHARED
    from rlexp.launch.json_entry import compose_json_experiment, load_json_experiment

    shutil.copy(SHARED / "seed-configs" / "cart_pole" / "gym_config.json", tmp_path)
    train = json.loads((SHARED / "seed-configs" / "cart_pole" / "train_config.json").read_text())
    train["rlexp"] = {"hooks": {"stop": {"func": "stop_at", "params": {"threshold": 475}}}}
    (tmp_path / "train_config.json").write_text(json.dumps(train))
    config = compose_json_experiment(load_json_experiment(tmp_path / "train_config.json", tmp_path))
    assert (
        config.hooks["stop"].func == "stop_at" and config.hooks["stop"].params["threshold"] == 475
    )
    train["rlexp"]["hooks"]["stop"]["params"] = {"threshhold": 475}
    (tmp_path / "train_config.json").write_text(json.dumps(train))
    with pytest.raises(ConfigError, match="did you mean 'threshold'"):
        compose_json_experiment(load_json_experiment(tmp_path / "train_config.json", tmp_path))


def test_the_trainer_holds_no_reference_in_the_hook_state():
    import dataclasses

    names = {f.name for f in dataclasses.fields(HookState)}
    assert "trainer" not in names and "algorithm" not in names and "policy" not in names
    assert torch  # (imported for the checkpoints above)


@register_hook("log_action_std", points=("rollout_end",))
def log_action_std(state, control, scale=1.0):
    """docs/hooks.md's own example, verbatim."""
    control.log("rollout/action_std", scale * float(state.batch["action"].std()))


def test_the_docs_custom_hook_runs_and_its_params_are_checked(tmp_path):
    trainer, config, run_dir = _trainer(
        tmp_path,
        ["trainer.total_frames=256", "trainer.eval_every=0", "trainer.save_every=0",
         "logger.jsonl=true", "+hooks.astd.func=log_action_std", "+hooks.astd.params.scale=2"],
    )  # fmt: skip
    try:
        trainer.train(config.trainer.total_frames)
    finally:
        trainer.close()
    row = json.loads((run_dir / "metrics.jsonl").read_text().splitlines()[0])
    assert row["rollout/action_std"] > 0
    with pytest.raises(ConfigError, match="did you mean 'scale'"):
        to_root_config(compose([*TINY, "+hooks.a.func=log_action_std", "+hooks.a.params.scal=2"]))
