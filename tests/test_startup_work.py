"""Start-up does only the work its command needs (#45 item 9), asserted as work done, not time:
``rlexp train --help`` builds Hydra's config repository once per listing (it built it for each of
~110 groups: ~1.2 s of 2 s) and imports no torch / TorchRL / W&B; re-running a finished sweep
skips its jobs before any of them imports torch or builds an env (12 s for 2 jobs before)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from conftest import REPO

#: Not needed before training starts (and not at all to print help or skip a finished job).
HEAVY = ("torch", "torchrl", "tensordict", "wandb", "optuna", "matplotlib", "scipy", "onnx",
         "mujoco", "torch.utils.tensorboard")  # fmt: skip

PROBE = """
import atexit, json, sys
from hydra._internal.config_loader_impl import ConfigLoaderImpl
builds = []
original = ConfigLoaderImpl._parse_overrides_and_create_caching_repo
def counted(self, *args, **kwargs):
    builds.append(1)
    return original(self, *args, **kwargs)
ConfigLoaderImpl._parse_overrides_and_create_caching_repo = counted
heavy = {heavy!r}
def report():
    print("PROBE " + json.dumps({{"builds": len(builds),
          "imported": [m for m in heavy if m in sys.modules]}}), flush=True)
atexit.register(report)
from rlexp import cli
cli.main({argv!r})
"""


def _probe(argv: list[str], cwd: Path) -> tuple[dict, subprocess.CompletedProcess]:
    env = {**os.environ, "PYTHONPATH": str(REPO / "src")}
    code = PROBE.format(heavy=HEAVY, argv=argv)
    proc = subprocess.run(
        [sys.executable, "-c", code], cwd=cwd, capture_output=True, text=True, env=env, timeout=300
    )
    lines = [line for line in proc.stdout.splitlines() if line.startswith("PROBE ")]
    assert lines, f"exit {proc.returncode}\n{proc.stdout}\n{proc.stderr}"
    return json.loads(lines[-1][len("PROBE ") :]), proc


def test_train_help_builds_the_config_repository_once_per_listing_and_imports_nothing_heavy(
    tmp_path,
):
    found, proc = _probe(["train", "--help"], tmp_path)
    assert "env: " in proc.stdout and "policy: " in proc.stdout  # the groups are listed
    assert found["imported"] == [], found
    # compose (1) + the two listings of groups (1 each); it was one per group (112)
    assert found["builds"] <= 4, found


def test_rerunning_a_finished_sweep_skips_its_jobs_without_importing_torch(tmp_path):
    sweep = tmp_path / "sweep"
    args = [
        "train", "-m", "trainer=smoke", "env=hopper",
        "env.name=Pendulum-v1", "trainer.total_frames=256", "trainer.frames_per_batch=128",
        "trainer.eval_every=256", "trainer.eval_episodes=1", "trainer.save_every=256",
        "trainer.progress=false", "seed=1,2", f"hydra.sweep.dir={sweep}",
    ]  # fmt: skip
    first, proc = _probe(args, tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "torch" in first["imported"]  # the probe sees a real run's imports
    again, proc = _probe(args, tmp_path)
    assert proc.returncode == 0, proc.stderr
    log = proc.stdout + proc.stderr
    assert log.count("already finished at step 256: skipping") == 2, log
    assert again["imported"] == [], again
