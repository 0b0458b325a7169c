"""Learning, measured (issue #28): the classic-control presets, several seeds each, and how soon
each run reaches its task's threshold in deterministic evaluation.

For every preset x seed, one after another (never two trainings at once: the numbers are wall
seconds), this runs

    python train.py +experiment=<preset> seed=<seed> trainer.progress=false hydra.run.dir=<root>/<preset>/seed<seed>

reads ``metrics.jsonl`` of the run and prints a markdown table (``--out`` writes it to a file too):

- steps to threshold: the first evaluation step whose ``eval/episode_return`` (mean over the
  eval episodes, deterministic actions) is >= the threshold;
- s to threshold: that evaluation row's ``time`` minus ``provenance.json``'s ``start_time`` (the
  run's start after Hydra composed the config; whole seconds), as ``rlexp report`` counts time to
  result;
- stays from: the first evaluation step from which every later evaluation is >= the threshold;
- final / best eval: the last and the highest ``eval/episode_return``;
- wall s: launch to exit of ``train.py``, measured here with ``time.perf_counter()``;
- load: the 1-minute load average when the run ended (other work on the machine slows the runs).

The medians are over the seeds that reached the threshold (n/N says how many did).

Thresholds: CartPole-v1 475, Acrobot-v1 -100, Pendulum-v1 -250, LunarLander-v3 200.

    python benchmarks/classic_control.py                                   # ~15-25 min on 2 cores
    python benchmarks/classic_control.py --presets cartpole_ppo --seeds 0  # one run, ~40 s
    python benchmarks/classic_control.py --read outputs/classic_control/<stamp>   # table only
    make results-classic ARGS="--out /tmp/classic.md"

The LunarLander preset needs Box2D (``pip install "rlexp[box2d]"``); without it, it is skipped with
a note unless named in ``--presets``.
"""

from __future__ import annotations

import argparse
import datetime
import importlib.util
import json
import os
import shlex
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

#: preset -> (Gymnasium id, threshold on the mean deterministic eval return)
PRESETS: dict[str, tuple[str, float]] = {
    "cartpole_ppo": ("CartPole-v1", 475.0),
    "acrobot_ppo": ("Acrobot-v1", -100.0),
    "pendulum_ppo": ("Pendulum-v1", -250.0),
    "lunar_lander_ppo": ("LunarLander-v3", 200.0),
}
NEEDS_BOX2D = {"lunar_lander_ppo"}
EVAL_METRIC = "eval/episode_return"


@dataclass
class Run:
    preset: str
    seed: int
    run_dir: Path
    wall_s: float | None = None  # launch to exit (None: read from disk, not run here)
    returncode: int | None = None
    evals: list[tuple[int, float, float | None]] = field(default_factory=list)  # step, return, time
    start: float | None = None  # provenance.json start_time, epoch seconds
    load: float | None = None  # 1-min load average at exit (the machine is shared: context)

    @property
    def threshold(self) -> float:
        return PRESETS[self.preset][1]

    def first_reach(self) -> tuple[int, float | None] | None:
        """(step, seconds from the run's start) of the first eval >= the threshold."""
        for step, ret, at in self.evals:
            if ret >= self.threshold:
                secs = at - self.start if at is not None and self.start is not None else None
                return step, secs
        return None

    def stays_from(self) -> int | None:
        """The first eval step from which every later eval is >= the threshold."""
        step = None
        for s, ret, _ in self.evals:
            if ret >= self.threshold:
                step = s if step is None else step
            else:
                step = None
        return step


def parse_time(text: object) -> float | None:
    """An rlexp timestamp (``2026-11-23T15:37:22+0000``) as epoch seconds."""
    try:
        return datetime.datetime.strptime(str(text), "%Y-%m-%dT%H:%M:%S%z").timestamp()
    except ValueError:
        return None


def read_run(run: Run) -> Run:
    """Fill ``run.evals`` (metrics.jsonl, last row per step) and ``run.start`` (provenance.json)."""
    by_step: dict[int, tuple[float, float | None]] = {}
    metrics = run.run_dir / "metrics.jsonl"
    if metrics.exists():
        for line in metrics.read_text().splitlines():
            try:
                row = json.loads(line)
            except ValueError:
                continue  # a torn last line of a killed run
            if EVAL_METRIC in row:
                by_step[int(row["step"])] = (float(row[EVAL_METRIC]), row.get("time"))
    run.evals = [(s, r, t) for s, (r, t) in sorted(by_step.items())]
    try:
        prov = json.loads((run.run_dir / "provenance.json").read_text())
        run.start = parse_time(prov.get("start_time"))
    except (OSError, ValueError):
        run.start = None
    return run


def command(preset: str, seed: int, run_dir: Path, extra: list[str]) -> list[str]:
    return [
        sys.executable,
        str(REPO / "train.py"),
        f"+experiment={preset}",
        f"seed={seed}",
        "trainer.progress=false",
        f"hydra.run.dir={run_dir}",
        *extra,
    ]


def train(run: Run, extra: list[str], timeout: float) -> Run:
    """One training, its output in ``<run_dir>.log``; killed (by subprocess.run) past ``timeout``."""
    run.run_dir.parent.mkdir(parents=True, exist_ok=True)
    cmd = command(run.preset, run.seed, run.run_dir, extra)
    print("$", shlex.join(cmd), flush=True)
    log = run.run_dir.with_suffix(".log")
    t0 = time.perf_counter()
    with log.open("w") as out:
        try:
            proc = subprocess.run(
                cmd, cwd=REPO, stdout=out, stderr=subprocess.STDOUT, timeout=timeout
            )
            run.returncode = proc.returncode
        except subprocess.TimeoutExpired:
            run.returncode = -9
    run.wall_s = time.perf_counter() - t0
    run.load = os.getloadavg()[0]
    read_run(run)
    reach = run.first_reach()
    print(
        f"  exit {run.returncode} after {run.wall_s:.0f} s; "
        + (f"threshold at step {reach[0]}" if reach else "threshold not reached")
        + (f"; final eval {run.evals[-1][1]:.1f}" if run.evals else "; no evaluation logged"),
        flush=True,
    )
    return run


def _fmt(x: float | None, digits: int = 0) -> str:
    return "-" if x is None else f"{x:,.{digits}f}"


def _median(values: list[float]) -> float | None:
    return statistics.median(values) if values else None


def table(runs: list[Run]) -> str:
    lines = [
        "| preset (env, threshold) | seed | steps to threshold | s to threshold | stays from step"
        " | final eval | best eval | wall s | load |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for preset in dict.fromkeys(r.preset for r in runs):
        group = [r for r in runs if r.preset == preset]
        env, thr = PRESETS[preset]
        name = f"{preset} ({env}, >= {thr:g})"
        for r in group:
            reach = r.first_reach()
            failed = "" if r.returncode in (0, None) else f" (exit {r.returncode})"
            lines.append(
                f"| {name} | {r.seed}{failed} | {_fmt(reach[0] if reach else None)}"
                f" | {_fmt(reach[1] if reach else None)} | {_fmt(r.stays_from())}"
                f" | {_fmt(r.evals[-1][1] if r.evals else None, 1)}"
                f" | {_fmt(max(x for _, x, _ in r.evals) if r.evals else None, 1)}"
                f" | {_fmt(r.wall_s)} | {_fmt(r.load, 1)} |"
            )
        reached = [r.first_reach() for r in group]
        hits = [x for x in reached if x is not None]
        finals = [r.evals[-1][1] for r in group if r.evals]
        bests = [max(x for _, x, _ in r.evals) for r in group if r.evals]
        stays = [s for r in group if (s := r.stays_from()) is not None]
        walls = [r.wall_s for r in group if r.wall_s is not None]
        lines.append(
            f"| {name} | **median** ({len(hits)}/{len(group)} reached)"
            f" | {_fmt(_median([s for s, _ in hits]))}"
            f" | {_fmt(_median([t for _, t in hits if t is not None]))}"
            f" | {_fmt(_median(stays))} | {_fmt(_median(finals), 1)} | {_fmt(_median(bests), 1)}"
            f" | {_fmt(_median(walls))} | |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--presets", nargs="+", choices=sorted(PRESETS), default=None)
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument(
        "--root",
        type=Path,
        default=None,
        help="where the run dirs go (default: outputs/classic_control/<date-time>)",
    )
    parser.add_argument(
        "--read", type=Path, default=None, help="only read the runs under this root"
    )
    parser.add_argument("--out", type=Path, default=None, help="also write the table here")
    parser.add_argument(
        "--timeout", type=float, default=1800, help="seconds per run before it is killed"
    )
    parser.add_argument("extra", nargs="*", help="Hydra overrides for every run (key=value)")
    args = parser.parse_args(argv)

    presets = args.presets
    if presets is None:
        presets = list(PRESETS)
        if importlib.util.find_spec("Box2D") is None:
            presets = [p for p in presets if p not in NEEDS_BOX2D]
            print("Box2D is not installed: lunar_lander_ppo skipped (pip install 'rlexp[box2d]')")

    root = args.read or args.root
    if root is None:
        stamp = datetime.datetime.now().strftime("%Y-%m-%d_%H-%M-%S")
        root = REPO / "outputs" / "classic_control" / stamp
    runs = [Run(p, s, root.resolve() / p / f"seed{s}") for p in presets for s in args.seeds]
    if args.read:
        runs = [read_run(run) for run in runs]
    else:
        for run in runs:
            if (run.run_dir / "metrics.jsonl").exists():
                parser.error(
                    f"{run.run_dir} already holds a run (it would resume): pick another --root"
                )
        runs = [train(run, args.extra, args.timeout) for run in runs]
    text = table(runs)
    print(text)
    if args.out:
        args.out.write_text(text + "\n")
    return 0 if all(r.returncode in (0, None) and r.first_reach() for r in runs) else 1


if __name__ == "__main__":
    sys.exit(main())
