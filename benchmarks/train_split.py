"""Where the time of one PPO iteration goes: env stepping, policy, framework, GAE, update.

Runs the real rlexp components (GymnasiumEnv, SamplingPolicy, RolloutCollector, GAE, ClipPPOLoss)
for a few iterations and times each part; physics and policy are also timed alone so the
"framework" share (TensorDict / collector bookkeeping) is what is left of collection.

    .venv/bin/python benchmarks/train_split.py [--env HalfCheetah-v5] [--iterations 5]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--env", default="HalfCheetah-v5")
    parser.add_argument("--num-envs", type=int, default=1)
    parser.add_argument("--frames-per-batch", type=int, default=2048)
    parser.add_argument("--iterations", type=int, default=5)
    parser.add_argument("--epochs", type=int, default=10)
    parser.add_argument("--mini-batch", type=int, default=64)
    parser.add_argument(
        "--collector",
        choices=["rlexp", "torchrl"],
        default="rlexp",
        help="rlexp's RolloutCollector or TorchRL's generic Collector loop",
    )
    args = parser.parse_args()

    torch.set_num_threads(1)
    torch.manual_seed(0)
    from rlexp import _speedups
    from rlexp.algorithms.ppo import make_algorithm
    from rlexp.collector import RolloutCollector
    from rlexp.config.schema import AlgorithmConfig, EnvConfig, PolicyConfig
    from rlexp.envs.factory import make_env
    from rlexp.policies.actor_critic import make_policy

    _speedups.apply()
    env = make_env(EnvConfig(name=args.env), args.num_envs, seed=0)
    obs_dim, act_dim = env.observation_spec["observation"].shape[-1], env.action_spec.shape[-1]
    policy = make_policy(PolicyConfig(), obs_dim, act_dim, env.action_spec)
    algo = make_algorithm(
        AlgorithmConfig(num_epochs=args.epochs, mini_batch_size=args.mini_batch), policy, 100
    )
    from torchrl.collectors import Collector

    cls = RolloutCollector if args.collector == "rlexp" else Collector
    collector = cls(
        env,
        policy.sampling_policy(),
        frames_per_batch=args.frames_per_batch,
        total_frames=-1,
        trust_policy=True,
        track_traj_ids=False,
    )
    rollouts = iter(collector)
    next(rollouts)  # warm-up

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

    # Physics alone: the same Gymnasium env, random actions, no TorchRL.
    import gymnasium as gym

    raw = gym.make(args.env)
    raw.reset(seed=0)
    a = raw.action_space.sample()
    n = args.frames_per_batch
    t0 = time.perf_counter()
    for _ in range(n):
        _, _, term, trunc, _ = raw.step(a)
        if term or trunc:
            raw.reset()
    t_env = (time.perf_counter() - t0) / n * args.frames_per_batch
    # Policy alone: the sampling policy's forward on one observation at a time, as in collection.
    from tensordict import TensorDict

    sp = policy.sampling_policy()
    td = TensorDict(
        {"observation": torch.zeros(args.num_envs, obs_dim)}, batch_size=[args.num_envs]
    )
    with torch.no_grad():
        t0 = time.perf_counter()
        for _ in range(n // args.num_envs):
            sp(td)
        t_pol = time.perf_counter() - t0

    c, g, u = (float(np.median(x)) for x in (t_collect, t_gae, t_update))
    framework = max(c - t_env - t_pol, 0.0)
    total = c + g + u
    print(
        f"{args.env} x{args.num_envs}, {args.frames_per_batch} steps/iteration, {args.collector} collector, "
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
    print(f"| **total** | {total:.3f} | env-steps/s {args.frames_per_batch / total:.0f} |")
    collector.shutdown()


if __name__ == "__main__":
    main()
