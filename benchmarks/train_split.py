"""Where the time of one PPO iteration goes: env stepping, policy, framework, GAE, update.

Runs the real rlexp components (the env, the sampling policy, RolloutCollector, GAE, ClipPPOLoss,
built from the same composed config as ``benchmarks/ppo_throughput.py``'s settings) for a few
iterations and times each part; physics and policy are also timed alone so the "framework" share
(TensorDict / collector bookkeeping) is what is left of collection.

    .venv/bin/python benchmarks/train_split.py [--setting standard|batched] [--iterations 5]
        [--compile true|false] [--collector rlexp|torchrl]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--setting", choices=["standard", "batched"], default="standard")
    parser.add_argument("--iterations", type=int, default=5)
    parser.add_argument("--steps-per-env", type=int, default=0, help="override the batch length")
    parser.add_argument(
        "--compile", choices=["auto", "true", "false"], default="false", help="algorithm.compile"
    )
    parser.add_argument(
        "--collector",
        choices=["rlexp", "torchrl"],
        default="rlexp",
        help="rlexp's RolloutCollector or TorchRL's generic Collector loop",
    )
    args = parser.parse_args()

    torch.set_num_threads(1)
    torch.manual_seed(0)
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from dataclasses import asdict

    from ppo_throughput import SETTINGS, Setting, compose

    from rlexp.algorithms.ppo import make_algorithm
    from rlexp.common import speedups as _speedups
    from rlexp.envs.factory import make_env
    from rlexp.policies.actor_critic import make_policy
    from rlexp.training.collector import RolloutCollector

    _speedups.apply()
    s = SETTINGS[args.setting]
    if args.steps_per_env:
        s = Setting(**{**asdict(s), "steps_per_env": args.steps_per_env})
    config = compose(s, 100, 1, 0, [f"algorithm.compile={args.compile}"])
    env = make_env(config.env, config.env.num_envs, seed=0)
    obs_dim, act_dim = env.observation_spec["observation"].shape[-1], env.action_spec.shape[-1]
    policy = make_policy(config.policy, obs_dim, act_dim, env.action_spec)
    algo = make_algorithm(config.algorithm, policy, 100)
    from torchrl.collectors import Collector

    cls = RolloutCollector if args.collector == "rlexp" else Collector
    frames = config.trainer.frames_per_batch
    collector = cls(
        env,
        policy.sampling_policy(),
        frames_per_batch=frames,
        total_frames=-1,
        trust_policy=True,
        track_traj_ids=False,
    )
    rollouts = iter(collector)
    algo.update(next(rollouts))  # warm-up (and the compile, if on)

    t_collect, t_gae, t_update = [], [], []
    for _ in range(args.iterations):
        t0 = time.perf_counter()
        batch = next(rollouts)
        t1 = time.perf_counter()
        algo.compute_advantages(batch)
        t2 = time.perf_counter()
        algo.update(batch)  # runs GAE again inside; subtract it below
        t3 = time.perf_counter()
        policy.normalizer.update(batch["observation"])
        t_collect.append(t1 - t0)
        t_gae.append(t2 - t1)
        t_update.append(t3 - t2 - (t2 - t1))

    # Physics alone: the env's own step on random actions, no collector, no policy.
    n_envs = config.env.num_envs
    steps = frames // n_envs
    base = make_env(config.env, n_envs, seed=1)
    base.reset()
    low, high = base.action_spec.space.low, base.action_spec.space.high
    actions = [low + (high - low) * torch.rand_like(low) for _ in range(16)]
    t0 = time.perf_counter()
    for i in range(steps):
        nxt = base.step_action(actions[i % 16])
        base.autoreset_observation(nxt)
    t_env = time.perf_counter() - t0
    # Policy alone: the collector's sampling function on one observation batch at a time.
    sample = policy.sampling_policy().sampler()
    obs = torch.zeros(n_envs, obs_dim)
    with torch.no_grad():
        t0 = time.perf_counter()
        for _ in range(steps):
            sample(obs)
        t_pol = time.perf_counter() - t0

    c, g, u = (float(np.median(x)) for x in (t_collect, t_gae, t_update))
    framework = max(c - t_env - t_pol, 0.0)
    total = c + g + u
    print(
        f"{args.setting}: {config.env.name} x{n_envs}, {frames} steps/iteration, "
        f"{args.collector} collector, compile={args.compile} (compiled: {algo.compiled}), "
        f"median of {args.iterations}"
    )
    print("| part | s / iteration | share |\n|---|---|---|")
    for name, v in (
        ("env stepping (physics alone)", t_env),
        ("policy forward", t_pol),
        ("collector/TensorDict framework", framework),
        ("GAE", g),
        ("PPO update", u),
    ):
        print(f"| {name} | {v:.3f} | {100 * v / total:.0f}% |")
    print(f"| **total** | {total:.3f} | env-steps/s {frames / total:.0f} |")
    collector.shutdown()


if __name__ == "__main__":
    main()
