"""Collection speed of a batched torch env through rlexp's adapters (issue #31), against the env
stepped by hand with the same policy: what the adapter and the collector cost per step.

The env is the tests' toy (``tests/batched_toy.py``: point masses, physics in torch), through both
contracts. For each device and number of envs, env-steps/s (all envs' steps, per wall second) of:

- ``raw env``: ``ToyVecEnv.step`` on random actions, nothing else;
- ``raw + policy``: a hand loop of the 64x64 policy's sampler and ``ToyVecEnv.step``;
- ``vecenv``: rlexp's collector (its lean loop) over ``VecEnvAdapter`` (rollouts of 32 steps);
- ``torchrl``: the same over ``TorchRLAdapter`` (TorchRL's ``step_and_maybe_reset`` inside).

    python benchmarks/batched_throughput.py                      # cpu (and cuda when visible)
    python benchmarks/batched_throughput.py --envs 64 4096 --devices cuda
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))


def _rate(fn, steps: int, envs: int, repeats: int = 3) -> float:
    fn(steps // 4)  # warm-up
    best = 0.0
    for _ in range(repeats):
        if torch.cuda.is_available():
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        fn(steps)
        if torch.cuda.is_available():
            torch.cuda.synchronize()
        best = max(best, steps * envs / (time.perf_counter() - t0))
    return best


def measure(envs: int, device: str, steps: int) -> dict[str, float]:
    from batched_toy import ToyTorchRLEnv, ToyVecEnv

    from rlexp.config.schema import EnvConfig, PolicyConfig
    from rlexp.envs.torchrl_env import TorchRLAdapter
    from rlexp.envs.vecenv import VecEnvAdapter
    from rlexp.policies.actor_critic import policy_for_env
    from rlexp.training.collector import RolloutCollector

    raw = ToyVecEnv(envs, device, seed=0)
    adapter = VecEnvAdapter(ToyVecEnv(envs, device, seed=0), "toy")
    policy = policy_for_env(PolicyConfig(), EnvConfig(), adapter).to(device)
    sampling = policy.sampling_policy()

    def raw_env(n: int) -> None:
        for _ in range(n):
            raw.step(torch.rand(envs, 2, device=device) * 2 - 1)

    @torch.no_grad()
    def raw_policy(n: int) -> None:
        sample, obs = sampling.sampler(), raw.get_observations()
        for _ in range(n):
            obs = raw.step(sample(obs)[-2])[0]

    out = {"raw env": _rate(raw_env, steps, envs), "raw + policy": _rate(raw_policy, steps, envs)}
    torchrl = TorchRLAdapter(ToyTorchRLEnv(envs, device, seed=0), "toy")
    for name, env in (("vecenv", adapter), ("torchrl", torchrl)):
        collector = RolloutCollector(
            env, sampling, frames_per_batch=32 * envs, total_frames=-1, trust_policy=True,
            track_traj_ids=False, auto_register_policy_transforms=False,
        )  # fmt: skip
        batches = iter(collector)

        def collect(n: int, batches=batches) -> None:
            with torch.no_grad():
                for _ in range(max(1, n // 32)):
                    next(batches)

        out[name] = _rate(collect, steps, envs)
        collector.shutdown()
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--envs", type=int, nargs="+", default=[4, 64, 1024])
    parser.add_argument("--devices", nargs="+", default=None)
    parser.add_argument("--steps", type=int, default=512, help="env steps per measurement")
    args = parser.parse_args()
    devices = args.devices or (["cpu", "cuda"] if torch.cuda.is_available() else ["cpu"])
    torch.set_num_threads(1)
    rows = []
    for device in devices:
        for envs in args.envs:
            rows.append((device, envs, measure(envs, device, args.steps)))
    cols = list(rows[0][2])
    print("| device | envs | " + " | ".join(cols) + " | vecenv / raw + policy |")
    print("|---|---:|" + "---:|" * (len(cols) + 1))
    for device, envs, r in rows:
        ratio = r["vecenv"] / r["raw + policy"]
        print(
            f"| {device} | {envs} | "
            + " | ".join(f"{r[c]:,.0f}" for c in cols)
            + f" | {ratio:.2f} |"
        )


if __name__ == "__main__":
    main()
