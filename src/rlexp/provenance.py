"""What produced a run: versions, git state, installed packages, host, device, start time."""

from __future__ import annotations

import json
import logging
import platform
import socket
import subprocess
import sys
import time
from importlib import metadata
from pathlib import Path

log = logging.getLogger(__name__)

REPO = Path(__file__).resolve().parents[2]
PACKAGES = ("rlexp", "torch", "torchrl", "tensordict", "mujoco", "gymnasium", "hydra-core", "numpy")


def versions() -> dict[str, str]:
    """Versions of Python and the packages that shape results."""
    out = {"python": platform.python_version()}
    for name in PACKAGES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = "not installed"
    return out


def _git(*args: str) -> str | None:
    try:
        proc = subprocess.run(
            ["git", "-C", str(REPO), *args], capture_output=True, text=True, timeout=20
        )
    except (OSError, subprocess.TimeoutExpired):
        return None
    return proc.stdout if proc.returncode == 0 else None


def write_provenance(run_dir: Path, device: str) -> dict:
    """Write ``provenance.json`` (+ ``git.diff`` when dirty, ``pip-freeze.txt``) into the run dir."""
    commit = _git("rev-parse", "HEAD")
    diff = _git("diff", "HEAD") if commit else None
    info = {
        "versions": versions(),
        "git_commit": commit.strip() if commit else None,
        "git_dirty": bool(diff),
        "host": socket.gethostname(),
        "platform": platform.platform(),
        "device": device,
        "argv": sys.argv,
        "start_time": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }
    if diff:
        (run_dir / "git.diff").write_text(diff)
    # pip freeze's content, read from package metadata (a pip subprocess costs ~0.3 s of start-up)
    dists = sorted(
        {
            f"{d.metadata['Name']}=={d.version}"
            for d in metadata.distributions()
            if d.metadata["Name"]
        },
        key=str.lower,
    )
    (run_dir / "pip-freeze.txt").write_text("\n".join(dists) + "\n")
    (run_dir / "provenance.json").write_text(json.dumps(info, indent=2) + "\n")
    return info
