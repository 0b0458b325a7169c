"""The plain-torch floors of CNN PPO on Pong's frames (issue #47, docs/performance.md "CNN PPO"):
one minibatch step of the Nature CNN with linear actor and critic heads (channels-last uint8 frames
scaled by 1/255, a policy and a value loss, backward, gradient clipping at 0.5, Adam), four epochs
of four minibatches of 256 over a 1,024-frame rollout as CleanRL's settings do; then the
collection step's forward on 8 frames. No rlexp code: what any implementation pays in fp32.

    python benchmarks/cnn_floor.py --threads 2
"""

from __future__ import annotations

import argparse
import json
import time

import torch
from torch import nn


def nature() -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(4, 32, 8, 4), nn.ReLU(), nn.Conv2d(32, 64, 4, 2), nn.ReLU(),
        nn.Conv2d(64, 64, 3, 1), nn.ReLU(), nn.Flatten(), nn.Linear(3136, 512), nn.ReLU(),
    ).to(memory_format=torch.channels_last)  # fmt: skip


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--reps", type=int, default=3)
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    enc, pi, v = nature(), nn.Linear(512, 6), nn.Linear(512, 1)
    params = [*enc.parameters(), *pi.parameters(), *v.parameters()]
    opt = torch.optim.Adam(params, lr=2.5e-4, eps=1e-5)
    frames = torch.randint(0, 256, (1024, 4, 84, 84), dtype=torch.uint8)
    frames = frames.contiguous(memory_format=torch.channels_last)
    actions = torch.randint(0, 6, (1024, 1))

    def step(idx: torch.Tensor) -> None:
        f = enc(frames[idx].div(255.0))
        logp = torch.log_softmax(pi(f), -1).gather(-1, actions[idx])
        loss = -logp.mean() + 0.5 * v(f).pow(2).mean()
        opt.zero_grad()
        loss.backward()
        nn.utils.clip_grad_norm_(params, 0.5)
        opt.step()

    update = []
    for _ in range(args.reps):
        t = time.perf_counter()
        for _epoch in range(4):
            perm = torch.randperm(1024)
            for i in range(4):
                step(perm[i * 256 : (i + 1) * 256])
        update.append((time.perf_counter() - t) / 16 * 1e3)
    obs = torch.randint(0, 256, (8, 4, 84, 84), dtype=torch.uint8)
    forward = []
    with torch.no_grad():
        for _ in range(args.reps):
            t = time.perf_counter()
            for _ in range(200):
                x = torch.div(obs.contiguous(memory_format=torch.channels_last), 255.0)
                torch.distributions.Categorical(logits=pi(enc(x))).sample()
            forward.append((time.perf_counter() - t) / 200 * 1e3)
    print(json.dumps({"threads": args.threads, "minibatch_step_ms": round(min(update), 1),
                      "collection_forward_8_frames_ms": round(min(forward), 2)}))  # fmt: skip


if __name__ == "__main__":
    main()
