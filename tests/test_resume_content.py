"""Resume trusts content, not status.json (#29 item 2; rlexp.run.proof, docs/runs.md): a run dir
whose run trained but whose checkpoints are gone or unloadable is refused, not restarted into the
same metrics.jsonl; a dir that says finished skips only for the config its config.yaml proves
(a sweep dir that lost its multirun.yaml included), and Optuna takes a finished job's result only
for the parameters it ran with; two sweeps racing for one sweep dir: exactly one wins."""

from __future__ import annotations

import json
import shutil
import threading
from pathlib import Path

import pytest

from conftest import SWEEP_TINY, compose, run_train
from rlexp.checkpoints.files import step_checkpoints
from rlexp.config.validate import ConfigError, to_root_config

#: A run with two checkpoints (256, 512) and an eval at each: status.json has a final eval.
RUN = [*SWEEP_TINY, "logger=none", "logger.jsonl=true", "seed=7"]


def _config(*extra: str):
    return to_root_config(compose([*RUN, *extra]))


def _train(config, run_dir: Path):
    from rlexp.app import train

    return train(config, run_dir)


def _snapshot(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in root.rglob("*") if p.is_file()}


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory) -> Path:
    """A finished run (seed 7, 512 steps, checkpoints at 256 and 512, two evals), trained once."""
    run_dir = tmp_path_factory.mktemp("resume_content") / "run"
    _train(_config(), run_dir)
    status = json.loads((run_dir / "status.json").read_text())
    assert status["state"] == "finished" and status["global_step"] == 512
    assert "eval/episode_return" in status["final_eval"]
    return run_dir


def _copy(finished_run: Path, tmp_path: Path) -> Path:
    run_dir = tmp_path / "run"
    shutil.copytree(finished_run, run_dir)
    return run_dir


def _interrupted_at_512(run_dir: Path) -> None:
    """status.json as a run stopped by a signal at step 512 leaves it (resume=auto continues it)."""
    status = json.loads((run_dir / "status.json").read_text())
    status.update(state="interrupted", reason="SIGINT received", final_eval={})
    (run_dir / "status.json").write_text(json.dumps(status))


# -- (a) trained, but no checkpoint that loads: refused, nothing appended --------------------------
def test_an_interrupted_run_whose_checkpoints_are_gone_is_refused_not_restarted(
    finished_run, tmp_path
):
    run_dir = _copy(finished_run, tmp_path)
    _interrupted_at_512(run_dir)
    shutil.rmtree(run_dir / "checkpoints")
    before = _snapshot(run_dir)
    proc = run_train(
        [*RUN, "trainer.total_frames=1024", f"hydra.run.dir={run_dir}"], cwd=tmp_path, check=False
    )
    assert proc.returncode == 2, proc.stdout + proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in proc.stdout + proc.stderr, proc.stderr
    assert f"run dir {run_dir} holds metrics of a run (step 512) in metrics.jsonl" in lines[0]
    assert "no checkpoint that loads" in lines[0] and "move that dir aside" in lines[0]
    # Nothing was written: not a row appended to metrics.jsonl, the status as it was.
    after = _snapshot(run_dir)
    assert {k: v for k, v in after.items() if k != ".rlexp.lock"} == {
        k: v for k, v in before.items() if k != ".rlexp.lock"
    }


def test_every_checkpoint_corrupt_is_refused_like_none(finished_run, tmp_path):
    """Not in the issue's text: checkpoints/ is there, but no file in it loads."""
    run_dir = _copy(finished_run, tmp_path)
    _interrupted_at_512(run_dir)
    for path in step_checkpoints(run_dir / "checkpoints"):
        path.write_bytes(b"PK\x03\x04 cut short")
    metrics = (run_dir / "metrics.jsonl").read_bytes()
    with pytest.raises(ConfigError, match=r"holds metrics of a run \(step 512\)"):
        _train(_config("trainer.total_frames=1024"), run_dir)
    assert (run_dir / "metrics.jsonl").read_bytes() == metrics
    assert len(list((run_dir / "checkpoints" / "corrupt").iterdir())) == 2  # moved aside, named


def test_a_status_at_a_step_without_metrics_or_checkpoints_is_refused(finished_run, tmp_path):
    run_dir = _copy(finished_run, tmp_path)
    _interrupted_at_512(run_dir)
    shutil.rmtree(run_dir / "checkpoints")
    (run_dir / "metrics.jsonl").unlink()
    with pytest.raises(ConfigError, match=r"a status.json of a run \(interrupted at step 512\)"):
        _train(_config("trainer.total_frames=1024"), run_dir)


def test_a_checkpoint_of_another_config_is_refused_when_config_yaml_is_gone(finished_run, tmp_path):
    """config.yaml gone, checkpoints there: the checkpoint's own config decides (lr differs)."""
    run_dir = _copy(finished_run, tmp_path)
    _interrupted_at_512(run_dir)
    (run_dir / "config.yaml").unlink()
    with pytest.raises(
        ConfigError, match=r"is of a different experiment \(differs in algorithm.lr\)"
    ):
        _train(_config("trainer.total_frames=1024", "algorithm.lr=0.00042"), run_dir)


def test_a_run_that_failed_in_its_first_rollout_is_not_a_run(tmp_path):
    """The NaN guard on the first batch: status failed at step 256 (its steps counted), nothing
    learned or logged past step 0; the corrected config may start in that dir."""
    from rlexp.run.proof import trained_without_checkpoint

    (tmp_path / "metrics.jsonl").write_text('{"step": 0, "eval/episode_return": 5.0}\n')
    (tmp_path / "status.json").write_text('{"state": "failed", "global_step": 256}')
    assert trained_without_checkpoint(tmp_path) == ""
    (tmp_path / "status.json").write_text('{"state": "running", "global_step": 256}')
    assert trained_without_checkpoint(tmp_path) == "a status.json of a run (running at step 256)"
    with (tmp_path / "metrics.jsonl").open("a") as f:
        f.write('{"step": 256, "loss/policy": 0.1}\n{"step": 512, "los')  # a torn last row
    assert trained_without_checkpoint(tmp_path) == "metrics of a run (step 256) in metrics.jsonl"


# -- (b) "already finished: skipping" only for the config config.yaml proves ----------------------
def test_a_finished_dir_skips_for_its_own_config_and_returns_its_result(finished_run, tmp_path):
    run_dir = _copy(finished_run, tmp_path)
    final = json.loads((run_dir / "status.json").read_text())["final_eval"]
    before = _snapshot(run_dir)
    # trainer.total_frames may change (a budget already reached): still this experiment's result
    assert _train(_config("trainer.total_frames=256"), run_dir) == final
    assert {k: v for k, v in _snapshot(run_dir).items() if k != ".rlexp.lock"} == {
        k: v for k, v in before.items() if k != ".rlexp.lock"
    }


def test_a_finished_dir_of_another_config_is_refused_not_skipped(finished_run, tmp_path):
    run_dir = _copy(finished_run, tmp_path)
    with pytest.raises(
        ConfigError,
        match=rf"run dir {run_dir} says finished at step 512 for a different experiment "
        r"\(differs in algorithm.clip_epsilon, algorithm.lr\)",
    ):
        _train(_config("algorithm.lr=0.00042", "algorithm.clip_epsilon=0.31"), run_dir)


def test_a_finished_dir_without_config_yaml_is_refused_not_skipped(finished_run, tmp_path):
    run_dir = _copy(finished_run, tmp_path)
    (run_dir / "config.yaml").unlink()
    with pytest.raises(ConfigError, match="holds no config.yaml to show which config that was"):
        _train(_config(), run_dir)  # even the same config: nothing proves it


def test_a_sweep_dir_without_multirun_yaml_does_not_hand_old_results_to_new_configs(tmp_path):
    sweep = tmp_path / "sweep"
    args = [
        "-m",
        *SWEEP_TINY,
        "logger=none",
        "trainer.total_frames=256",
        f"hydra.sweep.dir={sweep}",
    ]
    run_train([*args, "seed=3,4"], cwd=tmp_path)
    (sweep / "multirun.yaml").unlink()
    before = {n: _snapshot(sweep / n) for n in ("0", "1")}
    proc = run_train([*args, "seed=3,4", "algorithm.gamma=0.91"], cwd=tmp_path, check=False)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 1, out
    assert "skipping" not in out and "Traceback" not in out
    for n in ("0", "1"):
        assert (
            f"run dir {sweep / n} says finished at step 256 for a different experiment "
            "(differs in algorithm.gamma)" in out
        )
        after = {k: v for k, v in _snapshot(sweep / n).items() if k != "train.log"}
        assert after == {k: v for k, v in before[n].items() if k != "train.log"}


def test_optuna_takes_a_finished_jobs_result_only_for_the_parameters_it_ran_with(tmp_path):
    from rlexp.launch.optuna_sweeper import finished_value

    job = tmp_path / "3"
    (job / ".hydra").mkdir(parents=True)
    (job / ".hydra" / "overrides.yaml").write_text("- algorithm.lr=0.00042\n- seed=5\n")
    status = {"state": "finished", "global_step": 512, "final_eval": {"eval/episode_return": 61.5}}
    (job / "status.json").write_text(json.dumps(status))
    assert finished_value(job, ["algorithm.lr=0.00042", "seed=5"]) == 61.5
    assert finished_value(job, ["algorithm.lr=0.0031", "seed=5"]) is None
    (job / ".hydra" / "overrides.yaml").unlink()
    assert finished_value(job, ["algorithm.lr=0.00042"]) is None


# -- (c) the sweep-dir check is atomic ---------------------------------------------------------------
def _sweep_config(sweep: Path, overrides: list[str]):
    from omegaconf import OmegaConf

    return OmegaConf.create(
        {"hydra": {"sweep": {"dir": str(sweep)}, "overrides": {"task": overrides}}}
    )


def _race(sweep: Path, overrides: dict[str, list[str]]) -> dict[str, int]:
    """Start one sweep per entry of ``overrides`` into ``sweep`` at the same instant (a barrier):
    the exit code each one's ``on_multirun_start`` gave (0: it went on)."""
    from rlexp.launch.sweep import SweepSummary

    barrier, outcome = threading.Barrier(len(overrides)), {}

    def start(name: str) -> None:
        barrier.wait()
        try:
            SweepSummary().on_multirun_start(_sweep_config(sweep, overrides[name]))
            outcome[name] = 0
        except SystemExit as exc:
            outcome[name] = exc.code

    threads = [threading.Thread(target=start, args=(name,)) for name in overrides]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    return outcome


def test_two_sweeps_racing_for_one_sweep_dir_exactly_one_wins(tmp_path, monkeypatch):
    """Two sweeps (different overrides) check the sweep dir at the same instant, and writing
    multirun.yaml takes 0.15 s: without the lock both pass the check (each checks before the other
    has written), every time. With it, exactly one wins, every round, and its multirun.yaml is the
    one on disk."""
    from omegaconf import OmegaConf

    real_save = OmegaConf.save

    def slow_save(config, f, *a, **kw):
        threading.Event().wait(0.15)
        return real_save(config, f, *a, **kw)

    monkeypatch.setattr(OmegaConf, "save", staticmethod(slow_save))
    mine = {"a": ["seed=0,1", "algorithm.lr=0.001"], "b": ["seed=0,1", "algorithm.lr=0.002"]}
    for round_ in range(8):
        sweep = tmp_path / f"sweep{round_}"
        outcome = _race(sweep, mine)
        assert sorted(outcome.values()) == [0, 2], f"round {round_}: {outcome}"
        winner = next(n for n, code in outcome.items() if code == 0)
        saved = OmegaConf.load(sweep / "multirun.yaml")
        assert list(saved.hydra.overrides.task) == mine[winner]
        assert not list(sweep.glob(".multirun.yaml.tmp-*"))
    # The same sweep started twice at once is a re-run of itself: both go on.
    assert _race(tmp_path / "same", {"a": mine["a"], "b": mine["a"]}) == {"a": 0, "b": 0}
