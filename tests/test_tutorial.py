"""docs/tutorial.md, run verbatim (#30 item 12): its bash blocks in order, as one script, in a
fresh directory, with ``rlexp`` on the PATH; then what each step promised is checked on disk."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

from conftest import REPO

DOC = REPO / "docs" / "tutorial.md"


def _script() -> str:
    blocks = re.findall(r"```bash\n(.*?)```", DOC.read_text(), re.S)
    return "set -euo pipefail\n" + "\n".join(blocks)


def _status(run_dir: Path) -> dict:
    return json.loads((run_dir / "status.json").read_text())


def test_the_tutorial_runs_verbatim(tmp_path, children):
    bin_dir = Path(sys.executable).parent  # rlexp's console script sits beside the venv's python
    env = {
        **os.environ,
        "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}",
        "PYTHONPATH": str(REPO / "src"),
        "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"),
    }
    console = tmp_path / "console.txt"
    with open(console, "w") as out:
        proc = children.popen(
            ["bash", "-c", _script()], cwd=tmp_path, env=env, stdout=out, stderr=subprocess.STDOUT
        )
    try:
        code = proc.wait(timeout=900)
    except subprocess.TimeoutExpired:
        raise AssertionError(
            f"the tutorial did not finish:\n{console.read_text()[-3000:]}"
        ) from None
    text = console.read_text()
    assert code == 0, text[-4000:]
    runs = tmp_path / "tutorial" / "runs"

    first = _status(runs / "first")
    assert first["state"] == "finished" and first["global_step"] == 4096
    assert "done: 4,096 env steps" in text and re.search(r"next: rlexp eval \S*runs/first ", text)
    assert re.search(r'"step": 4096', (runs / "first" / "metrics.jsonl").read_text())
    assert "mean return" in text  # rlexp eval
    for sweep in ("clip02", "clip01"):
        for job in ("0", "1"):
            assert _status(runs / sweep / job)["state"] == "finished"
    assert (runs / "clip02" / "report.md").is_file() and (runs / "clip02" / "report.csv").is_file()
    assert "algorithm.clip_epsilon" in text  # compare names what differs
    assert (runs / "first_policy.pt").is_file() and (runs / "first_policy.pt.json").is_file()

    # the crash: rlexp runs saw it died, the same command resumed it from its checkpoint
    assert re.search(r"\bdied\b", text), text[-3000:]  # no other run of the tutorial dies
    long = _status(runs / "long")
    assert long["state"] == "finished" and long["global_step"] == 8192
    log = (runs / "long" / "train.log").read_text()
    assert re.search(r"\[resume\] continuing from \S+_step_0+[1-9]\d*\.pt at step [1-9]", log), log[
        -2000:
    ]
