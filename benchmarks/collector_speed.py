"""Collection alone: env-steps/s of rlexp's ``RolloutCollector`` on one task (default HalfCheetah-v5,
1 env, 2048-step rollouts, the default 64x64 policy), median over rounds, one torch thread.

Used to check that a change to the Gymnasium adapter, the policy heads or the collector does not slow
collection down (issue #28: run before and after, rows in ``benchmarks/results.md``)::

    .venv/bin/python benchmarks/collector_speed.py [--env half_cheetah] [--rounds 7]
        [--override env.name=CartPole-v1 ...]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="half_cheetah", help="a conf/env option")
    parser.add_argument("--rounds", type=int, default=7, help="timed rollouts (after one warm-up)")
    parser.add_argument("--steps", type=int, default=2048, help="env steps per rollout")
    parser.add_argument("--override", nargs="*", default=[], help="more Hydra overrides")
    args = parser.parse_args()

    import torch

    torch.set_num_threads(1)
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))
    from hydra import compose, initialize_config_dir

    from rlexp import _speedups
    from rlexp.collector import RolloutCollector
    from rlexp.config.schema import register_configs
    from rlexp.config.validate import to_root_config
    from rlexp.envs.factory import make_env
    from rlexp.paths import CONF_DIR
    from rlexp.policies.actor_critic import policy_for_env

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
    print(
        f"{config.env.name}: {args.steps} steps per rollout, median {med * 1e3:.1f} ms "
        f"({args.steps / med:,.0f} env-steps/s; min {min(times) * 1e3:.1f} ms, "
        f"max {max(times) * 1e3:.1f} ms, {args.rounds} rounds)"
    )


if __name__ == "__main__":
    main()
