"""How EnvPool's MuJoCo tasks relate to Gymnasium's (#31, docs/envs.md "Vectorised backends"):
spaces, the same trajectory from the same start, and random-action statistics; markdown tables.

1. Spaces: observation and action shapes, dtypes and bounds of each task on both.
2. Same start, same actions: both built with ``reset_noise_scale=0`` (the initial state is the
   model's own, no RNG), then one fixed sequence of uniform random actions in the box (seed 0) until
   the episode ends (1000 steps or a termination): the largest absolute observation and reward
   differences by step, and both returns and lengths. Differences come from the physics builds
   (EnvPool links its own MuJoCo; Gymnasium uses the ``mujoco`` package) and the task code.
3. Random actions, default reset noise: ``--episodes`` episodes on each (their own RNGs), the mean
   and standard deviation of the return, the length and the per-step reward.

    python benchmarks/envpool_vs_gymnasium.py                  # ~1 min on 2 cores
    python benchmarks/envpool_vs_gymnasium.py --tasks Hopper-v5 --episodes 20
"""

from __future__ import annotations

import argparse

import envpool
import gymnasium as gym
import mujoco
import numpy as np


def spaces_row(task: str) -> str:
    g = gym.make(task)
    e = envpool.make_gymnasium(task, num_envs=1)
    go, eo, ga, ea = g.observation_space, e.observation_space, g.action_space, e.action_space
    same = (
        go.shape == eo.shape
        and np.array_equal(ga.low, ea.low)
        and np.array_equal(ga.high, ea.high)
        and ga.shape == ea.shape
    )
    row = (
        f"| {task} | {go.shape} {go.dtype} / {eo.shape} {eo.dtype} | {ga.shape} "
        f"[{ga.low.min():g}, {ga.high.max():g}] {ga.dtype} / {ea.shape} [{ea.low.min():g}, "
        f"{ea.high.max():g}] {ea.dtype} | {'same shapes and bounds' if same else 'DIFFER'} |"
    )
    g.close(), e.close()
    return row


def same_start_row(task: str) -> str:
    """Both from the noiseless initial state under one action sequence."""
    g = gym.make(task, reset_noise_scale=0.0)
    e = envpool.make_gymnasium(task, num_envs=1, reset_noise_scale=0.0)
    go, _ = g.reset(seed=0)
    eo, _ = e.reset()
    low, high = g.action_space.low, g.action_space.high
    actions = np.random.default_rng(0).uniform(low, high, (1000, *low.shape))
    gap = {0: float(np.abs(go - eo[0]).max())}
    rgap, ret_g, ret_e, t, end_g, end_e = 0.0, 0.0, 0.0, 0, "", ""
    for t, a in enumerate(actions, start=1):
        go, gr, gterm, gtrunc, _ = g.step(a)
        eo, er, eterm, etrunc, _ = e.step(a[None])
        ret_g, ret_e = ret_g + gr, ret_e + float(er[0])
        rgap = max(rgap, abs(gr - float(er[0])))
        gap[t] = float(np.abs(go - eo[0]).max())
        end_g = "terminated" if gterm else "truncated" if gtrunc else ""
        end_e = "terminated" if eterm[0] else "truncated" if etrunc[0] else ""
        if end_g or end_e:
            break
    ends = f"{end_g or 'running'} / {end_e or 'running'} at step {t}"
    marks = " | ".join(f"{gap[m]:.1e}" if m in gap else "" for m in (0, 1, 10, 100))
    marks += f" | {gap[t]:.1e} (step {t})"
    g.close(), e.close()
    return f"| {task} | {marks} | {rgap:.1e} | {ret_g:.2f} / {ret_e:.2f} | {ends} |"


def random_episodes(task: str, episodes: int) -> str:
    """Returns, lengths and per-step rewards of random-action episodes on both."""
    out = []
    for backend in ("Gymnasium", "EnvPool"):
        rng = np.random.default_rng(1)
        if backend == "Gymnasium":
            env = gym.make(task)
            env.reset(seed=1)
            low, high = env.action_space.low, env.action_space.high
        else:
            env = envpool.make_gymnasium(task, num_envs=1, seed=1)
            env.reset()
            low, high = env.action_space.low, env.action_space.high
        returns, lengths, rewards = [], [], []
        for _ in range(episodes):
            total, steps, done = 0.0, 0, False
            while not done:
                a = rng.uniform(low, high)
                if backend == "Gymnasium":
                    _, r, term, trunc, _ = env.step(a)
                else:
                    _, r, term, trunc, _ = env.step(a[None])
                    r, term, trunc = float(r[0]), bool(term[0]), bool(trunc[0])
                total, steps, done = total + r, steps + 1, term or trunc
                rewards.append(r)
            returns.append(total)
            lengths.append(steps)
            if backend == "Gymnasium":
                env.reset()
            else:
                env.step(np.zeros((1, *low.shape)))  # EnvPool resets at the next step
        env.close()
        out.append(
            f"| {task} | {backend} | {np.mean(returns):.1f} +- {np.std(returns):.1f} | "
            f"{np.mean(lengths):.1f} +- {np.std(lengths):.1f} | "
            f"{np.mean(rewards):.4f} +- {np.std(rewards):.4f} |"
        )
    return "\n".join(out)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--tasks", nargs="+", default=["HalfCheetah-v5", "Hopper-v5", "Walker2d-v5"]
    )
    parser.add_argument("--episodes", type=int, default=50, help="random-action episodes each")
    args = parser.parse_args()
    print(
        f"envpool {envpool.__version__} (its own MuJoCo build), gymnasium {gym.__version__} with "
        f"mujoco {mujoco.__version__}\n"
    )
    print("| task | observation: Gymnasium / EnvPool | action: Gymnasium / EnvPool | |")
    print("|---|---|---|---|")
    for task in args.tasks:
        print(spaces_row(task))
    print("\nSame start (reset_noise_scale=0), same actions: max |obs difference| after step N\n")
    print("| task | reset | 1 | 10 | 100 | last step | max reward difference "
          "| return Gymnasium / EnvPool | episode end Gymnasium / EnvPool |")  # fmt: skip
    print("|---|---:|---:|---:|---:|---:|---:|---|---|")
    for task in args.tasks:
        print(same_start_row(task))
    print(f"\nRandom actions, default reset noise, {args.episodes} episodes each\n")
    print("| task | backend | return | length | reward per step |")
    print("|---|---|---:|---:|---:|")
    for task in args.tasks:
        print(random_episodes(task, args.episodes))


if __name__ == "__main__":
    main()
