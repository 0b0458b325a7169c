"""The machine a benchmark ran on, in one line for its results file (CPU, cores, load, versions):
shared by ppo_throughput.py and end_to_end.py."""

from __future__ import annotations

import os
import platform
from pathlib import Path


def machine_note() -> str:
    import torch

    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    vers = [f"torch {torch.__version__}"]
    for mod in ("torchrl", "stable_baselines3", "gymnasium", "mujoco"):
        try:
            vers.append(f"{mod} {__import__(mod).__version__}")
        except ImportError:
            vers.append(f"{mod} (not installed)")
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    return f"{cpu}, {cores} cores, load average {load:.1f} at the start; " + ", ".join(vers)
