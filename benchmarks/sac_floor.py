"""The floor of one SAC gradient step on one core: plain torch, no TensorDict, no TorchRL, the
whole update (twin critics' loss, the tanh-Gaussian actor's loss, alpha's loss, one backward, three
Adam steps, the soft target update) as one function, ``torch.compile``d or eager. The sizes are
SB3's / rl-zoo's MuJoCo SAC: 256x256 ReLU networks, batch 256 (HalfCheetah: obs 17, action 6).

    python benchmarks/sac_floor.py            # prints compiled and eager microseconds per step
    python benchmarks/sac_floor.py --eager --threads 1 2   # eager only, at 1 and at 2 torch threads
    python benchmarks/sac_floor.py --precision bf16 --threads 2   # networks under autocast (bf16)
"""

from __future__ import annotations

import argparse
import math
import os
import time

import torch
from torch import nn

OBS, ACT, HIDDEN, BATCH = 17, 6, 256, 256


def _mlp(i: int, o: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(i, HIDDEN), nn.ReLU(), nn.Linear(HIDDEN, HIDDEN), nn.ReLU(),
                         nn.Linear(HIDDEN, o))  # fmt: skip


def plain_step_fn(compiled: bool, precision: str = "fp32"):
    """A closure running one SAC gradient step on a fixed random batch (``precision`` bf16: each
    network under ``torch.autocast(bfloat16)``, its output cast to float32, as rlexp's
    ``trainer.precision=bf16``)."""

    def net(m: nn.Module, x: torch.Tensor) -> torch.Tensor:
        if precision == "fp32":
            return m(x)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            return m(x).float()

    torch.manual_seed(0)
    actor = _mlp(OBS, 2 * ACT)
    qs = nn.ModuleList(_mlp(OBS + ACT, 1) for _ in range(2))
    targets = [p.detach().clone() for p in qs.parameters()]
    log_alpha = torch.zeros((), requires_grad=True)
    opts = [torch.optim.Adam(m, lr=3e-4, fused=True) for m in
            (list(actor.parameters()), list(qs.parameters()), [log_alpha])]  # fmt: skip
    tq = nn.ModuleList(_mlp(OBS + ACT, 1) for _ in range(2))
    obs, act = torch.randn(BATCH, OBS), torch.rand(BATCH, ACT) * 2 - 1
    rew, nobs, term = torch.randn(BATCH), torch.randn(BATCH, OBS), torch.zeros(BATCH)

    def policy(o: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        loc, log_std = net(actor, o).chunk(2, -1)
        log_std = log_std.clamp(-20, 2)
        eps = torch.randn_like(loc)
        u = loc + log_std.exp() * eps
        log_det = 2.0 * (math.log(2.0) - u - nn.functional.softplus(-2.0 * u))
        logp = (-0.5 * eps.pow(2) - log_std - 0.5 * math.log(2 * math.pi) - log_det).sum(-1)
        return torch.tanh(u), logp

    def losses() -> torch.Tensor:
        alpha = log_alpha.detach().exp()
        with torch.no_grad():
            a2, lp2 = policy(nobs)
            x2 = torch.cat([nobs, a2], -1)
            y = rew + 0.99 * (1 - term) * (
                torch.minimum(net(tq[0], x2), net(tq[1], x2)).squeeze(-1) - alpha * lp2
            )
        x = torch.cat([obs, act], -1)
        q_loss = sum((net(q, x).squeeze(-1) - y).pow(2).mean() for q in qs)
        a, lp = policy(obs)
        xa = torch.cat([obs, a], -1)
        for p in qs.parameters():
            p.requires_grad_(False)
        q_pi = torch.minimum(net(qs[0], xa), net(qs[1], xa)).squeeze(-1)
        for p in qs.parameters():
            p.requires_grad_(True)
        actor_loss = (alpha * lp - q_pi).mean()
        alpha_loss = (-log_alpha * (lp.detach() - ACT)).mean()
        return q_loss + actor_loss + alpha_loss

    fn = torch.compile(losses) if compiled else losses

    def step() -> None:
        for o in opts:
            o.zero_grad(set_to_none=True)
        fn().backward()
        for o in opts:
            o.step()
        with torch.no_grad():
            torch._foreach_lerp_(list(tq.parameters()), list(qs.parameters()), 0.005)

    del targets
    return step


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--threads", type=int, nargs="+", default=[1], help="torch thread counts")
    parser.add_argument("--eager", action="store_true", help="the eager step only")
    parser.add_argument("--precision", choices=["fp32", "bf16"], default="fp32")
    args = parser.parse_args()
    for threads in args.threads:
        torch.set_num_threads(threads)
        for compiled in (False,) if args.eager else (True, False):
            call = plain_step_fn(compiled, args.precision)
            t0 = time.perf_counter()
            for _ in range(20):
                call()
            warm = time.perf_counter() - t0
            t0 = time.perf_counter()
            for _ in range(200):
                call()
            us = (time.perf_counter() - t0) / 200 * 1e6
            print(f"{threads} thread(s), {args.precision}, {'compiled' if compiled else 'eager'}: {us:.0f} us per SAC "
                  f"step (warm-up {warm:.1f} s; load {os.getloadavg()[0]:.1f})", flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
