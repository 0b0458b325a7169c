"""What the shared image encoder costs per PPO minibatch when actor and critic each run it (rlexp's
``actor_net(obs)`` and ``critic_net(obs)``, each through the shared ``NatureCNN``) against running it
once for both heads (SB3's and CleanRL's shared-features path), issue #47 (docs/performance.md
"CNN PPO"). Forward and backward of actor logits + value on a uint8 [mb, 4, 84, 84] minibatch, one
torch thread, the two variants alternating; prints the min of ``--reps`` in ms.

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

    def twice() -> None:  # rlexp today: the encoder once per network
        loss = actor(enc(x)).logsumexp(-1).mean() + critic(enc(x)).square().mean()
        loss.backward()

    def once() -> None:  # SB3 / CleanRL: features once, two heads
        f = enc(x)
        loss = actor(f).logsumexp(-1).mean() + critic(f).square().mean()
        loss.backward()

    times: dict[str, list[float]] = {"twice": [], "once": []}
    for _ in range(args.reps):
        for name, fn in (("twice", twice), ("once", once)):
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
