"""User envs that exit, interrupt, fail to restore or never end (#43 items 5, 6, 7, 11;
tests/fault_envs.py, docs/faults.md): each is the env's error like any other, one line naming what
was raised and where, with the documented exit code and status; nothing hangs."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from conftest import REPO, run_train

TESTS = Path(__file__).resolve().parent
PYPATH = {"PYTHONPATH": f"{REPO / 'src'}{os.pathsep}{TESTS}"}  # fault_envs importable
FAULT_ENVS = str(TESTS / "fault_envs.py")

RUN = [
    "env=hopper",
    "env.name=fault_envs:Walk-v0",
    "env.num_envs=1",
    "trainer.total_frames=512",
    "trainer.frames_per_batch=128",
    "trainer.save_every=128",
    "trainer.eval_every=0",
    "algorithm.num_epochs=1",
    "algorithm.compile=false",
    "logger=none",
    "trainer.progress=false",
]


def _train(tmp_path: Path, *args: str, run: str = "run") -> tuple[Path, int, str]:
    run_dir = tmp_path / run
    proc = run_train(
        [*RUN, f"hydra.run.dir={run_dir}", *args],
        cwd=tmp_path, check=False, env_extra=PYPATH, timeout=300,
    )  # fmt: skip
    return run_dir, proc.returncode, proc.stdout + proc.stderr


def _status(run_dir: Path) -> dict:
    return json.loads((run_dir / "status.json").read_text())


# -- item 11: the overlap child's error names its type and message -------------------------------
@pytest.mark.parametrize(
    ("what", "expected"),
    [
        ("memory", "MemoryError: Unable to allocate 2.00 PiB"),  # numpy's _ArrayMemoryError
        ("exit0", "SystemExit(0)"),  # user code's exit in the child: the same error
    ],
)
def test_an_error_in_the_overlap_child_names_its_type_message_and_place(tmp_path, what, expected):
    run_dir, code, out = _train(
        tmp_path, "algorithm.overlap=true", "+env.kwargs.exit_at=300",
        f"+env.kwargs.raise_what={what}",
    )  # fmt: skip
    assert code == 1, out[-3000:]
    reason = _status(run_dir)["reason"]
    head = f"CollectionError: in the collection process (algorithm.overlap=true): {expected}"
    assert reason.startswith(head), reason
    assert f"(raised in _raise() at {FAULT_ENVS}:" in reason
    assert "Traceback" not in out, out[-3000:]
