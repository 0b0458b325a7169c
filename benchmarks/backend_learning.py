"""PPO learning and launch-to-exit time on each env backend (#31): the same config
(``+experiment=mujoco_throughput``: 4 envs, 4096-step rollouts), tasks x seeds x backends, one run
after another, each ``python train.py`` timed from launch to exit; a markdown table per task.

Columns: launch to exit (median over seeds) and its speed-up over the first backend, the final
training return (mean of the last 100 episodes, as logged; mean +- std over seeds) and the last
evaluation's mean return (10 deterministic episodes; mean +- std over seeds). #31's target: EnvPool
>= 1.5x faster than the in-process backend, with learning within the seeds' spread.

    python benchmarks/backend_learning.py                                   # 12 runs of 1M steps
    python benchmarks/backend_learning.py --steps 20480 --seeds 1 --tasks hopper   # smoke, ~1 min
    python benchmarks/backend_learning.py --dry-run                         # the commands only
"""

from __future__ import annotations

import argparse
import json
import shlex
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def command(task: str, backend: str, seed: int, steps: int, run_dir: Path) -> list[str]:
    return [
        sys.executable,
        str(ROOT / "train.py"),
        f"env={task}",
        "+experiment=mujoco_throughput",
        f"env.backend={backend}",
        f"seed={seed}",
        f"trainer.total_frames={steps}",
        "trainer.progress=false",
        f"hydra.run.dir={run_dir}",
    ]


def outcome(run_dir: Path) -> tuple[float, float]:
    """The run's last ``train/episode_return`` and last ``eval/episode_return`` (NaN if none)."""
    train = evaluation = float("nan")
    for line in (run_dir / "metrics.jsonl").read_text().splitlines():
        row = json.loads(line)
        train = row.get("train/episode_return", train)
        evaluation = row.get("eval/episode_return", evaluation)
    return train, evaluation


def spread(values: list[float]) -> str:
    sd = statistics.stdev(values) if len(values) > 1 else 0.0
    return f"{statistics.mean(values):,.0f} +- {sd:,.0f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", nargs="+", default=["half_cheetah", "hopper"], help="conf/env")
    parser.add_argument("--backends", nargs="+", default=["gymnasium", "envpool"])
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    parser.add_argument("--steps", type=int, default=1_000_000, help="env steps per run")
    parser.add_argument("--runs", type=Path, help="keep the run dirs here (default: a temp dir)")
    parser.add_argument("--dry-run", action="store_true", help="print the commands and stop")
    args = parser.parse_args()
    root = args.runs or Path(tempfile.mkdtemp(prefix="backend_learning_"))
    results: dict[tuple[str, str], list[tuple[float, float, float]]] = {}
    for task in args.tasks:
        for seed in args.seeds:
            for backend in args.backends:  # alternate backends: load drifts hit both alike
                run_dir = root / f"{task}_{backend}_seed{seed}"
                cmd = command(task, backend, seed, args.steps, run_dir)
                if args.dry_run:
                    print(shlex.join(cmd))
                    continue
                start = time.perf_counter()
                with open(f"{run_dir}.log", "w") as log:
                    subprocess.run(cmd, cwd=root, stdout=log, stderr=subprocess.STDOUT, check=True)
                seconds = time.perf_counter() - start
                results.setdefault((task, backend), []).append((seconds, *outcome(run_dir)))
                print(f"{task} {backend} seed {seed}: {seconds:.0f} s", file=sys.stderr, flush=True)
    if args.dry_run:
        return
    print(
        f"\n{args.steps:,} env steps, +experiment=mujoco_throughput, seeds {args.seeds}; runs {root}"
    )
    for task in args.tasks:
        base = statistics.median(r[0] for r in results[(task, args.backends[0])])
        print(f"\n### {task}\n")
        print("| backend | launch to exit, s (median) | speed-up | final train return "
              "| last eval return |")  # fmt: skip
        print("|---|---:|---:|---:|---:|")
        for backend in args.backends:
            rows = results[(task, backend)]
            seconds = statistics.median(r[0] for r in rows)
            print(
                f"| {backend} | {seconds:,.0f} | {base / seconds:.2f}x | "
                f"{spread([r[1] for r in rows])} | {spread([r[2] for r in rows])} |"
            )


if __name__ == "__main__":
    main()
