"""Batched envs and scale (#31): collection env-steps/s of HalfCheetah-v5 at 1, 8 and 64 envs on each
CPU backend, through rlexp's ``RolloutCollector`` with the default policy (64x64 tanh MLP, one torch
thread), next to raw EnvPool stepping at the same settings; a markdown table.

Rows: ``gymnasium`` (the copies one after another in the training process), ``gymnasium_async``
(a worker process per copy), ``envpool`` at 1 and 2 threads (``env.num_threads``), and raw
``envpool.make_gymnasium(...).step`` at 1 and 2 threads (uniform random actions drawn beforehand,
EnvPool's own autoreset: no policy, no tensors), and rlexp's envpool rows as a fraction of raw
EnvPool at the same thread count (#31's target: >= 0.8 at 8 and 64 envs).

A measurement: rollouts of ``--frames`` env steps over all envs (rounded to a multiple of the env
count), one warm-up, the median of ``--rounds`` timed ones (wall clock around ``next(collector)``).
A cell: the median of ``--repeats`` measurements, taken round-robin over the cells of an env count
(so that load coming and going on the machine hits each alike).

    python benchmarks/env_scale.py                       # ~10 min on 2 cores
    python benchmarks/env_scale.py --envs 1 8 --rounds 3 --backends envpool raw
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BACKENDS = ("gymnasium", "gymnasium_async", "envpool", "raw")


def collection_rate(backend: str, num_envs: int, threads: int, frames: int, rounds: int) -> float:
    """Env-steps/s of rlexp's collector on ``backend`` (median of ``rounds`` rollouts)."""
    import torch

    from rlexp.config.schema import EnvConfig, PolicyConfig
    from rlexp.envs.factory import make_env
    from rlexp.policies.actor_critic import policy_for_env
    from rlexp.training.collector import RolloutCollector

    cfg = EnvConfig(name="HalfCheetah-v5", backend=backend, num_envs=num_envs, num_threads=threads)
    torch.manual_seed(0)
    env = make_env(cfg, num_envs, seed=0)
    try:
        policy = policy_for_env(PolicyConfig(), cfg, env)
        collector = RolloutCollector(
            env, policy.sampling_policy(), frames_per_batch=frames, total_frames=-1
        )
        rollouts = iter(collector)
        next(rollouts)  # warm-up
        times = []
        for _ in range(rounds):
            start = time.perf_counter()
            next(rollouts)
            times.append(time.perf_counter() - start)
        collector.shutdown()
    finally:
        env.close()
    return frames / statistics.median(times)


def raw_envpool_rate(num_envs: int, threads: int, frames: int, rounds: int) -> float:
    """Env-steps/s of EnvPool's own ``step`` (synchronous, every env each call)."""
    import envpool
    import numpy as np

    pool = envpool.make_gymnasium(
        "HalfCheetah-v5", num_envs=num_envs, batch_size=num_envs, num_threads=threads, seed=0
    )
    steps = frames // num_envs
    actions = np.random.default_rng(0).uniform(-1, 1, (steps, num_envs, 6))
    pool.reset()
    times = []
    for i in range(rounds + 1):
        start = time.perf_counter()
        for t in range(steps):
            pool.step(actions[t])
        if i:  # the first is the warm-up
            times.append(time.perf_counter() - start)
    pool.close()
    return frames / statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--envs", type=int, nargs="+", default=[1, 8, 64], help="env counts")
    parser.add_argument("--backends", nargs="+", default=list(BACKENDS), choices=BACKENDS)
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2], help="EnvPool threads")
    parser.add_argument("--frames", type=int, default=4096, help="env steps per rollout")
    parser.add_argument("--rounds", type=int, default=3, help="timed rollouts per measurement")
    parser.add_argument("--repeats", type=int, default=3, help="measurements per cell (median)")
    args = parser.parse_args()
    sys.path.insert(0, str(ROOT / "src"))
    import torch

    from rlexp.common import speedups as _speedups
    from rlexp.config.rules import available_cpus

    torch.set_num_threads(1)
    _speedups.apply()
    rows: dict[str, dict[int, float]] = {}
    for n in args.envs:
        frames = max(n, args.frames // n * n)
        cells = []  # (label, measure): every cell of this env count, measured round-robin
        for backend in args.backends:
            for threads in args.threads if backend in ("envpool", "raw") else [0]:
                if threads > n:
                    continue
                name = {"raw": "raw EnvPool step", "gymnasium": "rlexp gymnasium (in-process)"}
                label = name.get(backend, f"rlexp {backend}")
                label += f", {threads} thread{'s' * (threads > 1)}" if threads else ""
                if backend == "raw":
                    cells.append((label, (raw_envpool_rate, n, threads, frames, args.rounds)))
                else:
                    cells.append(
                        (label, (collection_rate, backend, n, threads, frames, args.rounds))
                    )
        rates: dict[str, list[float]] = {}
        for _ in range(args.repeats):  # load that comes and goes hits every cell alike
            for label, (measure, *params) in cells:
                rates.setdefault(label, []).append(measure(*params))
                print(f"{label}, {n} envs: {rates[label][-1]:,.0f} env-steps/s", file=sys.stderr)
        for label, values in rates.items():
            rows.setdefault(label, {})[n] = statistics.median(values)
    for threads in args.threads:
        ours, raw = (
            rows.get(f"rlexp envpool, {threads} thread{'s' * (threads > 1)}"),
            rows.get(f"raw EnvPool step, {threads} thread{'s' * (threads > 1)}"),
        )
        if ours and raw:
            rows[f"rlexp envpool / raw, {threads} thread{'s' * (threads > 1)}"] = {
                n: ours[n] / raw[n] for n in ours if n in raw
            }
    print(
        f"\nHalfCheetah-v5, env-steps/s: median of {args.repeats} measurements taken round-robin, "
        f"each the median of {args.rounds} rollouts of ~{args.frames} steps ({available_cpus()} "
        "CPUs, torch threads 1)\n"
    )
    print("| | " + " | ".join(f"{n} env{'s' * (n > 1)}" for n in args.envs) + " |")
    print("|---|" + "---:|" * len(args.envs))
    for label, cells in rows.items():
        fmt = "{:.2f}" if "/ raw" in label else "{:,.0f}"
        print(
            f"| {label} | "
            + " | ".join(fmt.format(cells[n]) if n in cells else "" for n in args.envs)
            + " |"
        )


if __name__ == "__main__":
    main()
