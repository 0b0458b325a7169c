"""Small helpers of the training loop: one torch thread while envs step, crossing a multiple of a
step count, the base env under transforms, and a digest of a module's parameters."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import torch
from torchrl.envs import EnvBase


def base_env(env: EnvBase | None) -> EnvBase | None:
    while env is not None and hasattr(env, "base_env"):
        env = env.base_env
    return env


def parameter_digest(module: torch.nn.Module) -> str:
    """sha256 of every parameter's bytes, in ``state_dict`` order."""
    import hashlib

    h = hashlib.sha256()
    for _, p in sorted(module.named_parameters()):
        h.update(p.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()[:16]


@contextmanager
def one_torch_thread() -> Iterator[None]:
    """Env stepping runs the policy on a few observations at a time: more torch threads only slow it
    down, and the cores belong to the physics (the native envs' thread pool). ``trainer.torch_threads``
    is for the update; collection and evaluation run with one (PushCube x64, torch_threads=2: 7,960
    -> 9,581 env-steps/s, docs/performance.md)."""
    threads = torch.get_num_threads()
    if threads == 1:
        yield
        return
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


def crossed(before: int, after: int, every: int) -> bool:
    """True when the step count went past a multiple of ``every`` (not only on exact equality)."""
    return every > 0 and after // every > before // every
