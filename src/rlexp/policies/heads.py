"""Action heads: what the actor MLP's output means, for each kind of action space.

- ``GaussianActorNet`` (Box actions): obs -> (loc, scale), a state-independent learned log-std;
  TorchRL's ``IndependentNormal`` over it (log-prob and entropy summed over the action dims).
- ``CategoricalActorNet`` (Discrete, MultiDiscrete, MultiBinary): obs -> logits, one block of
  ``nvec[k]`` logits per component; ``MultiCategorical`` over it: independent
  ``torch.distributions.Categorical`` per component, log-prob and entropy summed over components,
  the action an int64 vector ``[K]`` (``K = 1`` for ``Discrete``), the mode the per-component argmax.
  With an action mask (the observation's bool ``action_mask`` entry ``[..., sum(nvec)]``, issue
  #48) the logits of invalid actions are the dtype's smallest value (``mask_logits``): probability
  exactly 0, never sampled nor the argmax; entropy and KL sum over valid actions only (an invalid
  action's ``p * log p`` is ``0 * finite = 0``, no NaN), as TorchRL's ``MaskedCategorical``.

Each head reads the observation through ``ReadsObservation``: the normaliser, then, where the
network selects groups or keys or reads images, its ``inputs.ObsInput``.

Each head also gives the collection sampler (``sampler``): the same distribution written as a few
tensor ops, drawing actions without building a distribution object per env step (tested equal in
log-density to the distribution TorchRL's loss uses).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import torch
from tensordict import TensorDictBase
from torch import distributions as D
from torch import nn

from rlexp.runtime.precision import Mixed, mixed

_LOG_SQRT_2PI = 0.5 * math.log(2 * math.pi)
#: The observation TensorDict's entry holding the action mask (``envs.masks.MASK_KEY``).
MASK_KEY = "action_mask"

#: A collection sampler: obs -> the head's output keys' tensors (``out_keys`` order).
Sampler = Callable[[torch.Tensor], tuple[torch.Tensor, ...]]


class MultiCategorical(D.Distribution):
    """Independent categoricals over ``K`` components, from one logits vector [..., sum(nvec)].

    ``sample`` / ``mode`` give int64 [..., K]; ``log_prob`` and ``entropy`` sum over the components
    (the shape of ``IndependentNormal``'s, so TorchRL's PPO loss treats both alike)."""

    arg_constraints: dict = {}
    has_rsample = False

    def __init__(self, logits: torch.Tensor, nvec: Sequence[int]) -> None:
        self.nvec = tuple(int(n) for n in nvec)
        self.logits = logits
        k = len(self.nvec)
        batch = logits.shape[:-1]
        self._uniform = len(set(self.nvec)) == 1
        if self._uniform:  # one Categorical over [..., K, n]
            self._parts = [D.Categorical(logits=logits.reshape(*batch, k, self.nvec[0]))]
        else:
            self._parts = [D.Categorical(logits=x) for x in logits.split(self.nvec, dim=-1)]
        super().__init__(batch, torch.Size([k]), validate_args=False)

    def log_prob(self, value: torch.Tensor) -> torch.Tensor:
        value = value.long()
        if self._uniform:
            return self._parts[0].log_prob(value).sum(-1)
        return sum(p.log_prob(value[..., i]) for i, p in enumerate(self._parts))

    def entropy(self) -> torch.Tensor:
        if self._uniform:
            return self._parts[0].entropy().sum(-1)
        return sum(p.entropy() for p in self._parts)

    def sample(self, sample_shape: torch.Size | Sequence[int] = ()) -> torch.Tensor:
        with torch.no_grad():
            if self._uniform:
                return self._parts[0].sample(torch.Size(sample_shape))
            return torch.stack([p.sample(torch.Size(sample_shape)) for p in self._parts], -1)

    @property
    def mode(self) -> torch.Tensor:
        if self._uniform:
            return self._parts[0].logits.argmax(-1)
        return torch.stack([p.logits.argmax(-1) for p in self._parts], -1)

    @property
    def deterministic_sample(self) -> torch.Tensor:
        return self.mode


def gaussian_kl(
    old_loc: torch.Tensor, old_scale: torch.Tensor, loc: torch.Tensor, scale: torch.Tensor
) -> torch.Tensor:
    """KL(old || new) of diagonal Gaussians, summed over the action dims, mean over the batch: rsl_rl's
    formula to the letter, its 1e-5 inside the log included (it adds ~1e-5 per action dim)."""
    kl = (
        torch.log(scale / old_scale + 1.0e-5)
        + (old_scale.square() + (old_loc - loc).square()) / (2.0 * scale.square())
        - 0.5
    ).sum(-1)
    return kl.mean()


def categorical_kl(
    old_logits: torch.Tensor, logits: torch.Tensor, nvec: Sequence[int]
) -> torch.Tensor:
    """KL(old || new) of two ``MultiCategorical``s, summed over components, mean over the batch."""
    old, new = MultiCategorical(old_logits, nvec), MultiCategorical(logits, nvec)
    kl = sum(D.kl_divergence(a, b) for a, b in zip(old._parts, new._parts, strict=True))
    return (kl.sum(-1) if old._uniform else kl).mean()


def mask_logits(logits: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
    """``logits`` with every invalid action's (``mask`` False) set to the dtype's smallest finite
    value: its softmax probability is exactly 0 (``exp`` underflows) while log-probabilities,
    entropy and KL stay finite; gradients flow to the valid logits only. ``mask`` None: as is."""
    if mask is None:
        return logits
    return logits.masked_fill(~mask.to(torch.bool), torch.finfo(logits.dtype).min)


def action_mask_of(obs: torch.Tensor | TensorDictBase) -> torch.Tensor | None:
    """The observation's action mask (bool [..., sum(nvec)]), None where it has none."""
    if isinstance(obs, TensorDictBase):
        return obs.get(MASK_KEY, None)
    return None


class ReadsObservation(Mixed, nn.Module):
    """What a network does with the env's observation before its MLP: normalise it, and, with an
    ``inputs`` module (``inputs.ObsInput``), select groups or keys of it and encode images. Its
    encoders and MLP run under ``self.autocast()`` (``trainer.precision``), its output float32."""

    normalizer: nn.Module
    inputs: nn.Module | None
    _gathers: bool
    #: set by ``Policy.encode_once`` for a loss call: the features cache the actor and the critic
    #: share (``inputs.encode``); None: each call runs its encoders
    feature_cache: dict | None = None

    def _set_inputs(self, normalizer: nn.Module, inputs: nn.Module | None) -> None:
        self.normalizer = normalizer
        self.inputs = inputs
        # a selection of groups or keys, or images: more than the normalised observation
        self._gathers = inputs is not None and not inputs.trivial

    def features(
        self, obs: torch.Tensor | TensorDictBase, cache: dict | None = None
    ) -> torch.Tensor:
        """The MLP's input: the normalised observation, or what the network selects of it
        (``cache``: image features shared with the other network, ``inputs.encode``)."""
        if self._gathers:
            cache = self.feature_cache if cache is None else cache
            return self.inputs(obs, self.normalizer, cache)
        return self.normalizer(obs)

    def input_function(self) -> Callable:
        """``obs -> the MLP's input`` for a collection sampler (the normaliser itself when the
        network reads the whole flat vector: the path and numbers of a policy without groups)."""
        if self._gathers:
            return self.features  # (reads ``feature_cache``: a collection step's shared features)
        return self.normalizer

    def body_function(self, layers: list[Callable]) -> Callable:
        """``obs -> the MLP's output`` (float32) for a collection sampler: the input function, then
        ``layers``, under autocast at the network's precision (``trainer.precision``)."""
        norm = self.input_function()

        def body(obs: torch.Tensor | TensorDictBase) -> torch.Tensor:
            x = norm(obs)
            for layer in layers:
                x = layer(x)
            return x

        return mixed(body, self.autocast_dtype, self.autocast_device)


class GaussianActorNet(ReadsObservation):
    """obs -> (loc, scale) with a learned state-independent log-std, clamped to its bounds."""

    #: the TensorDict keys the actor writes (the distribution's parameters)
    dist_keys = ("loc", "scale")

    def __init__(
        self,
        normalizer: nn.Module,
        mlp: nn.Sequential,
        act_dim: int,
        init_log_std: float,
        min_log_std: float,
        max_log_std: float,
        inputs: nn.Module | None = None,
    ):
        super().__init__()
        self._set_inputs(normalizer, inputs)
        self.mlp = mlp
        self.log_std = nn.Parameter(torch.full((act_dim,), float(init_log_std)))
        self.min_log_std = min_log_std
        self.max_log_std = max_log_std

    def log_scale(self) -> torch.Tensor:
        """The clamped log standard deviation, [act_dim]."""
        return torch.clamp(self.log_std, self.min_log_std, self.max_log_std)

    def forward(
        self, obs: torch.Tensor | TensorDictBase, cache: dict | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        with self.autocast():
            loc = self.mlp(self.features(obs, cache))
        loc = loc.float()  # (a no-op in float32)
        scale = self.log_scale().exp().expand_as(loc)
        return loc, scale

    def sampler(self, deterministic: bool, layers: list[Callable]) -> Sampler:
        """obs -> (loc, scale, action, log-probability of the action) for one rollout: the clamped
        log-std and the density's constant are computed once here."""
        body = self.body_function(layers)
        log_scale = self.log_scale().detach()
        scale = log_scale.exp()
        log_norm = (log_scale + _LOG_SQRT_2PI).sum()  # -log of the density's normalising constant

        def sample(obs: torch.Tensor) -> tuple[torch.Tensor, ...]:
            loc = body(obs)
            scales = scale.expand_as(loc)
            if deterministic:
                return loc, scales, loc, (-log_norm).expand(loc.shape[:-1])
            noise = torch.randn_like(loc)
            action = torch.addcmul(loc, scales, noise)
            log_prob = noise.pow(2).sum(-1).mul(-0.5) - log_norm
            return loc, scales, action, log_prob

        return sample

    def kl(self, behaviour: dict[str, torch.Tensor], obs: torch.Tensor) -> torch.Tensor:
        """KL(behaviour || current) on ``obs`` (rsl_rl's formula: ``gaussian_kl``)."""
        loc, scale = self(obs)
        return gaussian_kl(behaviour["loc"], behaviour["scale"], loc, scale)


class CategoricalActorNet(ReadsObservation):
    """obs -> logits [..., sum(nvec)]: one categorical per action component."""

    dist_keys = ("logits",)

    def __init__(
        self,
        normalizer: nn.Module,
        mlp: nn.Sequential,
        nvec: Sequence[int],
        inputs: nn.Module | None = None,
    ) -> None:
        super().__init__()
        self._set_inputs(normalizer, inputs)
        self.mlp = mlp
        self.nvec = tuple(int(n) for n in nvec)

    def forward(
        self, obs: torch.Tensor | TensorDictBase, cache: dict | None = None
    ) -> torch.Tensor:
        """The logits, invalid actions' at the dtype's minimum where the observation has a mask."""
        with self.autocast():
            logits = self.mlp(self.features(obs, cache))
        return mask_logits(logits.float(), action_mask_of(obs))

    def sampler(self, deterministic: bool, layers: list[Callable]) -> Sampler:
        """obs -> (logits, action, log-probability of the action): the Gumbel-max draw of each
        component (exactly a draw from its softmax), log-probs from ``log_softmax``; the logits
        masked as ``forward`` masks them (an invalid action's logit plus any Gumbel noise stays
        below every valid one's)."""
        body = self.body_function(layers)
        nvec = self.nvec
        k = len(nvec)
        uniform = len(set(nvec)) == 1

        def pick(blocks: torch.Tensor, masked: bool) -> tuple[torch.Tensor, torch.Tensor]:
            log_p = blocks.log_softmax(-1)
            if deterministic:
                action = blocks.argmax(-1)
            else:
                uniform = torch.rand_like(blocks)
                if masked:  # a draw of exactly 0 would make a valid action's noise -inf
                    uniform = uniform.clamp_(min=torch.finfo(blocks.dtype).tiny)
                gumbel = -torch.log(-torch.log(uniform))
                action = (blocks + gumbel).argmax(-1)
            return action, log_p.gather(-1, action.unsqueeze(-1)).squeeze(-1)

        def sample(obs: torch.Tensor) -> tuple[torch.Tensor, ...]:
            mask = action_mask_of(obs)
            logits = mask_logits(body(obs), mask)
            masked = mask is not None
            if uniform:
                action, log_p = pick(logits.reshape(*logits.shape[:-1], k, nvec[0]), masked)
            else:
                picked = [pick(b, masked) for b in logits.split(nvec, dim=-1)]
                action = torch.stack([a for a, _ in picked], -1)
                log_p = torch.stack([lp for _, lp in picked], -1)
            return logits, action, log_p.sum(-1)

        return sample

    def kl(self, behaviour: dict[str, torch.Tensor], obs: torch.Tensor) -> torch.Tensor:
        """KL(behaviour || current) on ``obs``, summed over components, mean over the batch."""
        return categorical_kl(behaviour["logits"], self(obs), self.nvec)
