"""``rlexp eval`` / ``rlexp export`` start as ``train`` starts (#30 item 13): the cyclic GC is off
while torch, tensordict and TorchRL import (they trigger dozens of collections, ~0.8 s of CPU
here), and Hydra, which neither needs, is never imported."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from conftest import REPO, SHORT, run_train

PROBE = """
import gc, json, sys
from rlexp.cli import main
count = [0]
gc.callbacks.append(lambda phase, info: phase == "start" and count.__setitem__(0, count[0] + 1))
try:
    main(sys.argv[1:])
finally:
    print(json.dumps({"collections": count[0], "hydra": "hydra" in sys.modules}), file=sys.stderr)
"""


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    root = tmp_path_factory.mktemp("startup")
    run_train([*SHORT, f"hydra.run.dir={root / 'run'}"], cwd=root)
    return root / "run"


@pytest.mark.parametrize("command", [["eval", "--episodes", "1"], ["export"]])
def test_eval_and_export_import_without_the_gc_and_without_hydra(run_dir, command, tmp_path):
    args = [command[0], str(run_dir), *command[1:]]
    if command[0] == "export":
        args += ["--out", str(tmp_path / "policy.pt")]
    out = subprocess.run(
        [sys.executable, "-c", PROBE, *args], cwd=tmp_path, capture_output=True, text=True,
        timeout=300, env={**os.environ, "PYTHONPATH": str(REPO / "src")},
    )  # fmt: skip
    assert out.returncode == 0, out.stderr
    seen = json.loads(out.stderr.strip().splitlines()[-1])
    assert seen["hydra"] is False
    # with the GC on, the imports alone trigger ~60 collections here; argparse's few remain
    assert seen["collections"] <= 8, seen
