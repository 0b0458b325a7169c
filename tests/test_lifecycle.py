"""Run lifecycle: NaN guard, W&B offline files and run-id reuse, provenance, keep_last."""

from __future__ import annotations

import json
import os
import subprocess
import sys

from conftest import REPO, only_run_dir, run_train
from rlexp.checkpoints.files import load_checkpoint, step_checkpoints

BASE = [
    "env=inverted_pendulum",
    "trainer.frames_per_batch=256",
    "trainer.save_every=256",
    "trainer.eval_every=0",
    "algorithm.num_epochs=1",
]


def test_non_finite_observation_stops_the_run_and_keeps_the_last_good_checkpoint(tmp_path):
    run_dir = tmp_path / "run"
    run_train([*BASE, "trainer.total_frames=512", f"hydra.run.dir={run_dir}"], cwd=tmp_path)
    before = {p.name: p.read_bytes() for p in (run_dir / "checkpoints").glob("*.pt")}
    # Continue it (an explicit resume: the events differ from the first part) with an env that
    # starts producing infinite observations.
    last = max((run_dir / "checkpoints").glob("*_step_*.pt"))
    proc = run_train(
        [
            *BASE,
            "trainer.total_frames=1024",
            f"hydra.run.dir={run_dir}",
            "events=noise",
            "events.train.observation_noise.params.std=1e300",
            f"trainer.resume={last}",
        ],
        cwd=tmp_path,
        check=False,
    )
    assert proc.returncode == 3, proc.stderr
    out = proc.stdout + proc.stderr
    assert "non-finite next/observation from the env at step 768" in out
    after = {p.name: p.read_bytes() for p in (run_dir / "checkpoints").glob("*.pt")}
    assert after == before, "a checkpoint was written or changed after the NaN"


def test_keep_last_and_provenance(tmp_path):
    head_before = _git(REPO, "rev-parse", "HEAD")
    run_train([*BASE, "trainer.total_frames=1280", "trainer.keep_last=2"], cwd=tmp_path)
    heads = {
        head_before,
        _git(REPO, "rev-parse", "HEAD"),
    }  # someone may commit while the run trains
    run_dir = only_run_dir(tmp_path)
    assert [p.name.rsplit("_", 1)[1] for p in step_checkpoints(run_dir / "checkpoints")] == [
        "000001024.pt",
        "000001280.pt",
    ]
    prov = json.loads((run_dir / "provenance.json").read_text())
    assert prov["versions"]["torch"].startswith("2.") and prov["versions"]["torchrl"] == "0.14.1"
    assert prov["device"] == "cpu" and prov["host"] and prov["start_time"]
    assert prov["git_commit"] in heads, (prov["git_commit"], heads)  # rlexp's checkout
    assert prov["git_dirty"] == (run_dir / "git.diff").is_file()
    assert prov["project"] is None  # the working dir (tmp_path) is no git repository
    assert "torch==" in (run_dir / "pip-freeze.txt").read_text()
    ckpt = load_checkpoint(step_checkpoints(run_dir / "checkpoints")[-1])
    assert (
        ckpt["versions"]["torchrl"] == "0.14.1"
        and ckpt["config"]["env"]["name"] == "InvertedPendulum-v5"
    )


def test_wandb_offline_writes_files_and_a_resumed_run_keeps_its_id(tmp_path, monkeypatch):
    monkeypatch.delenv("WANDB_MODE", raising=False)
    monkeypatch.delenv("WANDB_API_KEY", raising=False)
    monkeypatch.setenv("HOME", str(tmp_path))  # no ~/.netrc key
    run_dir = tmp_path / "run"
    # eval_every=0 would mean no evaluation: these runs evaluate, so eval rows reach W&B too.
    args = [
        *BASE,
        "trainer.eval_every=256",
        "logger=[tensorboard,wandb]",
        f"hydra.run.dir={run_dir}",
    ]
    first = run_train(
        [*args, "trainer.total_frames=512"], cwd=tmp_path, env_extra={"WANDB_MODE": None}
    )
    assert "logging offline" in first.stdout + first.stderr
    run_id = (run_dir / "wandb_run_id.txt").read_text().strip()
    runs = sorted((run_dir / "wandb").glob("offline-run-*"))
    assert len(runs) == 1 and runs[0].name.endswith(run_id)
    wandb_file = next(runs[0].glob("run-*.wandb"))
    assert wandb_file.stat().st_size > 0
    run_train([*args, "trainer.total_frames=768"], cwd=tmp_path, env_extra={"WANDB_MODE": None})
    runs = sorted((run_dir / "wandb").glob("offline-run-*"))
    assert all(r.name.endswith(run_id) for r in runs), "the resumed run got a new W&B id"

    from wandb_reader import history  # read back what W&B wrote

    rows = [r for run in runs for r in history(next(run.glob("run-*.wandb")))]
    steps = sorted(r["_step"] for r in rows if "loss/policy" in r)
    assert steps == [256, 512, 768], steps
    assert any("eval/episode_return" in r for r in rows)


def test_tensorboard_continues_the_step_axis_on_resume(tmp_path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    run_dir = tmp_path / "run"
    run_train([*BASE, "trainer.total_frames=512", f"hydra.run.dir={run_dir}"], cwd=tmp_path)
    run_train([*BASE, "trainer.total_frames=1024", f"hydra.run.dir={run_dir}"], cwd=tmp_path)
    steps = []
    for f in sorted((run_dir / "tensorboard").glob("events.*")):
        acc = EventAccumulator(str(f))
        acc.Reload()
        steps += [e.step for e in acc.Scalars("loss/policy")]
    assert sorted(steps) == [256, 512, 768, 1024]


def test_wandb_in_a_multirun_one_run_per_job_grouped_by_the_sweep(tmp_path):
    from wandb_reader import run_info

    sweep_dir = tmp_path / "sweep"
    proc = subprocess.run(
        [
            sys.executable,
            str(REPO / "train.py"),
            "-m",
            *BASE,
            "trainer.total_frames=256",
            "logger=wandb",
            "seed=0,1",
            f"hydra.sweep.dir={sweep_dir}",
        ],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "PYTHONPATH": str(REPO / "src"), "WANDB_MODE": "offline"},
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    infos = [
        run_info(next((sweep_dir / job / "wandb").glob("offline-run-*/run-*.wandb")))
        for job in ("0", "1")
    ]
    assert infos[0]["id"] != infos[1]["id"]
    assert infos[0]["group"] == infos[1]["group"] == sweep_dir.name


def _git(repo, *args: str) -> str:
    return subprocess.run(
        ["git", "-C", str(repo), *args], capture_output=True, text=True, check=True
    ).stdout.strip()


def _repo(path, files: dict[str, str]):
    path.mkdir(parents=True)
    for name, text in files.items():
        (path / name).parent.mkdir(parents=True, exist_ok=True)
        (path / name).write_text(text)
    _git(path, "init", "-q")
    _git(path, "add", ".")
    _git(path, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "-m", "first")
    return path


def test_provenance_records_the_checkouts_commit_and_whether_it_is_dirty(tmp_path, monkeypatch):
    """rlexp's checkout (a stand-in repository) and the working dir's project: commit = rev-parse
    HEAD, git_dirty and git.diff follow a change to a tracked file."""
    from rlexp.run import provenance

    checkout = _repo(tmp_path / "rlexp", {"pyproject.toml": "", "src/rlexp/__init__.py": "x = 1\n"})
    project = _repo(tmp_path / "project", {"train.py": "print(1)\n"})
    monkeypatch.setattr(provenance, "REPO", checkout)
    monkeypatch.chdir(project)
    (tmp_path / "run_clean").mkdir()
    clean = provenance.write_provenance(tmp_path / "run_clean", "cpu")
    assert clean["git_commit"] == _git(checkout, "rev-parse", "HEAD") and not clean["git_dirty"]
    assert not (tmp_path / "run_clean" / "git.diff").exists()
    assert clean["project"] == {
        "path": str(project.resolve()),
        "git_commit": _git(project, "rev-parse", "HEAD"),
        "git_dirty": False,
    }

    (checkout / "src" / "rlexp" / "__init__.py").write_text("x = 2\n")
    (project / "train.py").write_text("print(2)\n")
    (tmp_path / "run_dirty").mkdir()
    dirty = provenance.write_provenance(tmp_path / "run_dirty", "cpu")
    assert dirty["git_commit"] == clean["git_commit"] and dirty["git_dirty"] is True
    assert "+x = 2" in (tmp_path / "run_dirty" / "git.diff").read_text()
    assert dirty["project"]["git_dirty"] is True
    assert json.loads((tmp_path / "run_dirty" / "provenance.json").read_text())["git_dirty"] is True
