"""The PPO minibatch step against its floor (issue #32): a plain-torch step (actor and critic
forward, clipped loss, backward, gradient clipping, Adam) eager and as one ``torch.compile``d
function, beside rlexp's ``PPO.update`` per minibatch, today's path (TorchRL's ClipPPOLoss) and the
fused step (``rlexp/algorithms/fused_step.py``), eager and compiled.

Shapes: the standard setting (64x64 tanh, obs 17, act 6, minibatch 64); rlexp's rows time whole
updates of a 2048-sample rollout x 10 epochs (GAE and the flatten included) divided by the 320
minibatch steps. Compile time is not counted (one untimed warm-up update or 50 steps first). One
torch thread. The contenders are timed in turns, ``--repeats`` rounds; prints a markdown table of
microseconds per minibatch step (medians).

    PYTHONPATH=src .venv/bin/python benchmarks/ppo_floor.py --repeats 5
"""

from __future__ import annotations

import argparse
import copy
import statistics
import time

import torch
from torch import nn

OBS, ACT, HIDDEN, MB, SAMPLES, EPOCHS = 17, 6, 64, 64, 2048, 10
#: The first call's (plain) or first update's (rlexp) seconds, compiling included, per contender.
WARMUP_S: dict = {}


def _mlp(out: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Linear(OBS, HIDDEN),
        nn.Tanh(),
        nn.Linear(HIDDEN, HIDDEN),
        nn.Tanh(),
        nn.Linear(HIDDEN, out),
    )


def plain_step_fn(compiled: bool):
    """A PPO minibatch step in plain torch, as CleanRL writes it; ``compiled``: the whole function
    (loss, backward, clipping, Adam) through one ``torch.compile``."""
    actor, critic = _mlp(ACT), _mlp(1)
    log_std = nn.Parameter(torch.zeros(ACT))
    params = [*actor.parameters(), *critic.parameters(), log_std]
    opt = torch.optim.Adam(params, lr=3e-4, eps=1e-5, fused=not compiled, capturable=compiled)
    if compiled:
        for group in opt.param_groups:
            group["lr"] = torch.tensor(3e-4)  # a tensor: annealing would not recompile

    def step(obs, action, old_logp, adv, ret):
        loc = actor(obs)
        std = log_std.exp().expand_as(loc)
        dist = torch.distributions.Normal(loc, std)
        logp = dist.log_prob(action).sum(-1)
        ratio = (logp - old_logp).exp()
        adv = (adv - adv.mean()) / (adv.std() + 1e-8)
        pg = torch.max(-adv * ratio, -adv * ratio.clamp(0.8, 1.2)).mean()
        v = critic(obs).squeeze(-1)
        loss = pg + 0.5 * (v - ret).pow(2).mean() - 0.0 * dist.entropy().sum(-1).mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        nn.utils.clip_grad_norm_(params, 0.5)
        opt.step()
        return loss.detach()

    fn = torch.compile(step) if compiled else step
    data = (
        torch.randn(MB, OBS),
        torch.randn(MB, ACT),
        torch.randn(MB),
        torch.randn(MB),
        torch.randn(MB),
    )
    return lambda: fn(*data)


def plain_contender(compiled: bool, steps: int):
    """A callable timing ``steps`` plain-torch steps (microseconds per step); warmed up."""
    call = plain_step_fn(compiled)
    t0 = time.perf_counter()
    call()  # compiles where compiled
    WARMUP_S[compiled] = time.perf_counter() - t0
    for _ in range(49):
        call()

    def run() -> float:
        t0 = time.perf_counter()
        for _ in range(steps):
            call()
        return (time.perf_counter() - t0) / steps * 1e6

    return run


def rlexp_setup(compile_choice: str, fused: bool):
    """A PPO learner on the standard shapes and a rollout of SAMPLES steps of one env."""
    from tensordict import TensorDict
    from torchrl.data import Bounded

    from rlexp.algorithms.ppo import make_algorithm
    from rlexp.config.schema import AlgorithmConfig, PolicyConfig
    from rlexp.policies.actor_critic import make_policy

    torch.manual_seed(0)
    pol = make_policy(PolicyConfig(), OBS, ACT, Bounded(-1.0, 1.0, shape=(ACT,)))
    cfg = AlgorithmConfig(num_epochs=EPOCHS, mini_batch_size=MB, compile=compile_choice)
    algo = make_algorithm(cfg, pol, total_iterations=500)
    algo.use_fused_step = fused
    obs = torch.randn(1, SAMPLES, OBS)
    with torch.no_grad():
        _, _, action, logp = pol.sampling_policy().sample(obs)
    done = torch.zeros(1, SAMPLES, 1, dtype=torch.bool)
    batch = TensorDict(
        {
            "observation": obs,
            "action": action,
            "action_log_prob": logp,
            "next": {
                "observation": torch.randn(1, SAMPLES, OBS),
                "reward": torch.randn(1, SAMPLES, 1),
                "terminated": done,
                "truncated": done,
                "done": done,
            },
        },
        batch_size=[1, SAMPLES],
    )
    return algo, batch


def rlexp_contender(compile_choice: str, fused: bool, updates: int):
    """A callable timing ``updates`` rlexp updates (microseconds per minibatch step); warmed up."""
    algo, batch = rlexp_setup(compile_choice, fused)
    t0 = time.perf_counter()
    algo.update(copy.deepcopy(batch))  # warm-up: compiles where compile is on
    WARMUP_S[(compile_choice, fused)] = time.perf_counter() - t0

    def run() -> float:
        t0 = time.perf_counter()
        for _ in range(updates):
            algo.update(batch.clone())
        return (time.perf_counter() - t0) / (updates * EPOCHS * (SAMPLES // MB)) * 1e6

    return run


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--steps", type=int, default=640, help="plain-torch steps per repeat")
    parser.add_argument("--updates", type=int, default=2, help="rlexp updates per repeat")
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    k = args.updates
    warmups = {  # the WARMUP_S key of each contender
        "plain torch, eager": False,
        "plain torch, one compiled step (floor)": True,
        "rlexp today (ClipPPOLoss), eager": ("false", False),
        "rlexp today (ClipPPOLoss), loss compiled": ("true", False),
        "rlexp fused step, eager": ("false", True),
        "rlexp fused step, compiled": ("true", True),
    }
    contenders = {  # all built (and compiled) first, then timed in turns: the load drifts
        "plain torch, eager": plain_contender(False, args.steps),
        "plain torch, one compiled step (floor)": plain_contender(True, args.steps),
        "rlexp today (ClipPPOLoss), eager": rlexp_contender("false", False, k),
        "rlexp today (ClipPPOLoss), loss compiled": rlexp_contender("true", False, k),
        "rlexp fused step, eager": rlexp_contender("false", True, k),
        "rlexp fused step, compiled": rlexp_contender("true", True, k),
    }
    results: dict[str, list[float]] = {name: [] for name in contenders}
    for _ in range(args.repeats):
        for name, run in contenders.items():
            results[name].append(run())
    floor = statistics.median(results["plain torch, one compiled step (floor)"])
    print(
        f"| minibatch step (64x64 tanh, obs {OBS}, act {ACT}, mb {MB}) | us / step | x floor "
        "| first call / update, s (compiling) |"
    )
    print("|---|---:|---:|---:|")
    for name, values in results.items():
        med = statistics.median(values)
        print(f"| {name} | {med:.0f} | {med / floor:.2f} | {WARMUP_S[warmups[name]]:.1f} |")


if __name__ == "__main__":
    main()
