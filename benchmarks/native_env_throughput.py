"""Env-steps/s of the native batched env against raw MuJoCo stepping of the same model.

For each N: (a) raw physics: ``mujoco.rollout`` advancing N states by ``substeps`` physics steps per
env step, with the same thread pool and controls held fixed (no Python per step besides the call);
(b) the env through TorchRL's ``step_and_maybe_reset`` with uniform random actions (observations,
rewards, auto-resets included). Prints a markdown table; the target is env >= 70% of raw at N = 64.

    PYTHONPATH=src python benchmarks/native_env_throughput.py [--task push_cube] [--sizes 1 16 64 256]
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import mujoco
import numpy as np
import torch
from mujoco import rollout

from rlexp.envs.native import default_task_config, make_native_env


def raw_physics_step(env):
    """One env-step of bare mujoco.rollout on the env's model, state size and thread count."""
    n, m = env.num_envs, env.model
    state = env._state.copy()
    control = np.repeat(env._ctrl[:, None, :], env.substeps, axis=1)
    traj = np.zeros((n, env.substeps, state.shape[1]))
    sens = np.zeros((n, env.substeps, m.nsensordata))
    models = [m] * n
    datas = [mujoco.MjData(m) for _ in range(max(1, env.num_threads))]
    chunk = max(1, n // (max(1, env.num_threads) * 4))
    pool = rollout.Rollout(nthread=env.num_threads)

    def step() -> None:
        pool.rollout(
            models, datas, state, control,
            control_spec=mujoco.mjtState.mjSTATE_CTRL.value, skip_checks=True,
            nstep=env.substeps, state=traj, sensordata=sens, chunk_size=chunk,
        )  # fmt: skip
        state[:] = traj[:, -1]

    return step, pool


def env_step(env):
    """One env-step through ``step_and_maybe_reset`` with uniform random actions."""
    td = env.reset()
    shape = env.action_spec.shape

    def step() -> None:
        nonlocal td
        td.set("action", torch.rand(shape) * 2 - 1)
        _, td = env.step_and_maybe_reset(td)

    return step


def measure(steps: dict, n: int, seconds: float, windows: int = 8) -> dict[str, float]:
    """Env-steps/s of each step function: best of ``windows`` short windows, taken in turns so that
    both see the same machine load (other processes on a small machine skew one-off timings)."""
    for step in steps.values():
        for _ in range(20):  # warm-up
            step()
    best = dict.fromkeys(steps, 0.0)
    for _ in range(windows):
        for name, step in steps.items():
            count, start = 0, time.perf_counter()
            while time.perf_counter() - start < seconds / windows:
                step()
                count += 1
            best[name] = max(best[name], count * n / (time.perf_counter() - start))
    return best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--task", default="push_cube", choices=["push_cube", "cart_pole"])
    parser.add_argument("--sizes", type=int, nargs="+", default=[1, 16, 64, 256])
    parser.add_argument("--seconds", type=float, default=3.0, help="measuring time per cell")
    parser.add_argument(
        "--threads", type=int, default=None, help="physics threads (default: env's choice)"
    )
    args = parser.parse_args()
    torch.set_num_threads(1)
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    print(
        f"task={args.task} cpu={platform.processor() or platform.machine()} cores={cores} "
        f"mujoco={mujoco.__version__} torch={torch.__version__}\n"
    )
    print(
        "| N | threads | raw physics env-steps/s | env step_and_maybe_reset env-steps/s | env / raw |"
    )
    print("|---:|---:|---:|---:|---:|")
    for n in args.sizes:
        env = make_native_env(default_task_config(args.task), n, seed=0, num_threads=args.threads)
        raw_step, pool = raw_physics_step(env)
        rates = measure({"raw": raw_step, "env": env_step(env)}, n, args.seconds)
        raw, ours = rates["raw"], rates["env"]
        pool.close()
        print(
            f"| {n} | {env.num_threads} | {raw:,.0f} | {ours:,.0f} | {ours / raw:.0%} |", flush=True
        )
        env.close()


if __name__ == "__main__":
    main()
