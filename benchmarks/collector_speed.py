"""Collection alone: env-steps/s of rlexp's ``RolloutCollector`` on one task (default HalfCheetah-v5,
1 env, 2048-step rollouts, the default 64x64 policy), median over rounds, one torch thread.

Used to check that a change to the Gymnasium adapter, the policy heads or the collector does not slow
collection down (issue #28: run before and after, rows in ``benchmarks/results.md``)::

    .venv/bin/python benchmarks/collector_speed.py [--env half_cheetah] [--rounds 7]
        [--override env.name=CartPole-v1 ...]

Before / after a change: ``--baseline DIR`` (a checkout of the older commit, e.g. ``git worktree add
/tmp/base <commit>``) runs the two source trees alternately, ``--pairs`` times each, every run in a
process of its own, and prints a markdown row per tree (median of the runs' medians, best run).
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="half_cheetah", help="a conf/env option")
    parser.add_argument("--rounds", type=int, default=7, help="timed rollouts (after one warm-up)")
    parser.add_argument("--steps", type=int, default=2048, help="env steps per rollout")
    parser.add_argument("--override", nargs="*", default=[], help="more Hydra overrides")
    parser.add_argument("--src", default=str(HERE.parents[1] / "src"), help="rlexp's source tree")
    parser.add_argument("--baseline", help="another checkout to compare with (runs alternate)")
    parser.add_argument("--pairs", type=int, default=5, help="runs of each tree with --baseline")
    parser.add_argument("--json", action="store_true", help="print the run's times as JSON")
    args = parser.parse_args()
    if args.baseline:
        compare(args)
        return

    import torch

    torch.set_num_threads(1)
    sys.path.insert(0, args.src)
    from hydra import compose, initialize_config_dir

    from rlexp.common import speedups as _speedups
    from rlexp.config.paths import CONF_DIR
    from rlexp.config.schema import register_configs
    from rlexp.config.validate import to_root_config
    from rlexp.envs.factory import make_env
    from rlexp.policies.actor_critic import policy_for_env
    from rlexp.training.collector import RolloutCollector

    _speedups.apply()
    register_configs()
    overrides = [f"env={args.env}", "env.num_envs=1", *args.override]
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        config = to_root_config(compose(config_name="config", overrides=overrides))
    torch.manual_seed(0)
    env = make_env(config.env, 1, seed=0)
    policy = policy_for_env(config.policy, config.env, env)
    collector = RolloutCollector(
        env, policy.sampling_policy(), frames_per_batch=args.steps, total_frames=-1
    )
    rollouts = iter(collector)
    next(rollouts)  # warm-up
    times = []
    for _ in range(args.rounds):
        t0 = time.perf_counter()
        next(rollouts)
        times.append(time.perf_counter() - t0)
    collector.shutdown()
    med = statistics.median(times)
    if args.json:
        print(json.dumps({"median": med, "min": min(times), "env": config.env.name}))
        return
    print(
        f"{config.env.name}: {args.steps} steps per rollout, median {med * 1e3:.1f} ms "
        f"({args.steps / med:,.0f} env-steps/s; min {min(times) * 1e3:.1f} ms, "
        f"max {max(times) * 1e3:.1f} ms, {args.rounds} rounds)"
    )


def compare(args: argparse.Namespace) -> None:
    """This tree and ``--baseline`` alternately; a markdown table of env-steps/s."""
    trees = {"this checkout": str(HERE.parents[1] / "src"), "baseline": f"{args.baseline}/src"}
    runs: dict[str, list[dict]] = {name: [] for name in trees}
    for _ in range(args.pairs):
        for name, src in trees.items():
            cmd = [sys.executable, str(HERE), "--json", "--src", src, "--env", args.env,
                   "--rounds", str(args.rounds), "--steps", str(args.steps),
                   "--override", *args.override]  # fmt: skip
            out = subprocess.run(cmd, capture_output=True, text=True, check=True, timeout=600)
            runs[name].append(json.loads(out.stdout.strip().splitlines()[-1]))
    print(f"| {args.env}, {args.steps}-step rollouts | env-steps/s (median of {args.pairs} runs) "
          "| best run | ms per rollout (median) |")  # fmt: skip
    print("|---|---:|---:|---:|")
    for name, rows in runs.items():
        med = statistics.median(r["median"] for r in rows)
        best = min(r["min"] for r in rows)
        print(f"| {name} | {args.steps / med:,.0f} | {args.steps / best:,.0f} | {med * 1e3:.1f} |")


if __name__ == "__main__":
    main()
