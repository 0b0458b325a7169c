"""What each tuned preset costs in wall time against the defaults (issue #34, docs/results.md,
"What each preset costs"): per MuJoCo task, the default config and ``+experiment=tuned`` train the
same number of env steps, one run at a time (never two at once: the numbers are wall seconds), and
the table gives each one's training seconds per 1M env steps and the ratio.

    python benchmarks/preset_cost.py                           # 9 tasks x 2 configs, ~10 min here
    python benchmarks/preset_cost.py --tasks hopper ant --steps 20480
    python benchmarks/preset_cost.py --out /tmp/cost.md

Each run is ``python train.py env=<task> [+experiment=tuned] trainer.total_frames=<steps>`` with no
evaluation, no checkpoint, no logger and the loss not compiled (``algorithm.compile=false``: a 1M
run compiles it, a short one would not pay the compile back), in a fresh temporary run dir. The time
is the training loop's own: from the first to the last row of ``metrics.jsonl`` (each row's
``time``), so that imports, env construction and the first rollout's start-up are left out, divided
by the env steps between those rows and scaled to 1M. A preset with smaller rollouts (512 steps:
HalfCheetah's, Humanoid's, Reacher's) has more iterations in the same steps; each iteration's fixed
costs are in the number.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def suite_tasks() -> list[str]:
    """The tuned suite's tasks, as ``conf/sweep/tuned_1m.yaml`` sweeps them."""
    from omegaconf import OmegaConf

    params = OmegaConf.load(REPO / "conf/sweep/tuned_1m.yaml").hydra.sweeper.params
    return str(params.env).split(",")


TASKS = suite_tasks()


def seconds_per_million(task: str, tuned: bool, steps: int, root: Path) -> float:
    """Training seconds per 1M env steps of one run (the first to the last metrics row)."""
    run_dir = root / f"{task}_{'tuned' if tuned else 'default'}"
    args = [
        sys.executable,
        str(REPO / "train.py"),
        f"env={task}",
        *(["+experiment=tuned"] if tuned else []),
        f"trainer.total_frames={steps}",
        "trainer.eval_every=0",
        "trainer.save_every=0",
        "trainer.progress=false",
        "trainer.device=cpu",
        "logger=none",
        "algorithm.compile=false",
        f"hydra.run.dir={run_dir}",
    ]
    subprocess.run(args, cwd=root, check=True, capture_output=True)
    rows = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    rows = [r for r in rows if "time" in r and "loss/policy" in r]  # the training rows
    first, last = rows[0], rows[-1]
    return (last["time"] - first["time"]) / (last["step"] - first["step"]) * 1_000_000


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", nargs="+", default=TASKS, choices=TASKS)
    parser.add_argument("--steps", type=int, default=61_440, help="env steps per run")
    parser.add_argument("--out", type=Path, default=None, help="also write the table here")
    args = parser.parse_args(argv)
    lines = [
        f"Training seconds per 1M env steps, from {args.steps:,}-step runs (eager, no eval), one "
        "at a time",
        "",
        "| task | default (s / 1M) | tuned preset (s / 1M) | tuned / default |",
        "|---|---:|---:|---:|",
    ]
    with tempfile.TemporaryDirectory(prefix="rlexp-preset-cost-") as tmp:
        for task in args.tasks:
            default = seconds_per_million(task, False, args.steps, Path(tmp))
            tuned = seconds_per_million(task, True, args.steps, Path(tmp))
            lines.append(f"| {task} | {default:,.0f} | {tuned:,.0f} | {tuned / default:.2f}x |")
            print(lines[-1], flush=True)
    text = "\n".join(lines) + "\n"
    print("\n" + text)
    if args.out is not None:
        args.out.write_text(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
