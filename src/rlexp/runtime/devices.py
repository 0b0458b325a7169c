"""Where things run: ``trainer.device`` (the policy, GAE and the update) and ``env.device`` (where a
batched torch env is built), resolved once per process, and ``auto`` decided from the env actually
built (docs/batched_envs.md, "Devices").

``trainer.device=auto`` picks what is fast, not merely what is there: the env's own GPU when the env
already steps on one (rollout, GAE and update then never leave it); the CPU for a CPU env and a
small MLP, where a GPU would copy every step's observations and actions across the bus to run a
network too small to gain from it (Stable-Baselines3 warns about PPO's MLP policies on a GPU for
this reason); CUDA for a CPU env only when the network is wide enough for the update to gain.
"""

from __future__ import annotations

import logging
from typing import Any

import torch

from rlexp.config.validate import ConfigError

log = logging.getLogger(__name__)

#: A CPU env keeps an MLP of at most this many units per hidden layer on the CPU under
#: ``trainer.device=auto`` (64x64 and 256x256 included: the usual PPO sizes).
SMALL_MLP_MAX_WIDTH = 256


def resolve_device(device: str, strict: bool = False, key: str = "trainer.device") -> str:
    """``auto`` -> ``cuda`` when a GPU is visible, else ``cpu``; CUDA asked on a CPU-only machine
    falls back to CPU with one warning unless ``strict``."""
    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if device.startswith("cuda") and not torch.cuda.is_available():
        if strict:
            raise ConfigError(
                f"{key}={device!r} but CUDA is not available on this machine "
                "(trainer.strict_device=true); use trainer.device=auto or cpu"
            )
        log.warning("%s=%r but CUDA is not available: running on cpu", key, device)
        return "cpu"
    return device


def same_device(a: torch.device | str | None, b: torch.device | str | None) -> bool:
    """Whether two devices are the same one (``cuda`` and ``cuda:<current>`` are)."""
    if a is None or b is None:
        return a is b
    a, b = torch.device(a), torch.device(b)
    if a.type != b.type:
        return False
    if a.type != "cuda" or a.index == b.index:
        return True
    current = torch.cuda.current_device() if torch.cuda.is_available() else 0
    return (current if a.index is None else a.index) == (current if b.index is None else b.index)


def module_device(module: Any) -> torch.device:
    """The device of a module's first parameter (CPU for one without parameters)."""
    for p in module.parameters():
        return p.device
    return torch.device("cpu")


def widest_layer(policy_cfg: Any) -> int:
    """The widest hidden layer of the policy's MLPs (actor and, where there is one, critic)."""
    widths = [0]
    for part in ("actor", "critic"):
        mlp = getattr(policy_cfg, part, None)
        if mlp is not None:
            widths += list(mlp.hidden_sizes)
    return max(widths)


def auto_device(
    env_device: torch.device | None, policy_cfg: Any, local_rank: int | None
) -> tuple[str, str]:
    """``trainer.device=auto`` for a built env: the device and why (logged once by the caller).
    ``local_rank``: distributed (every rank's device must take part in the process group)."""
    if not torch.cuda.is_available():
        return "cpu", "no CUDA device is visible"
    if local_rank is not None:
        return f"cuda:{local_rank}", "distributed on CUDA (nccl): each rank on its own GPU"
    if env_device is not None and env_device.type == "cuda":
        return str(env_device), (
            f"the env steps on {env_device}: rollout, GAE and update stay there, no copy per step"
        )
    width = widest_layer(policy_cfg)
    if width <= SMALL_MLP_MAX_WIDTH:
        return "cpu", (
            f"a CPU env and a small MLP (widest layer {width} <= {SMALL_MLP_MAX_WIDTH}): a GPU would "
            "copy every step's observations and actions to run a network too small to gain"
        )
    return "cuda", (
        f"a CPU env and a wide MLP (widest layer {width} > {SMALL_MLP_MAX_WIDTH}): the update gains "
        "more on the GPU than the per-step copies cost"
    )
