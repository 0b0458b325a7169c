"""The Gaussian collection sampler's maths in numpy, for a CPU policy acting on a few envs.

Collection only: the deterministic sampler (evaluation) stays torch, so an evaluation round and an
exported policy (torch, TorchScript, ONNX) take the same actions bit for bit.

Why (issue #32): at one to a few envs per step, torch's per-operator dispatch is most of the policy's
cost, and alternating torch's large code path with the physics step slows both (HalfCheetah-v5, one
env, measured interleaved: 85 us per torch sampler call and 130 us per env step, against 48 us and
77 us with this one; benchmarks/collect_floor.py). Here the normaliser, the MLP (Linear with Tanh,
ReLU, ELU or SiLU) and the Gaussian draw are numpy float32 operations on views of the policy's own
parameters; the noise comes from torch's global generator, per call as the torch sampler draws it
or, in the collector, a rollout's worth at a time (``NoiseStream``), so seeding and resume work as
before.

The values equal the torch sampler's up to float rounding (matmul summation order, fused
multiply-add), not bit for bit; both of TorchRL's and rlexp's collection loops call the same
sampler, so they stay equal to each other (tests/test_ppo_math.py), and the loss recomputes the
log-probability in torch from the stored action as before. Where numpy would be slower or differ in
kind it is not used (``numpy_sampler`` returns None): a policy off the CPU, a float64 policy, other
activations or layers, image observations (a TensorDict; an actor reading some of a flat vector's
groups is supported: its columns are gathered first), or many rows per call (where OpenBLAS would start its own threads; the
torch sampler then runs, per call).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch
from torch import nn

from rlexp.policies.heads import _LOG_SQRT_2PI, GaussianActorNet, Sampler

#: The most multiply-adds per row of the widest layer times rows for which a call runs in numpy:
#: OpenBLAS threads a GEMM from m*n*k >= 4 * 65536 (its SMP threshold); below it, one thread.
MAX_ROW_MACS = 4 * 65536


def _silu(x: np.ndarray) -> np.ndarray:
    return x / (1.0 + np.exp(-x))


def _elu(x: np.ndarray) -> np.ndarray:
    return np.where(x > 0, x, np.expm1(np.minimum(x, 0)))


def _relu(x: np.ndarray) -> np.ndarray:
    return np.maximum(x, 0)


_ACTIVATIONS: dict[type[nn.Module], Callable[[np.ndarray], np.ndarray]] = {
    nn.Tanh: np.tanh,
    nn.ReLU: _relu,
    nn.ELU: _elu,
    nn.SiLU: _silu,
}


def _layers(mlp: nn.Sequential) -> list[tuple[np.ndarray, np.ndarray] | Callable] | None:
    """Each layer as (W^T, b) numpy views or an activation; None where one has no numpy form."""
    out: list[tuple[np.ndarray, np.ndarray] | Callable] = []
    for module in mlp:
        if isinstance(module, nn.Linear) and module.bias is not None:
            out.append((module.weight.detach().numpy().T, module.bias.detach().numpy()))
        elif type(module) in _ACTIVATIONS and getattr(module, "alpha", 1.0) == 1.0:
            out.append(_ACTIVATIONS[type(module)])
        else:
            return None
    return out


class NoiseStream:
    """Standard normal noise for one call at a time, drawn from torch's global generator ``block``
    calls at a time (``torch.randn([block, *shape])``).

    Why: in a loop that alternates with the physics, the first torch call after an env step costs
    ~25 us (HalfCheetah-v5, one env: 106 -> 81 us per collected step without it), however small.
    The collector sets ``block`` to its rollout length (steps per env), so a block is drawn at the
    first step of each rollout and is used up at its last: between rollouts, where checkpoints are
    taken, nothing is left over, and a resumed run draws the blocks an uninterrupted one draws.
    TorchRL's loop, stepping the same ``SamplingPolicy``, takes the same slices."""

    def __init__(self, block: int) -> None:
        self.block = block
        self._noise: np.ndarray | None = None
        self._next = 0

    def restart(self) -> None:
        """Start a rollout: what is left of a block (nothing, unless the policy was called between
        rollouts) is dropped, so blocks stay aligned with rollouts."""
        self._noise = None

    def take(self, shape: tuple[int, ...]) -> np.ndarray:
        """The next call's noise, float32 of ``shape``."""
        noise = self._noise
        if noise is None or self._next == self.block or noise.shape[1:] != shape:
            noise = torch.randn((self.block, *shape), dtype=torch.float32).numpy()
            self._noise, self._next = noise, 0
        self._next += 1
        return noise[self._next - 1]


def numpy_sampler(
    actor_net: nn.Module, fallback: Sampler, noise: NoiseStream | None = None
) -> Sampler | None:
    """The numpy form of ``actor_net.sampler(False, ...)``, the stochastic collection sampler
    (``fallback``: that sampler, run for calls with too many rows), or None where it does not
    apply. ``noise``: where the draws come from (None: ``torch.randn`` per call, as the torch
    sampler draws)."""
    if not isinstance(actor_net, GaussianActorNet):
        return None
    params = list(actor_net.parameters())
    if any(p.device.type != "cpu" or p.dtype != torch.float32 for p in params):
        return None
    layers = _layers(actor_net.mlp)
    if layers is None:
        return None
    widest = max(w.shape[0] * w.shape[1] for w in (x[0] for x in layers if isinstance(x, tuple)))
    max_rows = MAX_ROW_MACS // widest
    norm = actor_net.normalizer
    normalise = norm.enabled
    shift, scale_obs = norm._shift.numpy(), norm._scale.numpy()
    columns = None  # the observation's entries the actor reads (None: all of them)
    if actor_net._gathers:
        inputs = actor_net.inputs
        if inputs.structured or inputs.index is None:  # images: torch's encoders
            return None
        columns = inputs.index.numpy()
        # normalising is per entry: gathering first gives the same values, on fewer entries
        shift, scale_obs = shift[columns], scale_obs[columns]
    clip = np.float32(norm.clip)
    log_scale = actor_net.log_scale().detach()
    scale_t = log_scale.exp()
    scale = scale_t.numpy()
    log_norm = (log_scale + _LOG_SQRT_2PI).sum().numpy()  # float32, as the torch sampler's

    def arrays(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(loc, action, log-probability) for observations [rows, D], float32 numpy."""
        if columns is not None:
            x = x[:, columns]
        if normalise:
            x = x * scale_obs + shift
            np.minimum(np.maximum(x, -clip, out=x), clip, out=x)
        for layer in layers:
            if isinstance(layer, tuple):
                x = x @ layer[0] + layer[1]
            else:
                x = layer(x)
        if noise is None:  # torch's generator, one draw per call: the torch sampler's draws
            draw = torch.randn(x.shape, dtype=torch.float32).numpy()
        else:
            draw = noise.take(x.shape)
        log_prob = np.add.reduce(draw * draw, axis=-1) * np.float32(-0.5) - log_norm
        return x, x + scale * draw, log_prob

    def sample(obs: torch.Tensor) -> tuple[torch.Tensor, ...]:
        if obs.dim() != 2 or obs.shape[0] > max_rows or obs.dtype != torch.float32:
            return fallback(obs)
        loc, action, log_prob = arrays(obs.detach().numpy())
        loc_t = torch.from_numpy(loc)
        return (
            loc_t,
            scale_t.expand(loc_t.shape),
            torch.from_numpy(action),
            torch.from_numpy(log_prob),
        )

    # The collector's all-numpy loop (collector.py) calls these directly
    sample.arrays = arrays  # type: ignore[attr-defined]
    sample.max_rows = max_rows  # type: ignore[attr-defined]
    sample.scale = scale_t  # type: ignore[attr-defined]
    return sample
