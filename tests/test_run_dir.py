"""What a run dir holds stays whole: pruning never loses the newest checkpoint, `resume=never` never
mixes two runs, a full disk or a failure mid-run ends with status `failed`, a reason and the last
good checkpoint, and a resumed checkpoint must fit the run (docs/faults.md)."""

from __future__ import annotations

import errno
import json
import subprocess
from pathlib import Path

import pytest
import torch

from conftest import SHORT, compose, run_train
from rlexp.checkpoints.files import (
    latest_checkpoint,
    load_checkpoint,
    save_checkpoint,
    step_checkpoints,
)
from rlexp.config.validate import ConfigError, to_root_config


def _status(run_dir: Path) -> dict:
    return json.loads((run_dir / "status.json").read_text())


def _steps(run_dir: Path) -> list[int]:
    return [int(p.stem.rsplit("_", 1)[1]) for p in step_checkpoints(run_dir / "checkpoints")]


def test_pruning_keeps_the_checkpoint_just_written_and_moves_corrupt_ones_aside(tmp_path):
    run_dir = tmp_path / "run"
    args = [*SHORT, "trainer.keep_last=1", f"hydra.run.dir={run_dir}"]
    run_train(args, cwd=tmp_path)
    assert _steps(run_dir) == [512]
    # A crash left a corrupt checkpoint with a higher step.
    corrupt = run_dir / "checkpoints" / "InvertedPendulum-v5_ppo_step_000999999.pt"
    corrupt.write_bytes(b"torn")
    proc = run_train([*args, "trainer.total_frames=1024"], cwd=tmp_path)
    assert "moved to" in proc.stdout and "corrupt" in proc.stdout
    assert (run_dir / "checkpoints" / "corrupt" / corrupt.name).read_bytes() == b"torn"
    assert _steps(run_dir) == [1024], "the newest good checkpoint was pruned"
    # The next run continues from it, not from scratch.
    proc = run_train([*args, "trainer.total_frames=1280"], cwd=tmp_path)
    assert "at step 1024" in proc.stdout
    assert load_checkpoint(latest_checkpoint(run_dir))["global_step"] == 1280


def test_resume_never_refuses_a_dir_that_holds_a_run(tmp_path):
    run_dir = tmp_path / "run"
    run_train([*SHORT, f"hydra.run.dir={run_dir}"], cwd=tmp_path)
    before = {p: p.read_bytes() for p in run_dir.rglob("*") if p.is_file()}
    proc = run_train(
        [*SHORT, "trainer.resume=never", "seed=3", f"hydra.run.dir={run_dir}"],
        cwd=tmp_path,
        check=False,
    )
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert f"trainer.resume=never but run dir {run_dir} holds a run" in proc.stderr
    after = {p: p.read_bytes() for p in run_dir.rglob("*") if p.is_file()}
    assert after == before, "the refused run wrote into the dir"
    # A new dir is fine.
    run_train([*SHORT, "trainer.resume=never", f"hydra.run.dir={tmp_path / 'new'}"], cwd=tmp_path)


# -- in-process runs with faults injected --------------------------------------------------------------
def _config(*extra: str):
    return to_root_config(compose([*SHORT, "logger=none", "logger.jsonl=true", *extra]))


def _train(config, run_dir: Path):
    from rlexp.app import train

    return train(config, run_dir)


def test_a_full_disk_at_a_checkpoint_fails_with_the_reason_and_keeps_the_last_good_one(
    tmp_path, monkeypatch
):
    import rlexp.checkpoints.files as ckpt_mod
    from rlexp.app import RunEnded

    real_save, calls = torch.save, []

    def save(obj, f, *a, **kw):
        calls.append(1)
        if len(calls) == 2:  # the second checkpoint: the disk is full half-way
            f.write(b"half a checkpoint")
            raise RuntimeError("PytorchStreamWriter failed writing file data/0: file write failed")
        return real_save(obj, f, *a, **kw)

    monkeypatch.setattr(ckpt_mod.torch, "save", save)
    run_dir = tmp_path / "run"
    with pytest.raises(RunEnded) as err:
        _train(_config(), run_dir)
    assert err.value.exit_code == 1
    status = _status(run_dir)
    assert status["state"] == "failed" and status["global_step"] == 512
    assert "writing" in status["reason"] and "step_000000512.pt" in status["reason"]
    assert "the last good checkpoint is" in status["reason"] and "000000256" in status["reason"]
    assert _steps(run_dir) == [256] and not list(run_dir.rglob("*.tmp-*"))
    assert load_checkpoint(latest_checkpoint(run_dir))["global_step"] == 256


def test_a_full_disk_for_metrics_keeps_training_and_never_tears_a_line(tmp_path, monkeypatch):
    import rlexp.run.metrics as logging_mod

    real_write, calls = logging_mod.os.write, []

    def write(fd, data):
        calls.append(1)
        if len(calls) in (2, 3):  # the second and third rows: ENOSPC after a few bytes
            real_write(fd, bytes(data[:7]))
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_write(fd, data)

    monkeypatch.setattr(logging_mod.os, "write", write)
    run_dir = tmp_path / "run"
    _train(_config("trainer.total_frames=1024"), run_dir)
    assert _status(run_dir)["state"] == "finished"
    rows = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == [256, 1024], "rows 2 and 3 were lost whole, no half line"
    assert _steps(run_dir)[-1] == 1024


def test_a_torn_last_line_from_an_older_crash_is_cut_before_appending(tmp_path):
    from rlexp.run.metrics import JsonlBackend

    (tmp_path / "metrics.jsonl").write_text('{"step": 1, "a": 1.0}\n{"step": 2, "a"')
    backend = JsonlBackend(tmp_path)
    backend.log({"a": 3.0}, 3)
    backend.close()
    rows = [json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == [1, 3]


def test_a_failure_after_an_update_saves_that_update_and_says_why(tmp_path, monkeypatch):
    from rlexp.app import RunEnded
    from rlexp.training.trainer import Trainer

    def broken_eval(self):
        raise RuntimeError("the renderer died")

    monkeypatch.setattr(Trainer, "eval_once", broken_eval)
    run_dir = tmp_path / "run"
    with pytest.raises(RunEnded) as err:
        _train(_config("trainer.eval_every=256", "trainer.save_every=0"), run_dir)
    assert err.value.exit_code == 1 and "the renderer died" in str(err.value)
    status = _status(run_dir)
    assert status["state"] == "failed" and "RuntimeError: the renderer died" in status["reason"]
    assert "error.log" in status["reason"]
    assert "broken_eval" in (run_dir / "error.log").read_text()
    assert _steps(run_dir) == [256], "the completed update of step 256 was not saved"


@pytest.mark.skipif(subprocess.run(["id", "-u"], capture_output=True, text=True).stdout.strip() != "0",
                    reason="mounting a tmpfs needs root")  # fmt: skip
def test_a_really_full_disk(tmp_path):
    """A 600 kB tmpfs: checkpoints of ~110 kB fill it; the run ends failed with the reason."""
    mnt = tmp_path / "small"
    mnt.mkdir()
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=600k", "tmpfs", str(mnt)])
    if mounted.returncode != 0:
        pytest.skip("mount -t tmpfs is not permitted here")
    try:
        run_dir = mnt / "run"
        args = [*SHORT, "trainer.total_frames=8192", "trainer.keep_last=0", "logger=none",
                "logger.jsonl=true", f"hydra.run.dir={run_dir}"]  # fmt: skip
        proc = run_train(args, cwd=tmp_path, check=False)
        assert proc.returncode == 1, proc.stdout + proc.stderr
        assert "Traceback" not in proc.stdout + proc.stderr
        assert "No space left on device" in proc.stdout + _status(run_dir)["reason"]
        assert _status(run_dir)["state"] == "failed"
        assert not list(run_dir.rglob("*.tmp-*"))
        for path in step_checkpoints(run_dir / "checkpoints"):
            load_checkpoint(path)  # every checkpoint left is whole
        for line in (run_dir / "metrics.jsonl").read_text().splitlines():
            json.loads(line)
    finally:
        subprocess.run(["umount", str(mnt)])


# -- a resumed checkpoint must fit ---------------------------------------------------------------------
def test_checkpoints_that_do_not_fit_are_refused_naming_the_part(tmp_path):
    from conftest import CONF_DIR
    from rlexp.launch.precheck import precheck

    run_dir = tmp_path / "src"
    run_train([*SHORT, f"hydra.run.dir={run_dir}"], cwd=tmp_path)
    good = load_checkpoint(latest_checkpoint(run_dir))
    base = ["env=inverted_pendulum", "trainer.frames_per_batch=256"]

    def variant(name: str, change) -> Path:
        ckpt = load_checkpoint(latest_checkpoint(run_dir))
        ckpt.pop("path")
        change(ckpt)
        return save_checkpoint(tmp_path / name, ckpt)

    def bad_opt(c):
        c["algorithm"]["optimizer"]["state"][0]["exp_avg"] = torch.zeros(3, 3)

    cases = {
        variant("neg.pt", lambda c: c.update(global_step=-5)): "global_step=-5",
        variant("opt.pt", bad_opt): "optimiser state exp_avg of",
        variant("iter.pt", lambda c: c["algorithm"].update(iteration=-1)): "iteration=-1",
        variant("nopolicy.pt", lambda c: c.pop("policy")): "no 'policy' section",
    }
    for path, message in cases.items():
        with pytest.raises(ConfigError, match=message):
            precheck([*base, f"trainer.resume={path}"], CONF_DIR)
    n = good["config"]["env"]["num_envs"]
    with pytest.raises(ConfigError, match=f"env.num_envs={n} training envs, this run has"):
        precheck(["env=inverted_pendulum", "env.num_envs=2", "trainer.frames_per_batch=256",
                  f"trainer.resume={good['path']}"], CONF_DIR)  # fmt: skip


# -- a refused run rewrites nothing ----------------------------------------------------------------------
def _snapshot(root: Path) -> dict[Path, bytes]:
    return {p: p.read_bytes() for p in root.rglob("*") if p.is_file()}


def test_a_run_refused_for_another_experiment_leaves_the_dir_untouched(tmp_path):
    run_dir = tmp_path / "run"
    run_train([*SHORT, f"hydra.run.dir={run_dir}"], cwd=tmp_path)
    before = _snapshot(run_dir)
    proc = run_train(
        [*SHORT, "algorithm.clip_epsilon=0.3", f"hydra.run.dir={run_dir}"],
        cwd=tmp_path,
        check=False,
    )
    assert proc.returncode == 2 and "holds a different experiment" in proc.stderr
    assert _snapshot(run_dir) == before, ".hydra/, train.log or status changed"


def test_a_sweep_dir_holding_another_sweep_is_refused_before_anything_is_written(tmp_path):
    sweep_dir = tmp_path / "sweep"
    args = [*SHORT, "trainer.total_frames=256", f"hydra.sweep.dir={sweep_dir}"]
    run_train(["-m", *args, "seed=0,1"], cwd=tmp_path)
    assert (sweep_dir / "0" / ".hydra" / "overrides.yaml").is_file()
    before = _snapshot(sweep_dir)
    proc = run_train(["-m", *args, "seed=2,3"], cwd=tmp_path, check=False)
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert f"sweep dir {sweep_dir} holds another sweep" in proc.stdout + proc.stderr
    assert _snapshot(sweep_dir) == before
    # The same sweep again is a re-run: its finished jobs are skipped.
    proc = run_train(["-m", *args, "seed=0,1"], cwd=tmp_path)
    assert proc.stdout.count("already finished") == 2


def test_strings_that_look_like_interpolations_stay_data_in_config_yaml_and_checkpoints(
    tmp_path, monkeypatch
):
    """A JSON file's "${oc.env:SECRET}" is escaped when loaded; it must stay those characters in
    everything the run writes (config.yaml, checkpoints, W&B's config), never become the secret."""
    from rlexp.config.validate import to_dict
    from rlexp.run.rundir import check_same_experiment, write_run_files

    monkeypatch.setenv("RLEXP_SECRET", "hunter2")
    config = _config("events=record_rollouts")
    literal = "${oc.env:RLEXP_SECRET}/rollouts"
    config.events.train["record_rollouts"].params["save_path"] = literal
    d = to_dict(config)
    assert d["events"]["train"]["record_rollouts"]["params"]["save_path"] == literal
    assert to_dict(to_root_config(d)) == d, "a checkpoint's config must read back as it was"
    (tmp_path / "run").mkdir()
    write_run_files(config, d, tmp_path / "run", "cpu")
    text = (tmp_path / "run" / "config.yaml").read_text()
    assert (
        "hunter2" not in text
        and "hunter2" not in (tmp_path / "run" / "train_config.json").read_text()
    )
    (tmp_path / "run" / "checkpoints").mkdir()
    save_checkpoint(tmp_path / "run" / "checkpoints" / "x_step_000000001.pt", {"config": d})
    check_same_experiment(tmp_path / "run", d)  # the saved config reads back equal
