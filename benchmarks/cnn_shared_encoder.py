"""What the shared image encoder costs per PPO minibatch (issue #47, docs/performance.md "CNN PPO"):
the Nature CNN run once per network (``actor_net(obs)`` and ``critic_net(obs)`` each through the
shared encoder: rlexp before the fix) against once for both heads (SB3's and CleanRL's
shared-features path), both on NCHW float images as SB3 gives them, and once for both heads with the
images in channels-last memory (rlexp now: ``encoders.scaled``). Forward and backward of actor
logits + value on a uint8 [mb, 4, 84, 84] minibatch, one torch thread, the variants alternating;
prints the min of ``--reps`` in ms.

    PYTHONPATH=src python benchmarks/cnn_shared_encoder.py --mb 256 --reps 5
"""

from __future__ import annotations

import argparse
import json
import time

import torch
from torch import nn

from rlexp.policies.encoders import NatureCNN


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--mb", type=int, default=256)
    p.add_argument("--reps", type=int, default=5)
    args = p.parse_args()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    enc = NatureCNN((4, 84, 84))
    actor, critic = nn.Linear(512, 6), nn.Linear(512, 1)
    params = [*enc.parameters(), *actor.parameters(), *critic.parameters()]
    x = torch.randint(0, 256, (args.mb, 4, 84, 84), dtype=torch.uint8)

    def nchw(images: torch.Tensor) -> torch.Tensor:  # the encoder on NCHW floats (SB3's layout)
        return torch.relu(enc.linear(enc.convs(images.to(torch.float32) / 255.0)))

    def twice() -> None:  # rlexp before: the encoder once per network
        loss = actor(nchw(x)).logsumexp(-1).mean() + critic(nchw(x)).square().mean()
        loss.backward()

    def once() -> None:  # SB3 / CleanRL: features once, two heads
        f = nchw(x)
        loss = actor(f).logsumexp(-1).mean() + critic(f).square().mean()
        loss.backward()

    def once_channels_last() -> None:  # rlexp now: once, channels-last images (NatureCNN.forward)
        f = enc(x)
        loss = actor(f).logsumexp(-1).mean() + critic(f).square().mean()
        loss.backward()

    variants = {"twice": twice, "once": once, "once_channels_last": once_channels_last}
    times: dict[str, list[float]] = {name: [] for name in variants}
    for _ in range(args.reps):
        for name, fn in variants.items():
            for q in params:
                q.grad = None
            t = time.perf_counter()
            fn()
            times[name].append((time.perf_counter() - t) * 1e3)
    out = {k: round(min(v), 1) for k, v in times.items()}
    out["mb"] = args.mb
    print(json.dumps(out))


if __name__ == "__main__":
    main()
