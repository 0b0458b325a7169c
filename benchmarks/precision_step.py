"""``trainer.precision``: fp32 against bf16 (mixed precision) on the steps it changes, in this
process, alternating A/B so that the machine's load falls on both (docs/performance.md, "Mixed
precision (bf16)"):

- ``ppo_cnn``: rlexp's fused PPO minibatch step (forward, backward, clipping, Adam) of the Pong
  preset's policy: the Nature CNN on 4x84x84 uint8 shared by linear actor (6 actions) and critic
  heads, a minibatch of 256, CleanRL's Atari settings;
- ``ppo_cnn_collect``: that policy's collection forward on 8 observations (8 envs), values written;
- ``sac``: rlexp's fused SAC gradient step at rl-zoo's HalfCheetah sizes (obs 17, action 6, 256x256
  ReLU actor and twin critics, batch 256);
- ``sac_floor``: ``benchmarks/sac_floor.py``'s plain-torch step, its networks under autocast.

    python benchmarks/precision_step.py --threads 1 2 --rounds 3
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))


def _ppo_cnn(precision: str) -> tuple[Callable[[], None], Callable[[], None]]:
    """(one fused minibatch step, one collection forward) of the Pong preset's policy."""
    from tensordict import TensorDict
    from torchrl.data import MultiCategorical as MultiCategoricalSpec

    from rlexp.algorithms.fused_step import MINIBATCH_KEYS, FusedPPOStep
    from rlexp.algorithms.ppo import make_algorithm
    from rlexp.config.schema import AlgorithmConfig, EncoderConfig, MLPConfig, PolicyConfig
    from rlexp.envs.spaces import ObsLayout, ObsPart
    from rlexp.policies.actor_critic import make_policy
    from rlexp.runtime.precision import set_precision

    torch.manual_seed(0)
    image = ObsPart("", "image", (4, 84, 84), -1, 0, image_key="pixels", source_layout="chw")
    layout = ObsLayout("Box", (image,), 0)
    cfg = PolicyConfig(
        actor=MLPConfig(hidden_sizes=[]),
        critic=MLPConfig(hidden_sizes=[]),
        encoder=EncoderConfig(name="nature"),
        share_encoder=True,
    )
    spec = MultiCategoricalSpec(nvec=[6], shape=(1,), dtype=torch.int64)
    policy = make_policy(cfg, 0, 1, spec, normalize_observations=False, nvec=(6,), layout=layout)
    set_precision(policy, precision, "cpu")
    algo = make_algorithm(
        AlgorithmConfig(
            lr=2.5e-4,
            adam_eps=1e-5,
            clip_epsilon=0.1,
            clip_value=0.1,
            entropy_coeff=0.01,
            max_grad_norm=0.5,
            mini_batch_size=256,
            compile="false",
        ),  # fmt: skip
        policy,
        1,
    )
    step = FusedPPOStep(algo, compiled=False)
    n = 256
    obs = TensorDict(
        {"pixels": torch.randint(0, 256, (n, 4, 84, 84), dtype=torch.uint8)}, batch_size=[n]
    )
    with torch.no_grad():
        _, action, log_prob = policy.sampling_policy().sample(obs)
    batch = TensorDict(
        {
            "observation": obs,
            "action": action,
            "action_log_prob": log_prob,
            "advantage": torch.randn(n, 1),
            "value_target": torch.randn(n, 1),
            "state_value": torch.randn(n, 1),
        },
        batch_size=[n],
    )
    data = step.minibatch_data(batch)
    hyper = torch.tensor(step.hyper_values(algo.cfg))
    lr = float(algo.optimizer.param_groups[0]["lr"])
    sample = policy.sampling_policy(values=True).sampler()
    eight = obs[:8].clone()

    def update() -> None:
        step.step(data, hyper, lr, "benchmark")

    def collect() -> None:
        with torch.no_grad():
            sample(eight)

    del MINIBATCH_KEYS
    return update, collect


def _sac(precision: str) -> Callable[[], None]:
    """One fused SAC gradient step (algorithm.compile=auto) at HalfCheetah's sizes."""
    import tempfile

    from tensordict import TensorDict
    from torchrl.data import Bounded

    from rlexp.algorithms.sac import SAC
    from rlexp.config.schema_base import MLPConfig
    from rlexp.config.schema_offpolicy import SACConfig, SACPolicyConfig
    from rlexp.policies.offpolicy import SACPolicy
    from rlexp.runtime.precision import set_precision

    torch.manual_seed(0)
    obs_dim, act, n = 17, 6, 256
    pcfg = SACPolicyConfig(
        actor=MLPConfig([256, 256], "relu"), critic=MLPConfig([256, 256], "relu")
    )
    policy = SACPolicy(pcfg, obs_dim, act, Bounded(-1.0, 1.0, shape=(act,)))
    set_precision(policy, precision, "cpu")
    algo = SAC(SACConfig(batch_size=n, buffer_size=n), policy, 1, run_dir=Path(tempfile.mkdtemp()))
    done = torch.zeros(n, 1, dtype=torch.bool)
    batch = TensorDict(
        {
            "observation": torch.randn(n, obs_dim),
            "action": torch.rand(n, act) * 2 - 1,
            "next": {
                "observation": torch.randn(n, obs_dim),
                "reward": torch.randn(n, 1),
                "terminated": done,
                "truncated": done,
                "done": done,
            },
        },
        [n],
    )
    assert algo.fused is not None
    return lambda: algo._gradient_step(batch)


def _sac_floor(precision: str) -> Callable[[], None]:
    from sac_floor import plain_step_fn

    return plain_step_fn(False, precision)


CASES: dict[str, Callable[[str], Callable[[], None]]] = {
    "ppo_cnn": lambda p: _ppo_cnn(p)[0],
    "ppo_cnn_collect": lambda p: _ppo_cnn(p)[1],
    "sac": _sac,
    "sac_floor": _sac_floor,
}


def _time(fn: Callable[[], None], seconds: float) -> float:
    """ms per call: warm-up, then as many calls as fit in ``seconds`` (at least 5)."""
    for _ in range(3):
        fn()
    calls, t0 = 0, time.perf_counter()
    while calls < 5 or time.perf_counter() - t0 < seconds:
        fn()
        calls += 1
    return (time.perf_counter() - t0) / calls * 1e3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cases", nargs="+", default=list(CASES), choices=list(CASES))
    parser.add_argument("--threads", nargs="+", type=int, default=[1, 2])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--seconds", type=float, default=3.0, help="timed per measurement")
    args = parser.parse_args()
    for case in args.cases:
        fns = {p: CASES[case](p) for p in ("fp32", "bf16")}
        for threads in args.threads:
            torch.set_num_threads(threads)
            for r in range(args.rounds):
                order = ("fp32", "bf16") if r % 2 == 0 else ("bf16", "fp32")
                ms = {p: _time(fns[p], args.seconds) for p in order}
                load = os.getloadavg()[0]
                print(
                    f"{case:16s} threads={threads} round={r} fp32 {ms['fp32']:8.2f} ms  "
                    f"bf16 {ms['bf16']:8.2f} ms  fp32/bf16 {ms['fp32'] / ms['bf16']:.2f}x  "
                    f"load_avg_1m {load:.1f}",
                    flush=True,
                )


if __name__ == "__main__":
    main()
