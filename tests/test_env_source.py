"""Your own env outside the training shell (#45 item 2): a run on ``env.name=<module>:<Id>`` trained
with ``PYTHONPATH=<project>`` records the folder its module came from, so ``rlexp eval RUN`` (the
``next:`` line the run prints, as written) and ``rlexp export RUN`` work from a shell without it; an
exported file never extends ``sys.path`` and a module that cannot be found is one line, exit 2."""

from __future__ import annotations

import json
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import REPO, run_train

MODULE = "lab_env_45"
SOURCE = """
import gymnasium as gym
import numpy as np
from gymnasium import spaces


class Slide(gym.Env):
    observation_space = spaces.Box(-1, 1, (3,), np.float32)
    action_space = spaces.Box(-1, 1, (2,), np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.s = self.np_random.uniform(-1, 1, 3).astype(np.float32)
        return self.s, {}

    def step(self, a):
        self.s = np.clip(self.s + 0.1 * np.r_[a, 0].astype(np.float32), -1, 1)
        return self.s, -float(np.abs(self.s).sum()), False, False, {}


gym.register("Slide-v0", entry_point=__name__ + ":Slide", max_episode_steps=15)
"""


def _rlexp(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    """``rlexp ARGS`` from a shell whose PYTHONPATH has rlexp only (not the project)."""
    env = {**os.environ, "PYTHONPATH": str(REPO / "src")}
    return subprocess.run(
        [sys.executable, "-m", "rlexp", *args],
        cwd=cwd, capture_output=True, text=True, timeout=120, env=env,
    )  # fmt: skip


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> tuple[Path, Path, str]:
    root = tmp_path_factory.mktemp("own_env")
    project = root / "project"
    project.mkdir()
    (project / f"{MODULE}.py").write_text(SOURCE)
    run_dir = root / "run"
    proc = run_train(
        [
            "env=hopper",
            f"env.name={MODULE}:Slide-v0",
            "env.num_eval_envs=3",
            "trainer.frames_per_batch=128",
            "trainer.total_frames=256",
            "trainer.eval_every=128",
            "trainer.eval_episodes=4",
            "trainer.save_every=256",
            "trainer.progress=false",
            f"hydra.run.dir={run_dir}",
        ],
        cwd=project,
        env_extra={"PYTHONPATH": f"{REPO / 'src'}{os.pathsep}{project}"},
    )
    nxt = re.search(r"^next: (rlexp eval \S+)", proc.stdout + proc.stderr, re.M)
    assert nxt, proc.stdout + proc.stderr
    return run_dir, project, nxt.group(1)


def test_the_run_records_where_its_env_module_came_from(trained):
    run_dir, project, _ = trained
    info = json.loads((run_dir / "provenance.json").read_text())
    assert info["env_source"] == {"module": MODULE, "path": str(project.resolve())}


def test_eval_and_export_of_the_run_work_from_a_shell_without_its_pythonpath(trained, tmp_path):
    run_dir, _, next_line = trained
    args = shlex.split(next_line)[1:]  # the line as printed: rlexp eval RUN
    proc = _rlexp(args, tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "over 4 episodes" in proc.stdout  # the run's own eval_episodes
    out = tmp_path / "slide.pt"
    proc = _rlexp(["export", str(run_dir), "--out", str(out)], tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert out.is_file()
    # The exported file's metadata never extends sys.path: one line naming the module, exit 2.
    proc = _rlexp(["eval", str(out)], tmp_path)
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr and len(proc.stderr.strip().splitlines()) == 1
    assert f"needs module {MODULE!r}" in proc.stderr and "PYTHONPATH=" in proc.stderr


def test_a_module_the_run_s_folder_no_longer_holds_is_one_line_exit_2(trained, tmp_path):
    run_dir, project, _ = trained
    (tmp_path / "away").mkdir()
    moved = tmp_path / "away" / f"{MODULE}.py"  # (not the cwd: python -m puts that on sys.path)
    (project / f"{MODULE}.py").rename(moved)
    try:
        for command in (["eval", str(run_dir)], ["export", str(run_dir), "--out", "x.pt"]):
            proc = _rlexp(command, tmp_path)
            assert proc.returncode == 2, proc.stderr
            lines = proc.stderr.strip().splitlines()
            assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
            assert f"needs module {MODULE!r}" in lines[0]
            assert f"the run imported it from {project.resolve()}" in lines[0]
    finally:
        moved.rename(project / f"{MODULE}.py")


def test_an_installed_module_is_never_shadowed_by_a_recorded_folder(tmp_path, monkeypatch):
    """The recorded folder goes at the end of sys.path, and only for a module not importable."""
    from rlexp.runtime.env_source import ensure_env_importable

    (tmp_path / "json.py").write_text("raise SystemExit('shadowed')\n")
    (tmp_path / "provenance.json").write_text(
        json.dumps({"env_source": {"module": "json", "path": str(tmp_path)}})
    )
    monkeypatch.setattr(sys, "path", list(sys.path))
    ensure_env_importable("json:Nothing-v0", tmp_path)
    assert str(tmp_path) not in sys.path
