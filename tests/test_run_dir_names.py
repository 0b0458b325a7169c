"""Default run dirs are one per launch (#30 item 1): seeds started together from a shell loop each
get their own dir, named by the launch time to the microsecond, so they still sort by time; a dir
named explicitly still resumes."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from datetime import datetime

import yaml

from conftest import REPO, SHORT

STAMP = re.compile(r"\d{4}-\d\d-\d\d/\d\d-\d\d-\d\d\.\d{6}")


def test_the_launch_time_is_read_once_per_process():
    from rlexp.config import schema

    first = schema.launch_time("%Y-%m-%d/%H-%M-%S.%f")
    assert STAMP.fullmatch(first)
    assert schema.launch_time("%H-%M-%S.%f") == first.split("/")[1]  # the same instant
    assert schema.launch_time("%Y-%m-%d") == first.split("/")[0]
    stamp = datetime.strptime(first, "%Y-%m-%d/%H-%M-%S.%f")
    assert abs((datetime.now() - stamp).total_seconds()) < 24 * 3600


def test_seeds_launched_together_each_get_a_run_dir_of_their_own(tmp_path, children):
    procs = []
    for seed in (0, 1, 2):
        procs.append(
            children.train([*SHORT, f"seed={seed}"], tmp_path, tmp_path / f"console{seed}.txt")
        )
    codes = [p.wait(timeout=600) for p in procs]
    consoles = [(tmp_path / f"console{s}.txt").read_text() for s in (0, 1, 2)]
    assert codes == [0, 0, 0], consoles
    dirs = sorted(p.parent for p in tmp_path.glob("outputs/*/*/status.json"))
    assert len(dirs) == 3, dirs
    for run_dir in dirs:
        assert STAMP.fullmatch(f"{run_dir.parent.name}/{run_dir.name}"), run_dir
        assert json.loads((run_dir / "status.json").read_text())["state"] == "finished"
    seeds = sorted(yaml.safe_load((d / "config.yaml").read_text())["seed"] for d in dirs)
    assert seeds == [0, 1, 2]


def test_a_sweep_dir_is_stamped_too(tmp_path):
    out = subprocess.run(
        [sys.executable, str(REPO / "train.py"), "-m", *SHORT, "seed=4,5"],
        cwd=tmp_path, capture_output=True, text=True, timeout=600,
        env={**os.environ, "PYTHONPATH": str(REPO / "src")},
    )  # fmt: skip
    assert out.returncode == 0, out.stderr[-3000:]
    (sweep,) = [p.parent for p in tmp_path.glob("multirun/*/*/multirun.yaml")]
    assert STAMP.fullmatch(f"{sweep.parent.name}/{sweep.name}")
    assert sorted(p.name for p in sweep.iterdir() if (p / "status.json").is_file()) == ["0", "1"]
