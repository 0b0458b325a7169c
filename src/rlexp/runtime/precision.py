"""``trainer.precision``: the arithmetic the policy's networks run in (docs/performance.md, "Mixed
precision (bf16)").

- ``fp32`` (default): everything float32, as before.
- ``bf16``: mixed precision, PyTorch Lightning's ``"bf16-mixed"`` (not its ``"bf16-true"``): the
  weights, gradients, Adam's state and checkpoints stay float32; the networks' matmuls and
  convolutions (MLPs, CNN encoders, SAC's / TD3's Q networks) run under
  ``torch.autocast(device_type, dtype=torch.bfloat16)``, and every network's output is cast back to
  float32 where it leaves the network, so the loss maths (log-probabilities, entropies, the
  clipped surrogate, value and Q targets, GAE, the normalisers, tanh's log-determinant, alpha) and
  the Adam step run in float32 outside autocast.

A network opts in by mixing in ``Mixed`` and running its layers inside ``self.autocast()``;
``set_precision(policy, ...)`` (the run's builder) switches every such module of a policy. A
policy built elsewhere (``rlexp export``, ``rlexp eval`` of a checkpoint) stays float32: exports
are float32 weights and float32 maths whatever the run trained with.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import platform
from collections.abc import Callable
from typing import Any

import torch

log = logging.getLogger(__name__)

#: ``trainer.precision`` values (rlexp.config.rules keeps its own copy, without importing torch).
PRECISIONS = ("fp32", "bf16")
#: The autocast dtype of each precision (None: no autocast).
DTYPES: dict[str, torch.dtype | None] = {"fp32": None, "bf16": torch.bfloat16}


class Mixed:
    """A network whose layers may run under autocast: ``with self.autocast(): ...`` around them,
    then its output through ``float32`` (a no-op in float32: the same tensor, no autograd node)."""

    #: the autocast dtype (None: float32, no autocast) and device type, set by ``set_precision``
    autocast_dtype: torch.dtype | None = None
    autocast_device: str = "cpu"

    def autocast(self) -> contextlib.AbstractContextManager:
        """``torch.autocast`` at this network's precision, or nothing."""
        return autocast(self.autocast_dtype, self.autocast_device)


def autocast(
    dtype: torch.dtype | None, device_type: str = "cpu"
) -> contextlib.AbstractContextManager:
    """``torch.autocast(device_type, dtype)``, or a no-op context for ``dtype=None``."""
    if dtype is None:
        return contextlib.nullcontext()
    return torch.autocast(device_type=device_type, dtype=dtype)


def float32(x: Any) -> Any:
    """A network's output as float32 (tensors in a tuple too); float32 and integer tensors as
    they are."""
    if isinstance(x, tuple):
        return tuple(float32(t) for t in x)
    if isinstance(x, torch.Tensor) and x.is_floating_point() and x.dtype != torch.float32:
        return x.float()
    return x


def mixed(fn: Callable, dtype: torch.dtype | None, device_type: str = "cpu") -> Callable:
    """``fn`` run under autocast at ``dtype``, its outputs cast to float32; ``fn`` itself for
    ``dtype=None`` (float32: not even a wrapper call)."""
    if dtype is None:
        return fn

    @functools.wraps(fn)
    def run(*args: Any, **kwargs: Any) -> Any:
        with torch.autocast(device_type=device_type, dtype=dtype):
            out = fn(*args, **kwargs)
        return float32(out)

    return run


def set_precision(module: torch.nn.Module, precision: str, device: str | torch.device) -> None:
    """Switch every ``Mixed`` network in ``module`` (a policy) to ``precision`` on ``device``."""
    dtype = DTYPES[check_precision(precision)]
    device_type = torch.device(device).type
    for m in module.modules():
        if isinstance(m, Mixed):
            m.autocast_dtype = dtype
            m.autocast_device = device_type


def check_precision(value: Any) -> str:
    """``trainer.precision`` as one of PRECISIONS, or a one-line ValueError naming the key."""
    if value not in PRECISIONS:
        raise ValueError(
            f"trainer.precision={value!r} must be one of {list(PRECISIONS)} (bf16: mixed precision,"
            " float32 weights and loss maths; Lightning's 'bf16-mixed')"
        )
    return value


def _cpu_flags() -> set[str]:
    """The x86 CPU's feature flags (Linux ``/proc/cpuinfo``; empty elsewhere)."""
    try:
        with open("/proc/cpuinfo", encoding="ascii", errors="replace") as f:
            for line in f:
                if line.startswith("flags"):
                    return set(line.split(":", 1)[1].split())
    except OSError:
        pass
    return set()


def bf16_unsupported(device: str | torch.device) -> str | None:
    """Why bfloat16 matmuls would not be fast on ``device`` (emulated or missing), or None."""
    dev = torch.device(device)
    if dev.type == "cuda":
        if not torch.cuda.is_bf16_supported(including_emulation=False):
            return f"{torch.cuda.get_device_name(dev)} has no native bfloat16"
        return None
    if dev.type != "cpu":
        return f"device {dev.type} is not one rlexp's mixed precision was measured on"
    if not torch.ops.mkldnn._is_mkldnn_bf16_supported():
        return "oneDNN has no bfloat16 kernels for this CPU"
    if platform.machine().lower() in ("x86_64", "amd64"):
        flags = _cpu_flags()
        if flags and not flags & {"avx512_bf16", "amx_bf16"}:
            return "this CPU has neither avx512_bf16 nor amx_bf16 (bfloat16 is emulated)"
    return None


def warn_if_slow(precision: str, device: str | torch.device) -> str | None:
    """Log one warning when ``trainer.precision=bf16`` would run emulated on ``device`` (the run
    goes on: the results are right, only slower than fp32); the warning's text, or None."""
    if precision != "bf16":
        return None
    problem = bf16_unsupported(device)
    if problem is None:
        return None
    text = (
        f"trainer.precision=bf16 on {torch.device(device).type}: {problem}, so it is likely "
        "slower than fp32 (the results are still right); use trainer.precision=fp32"
    )
    log.warning(text)
    return text
