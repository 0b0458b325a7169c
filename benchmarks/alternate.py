"""What the rlexp-against-SB3 comparisons share (``sb3_cnn_compare.py``, ``sb3_recurrent_compare.py``):
their options, one process timed from launch to exit, and the rounds that alternate the two sides
(rlexp, SB3, rlexp, SB3, ...) so a shared machine's load falls on both, each run one JSON line, the
last line the ratio of the median rates (rlexp / SB3).

Standard library only: the SB3 interpreter imports it too (``--sb3-worker``).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SIDES = ("rlexp", "sb3")


def parser(doc: str, sb3_help: str) -> argparse.ArgumentParser:
    """The options both comparisons take; a script adds its own before :func:`parse`."""
    p = argparse.ArgumentParser(description=doc.splitlines()[0])
    p.add_argument("--sb3-python", help=sb3_help)
    p.add_argument("--steps", type=int, default=16384, help="env steps per run (both sides)")
    p.add_argument("--rounds", type=int, default=2, help="rlexp/SB3 pairs, alternating")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--threads", type=int, default=1, help="torch threads (both sides)")
    p.add_argument("--only", choices=SIDES, help="run one side only")
    p.add_argument("--rlexp-arg", action="append", default=[], help="extra train.py override")
    p.add_argument("--sb3-worker", action="store_true", help=argparse.SUPPRESS)
    return p


def parse(
    p: argparse.ArgumentParser, sb3_worker: Callable[[argparse.Namespace], None]
) -> argparse.Namespace | None:
    """The parsed options; None where this process was the SB3 side (``sb3_worker`` ran)."""
    args = p.parse_args()
    if args.sb3_worker:
        sb3_worker(args)
        return None
    if args.only != "rlexp" and not args.sb3_python:
        p.error("--sb3-python is required (or --only rlexp)")
    return args


def rlexp_cmd(args: argparse.Namespace, run_dir: Path, experiment: str, *more: str) -> list[str]:
    """``python train.py +experiment=...``: the run's steps and threads, no eval, no checkpoint
    but the final one, then ``more`` and the user's ``--rlexp-arg``."""
    return [
        sys.executable,
        str(REPO / "train.py"),
        f"+experiment={experiment}",
        f"seed={args.seed}",
        *more,
        f"trainer.total_frames={args.steps}",
        "trainer.eval_every=0",
        "trainer.save_every=0",
        f"trainer.torch_threads={args.threads}",
        f"hydra.run.dir={run_dir}",
        *args.rlexp_arg,
    ]


def sb3_cmd(args: argparse.Namespace, script: str, *more: str) -> list[str]:
    """``script --sb3-worker`` in the SB3 interpreter, with the run's steps, seed and threads."""
    return [
        args.sb3_python,
        str(Path(script).resolve()),
        "--sb3-worker",
        *more,
        f"--steps={args.steps}",
        f"--seed={args.seed}",
        f"--threads={args.threads}",
    ]


def run(cmd: list[str], rlexp: bool = False) -> dict:
    """Launch to exit: wall seconds, the child's peak RSS (MiB) and its output (``rlexp``: with
    this checkout's ``src`` on its path)."""
    env = dict(os.environ, PYTHONPATH=str(REPO / "src")) if rlexp else None
    start = time.perf_counter()
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    out = proc.stdout.read() if proc.stdout else b""
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - start
    if os.waitstatus_to_exitcode(status) != 0:
        sys.stderr.write(out.decode(errors="replace")[-3000:])
        raise SystemExit(f"failed: {' '.join(cmd)}")
    return {"wall_s": wall, "peak_rss_mib": usage.ru_maxrss / 1024, "out": out.decode()}


#: ``one_run(side, round, tmp)``: the run's :func:`run` result and the line's entries before
#: ``round`` and after ``peak_rss_mib``.
OneRun = Callable[[str, int, Path], tuple[dict, dict, dict]]


def alternate(args: argparse.Namespace, prefix: str, one_run: OneRun) -> None:
    """``args.rounds`` rounds of rlexp then SB3 (``--only``: one side), in a temporary dir; a
    JSON line each, then the ratio of the median rates."""
    rates: dict[str, list[float]] = {side: [] for side in SIDES}
    with tempfile.TemporaryDirectory(prefix=prefix) as tmp:
        for r in range(args.rounds):
            for side in SIDES:
                if args.only and side != args.only:
                    continue
                res, before, after = one_run(side, r, Path(tmp))
                rate = args.steps / res["wall_s"]
                rates[side].append(rate)
                line = {
                    "side": side,
                    **before,
                    "round": r,
                    "steps": args.steps,
                    "wall_s": round(res["wall_s"], 1),
                    "steps_per_s": round(rate, 1),
                    "peak_rss_mib": round(res["peak_rss_mib"]),
                    **after,
                }
                print(json.dumps(line), flush=True)
    if rates["rlexp"] and rates["sb3"]:
        ratio = statistics.median(rates["rlexp"]) / statistics.median(rates["sb3"])
        print(json.dumps({"ratio_rlexp_over_sb3": round(ratio, 2)}), flush=True)
