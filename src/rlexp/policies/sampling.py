"""The fast collection policy: ``SamplingPolicy`` samples actions and scores them with plain tensor
ops (the numpy sampler where it applies), optionally writing the critic's values with the image
features the actor and critic share computed once (``sharing_features``)."""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import nn
from torch.nn import functional as F

from rlexp.policies.heads import CategoricalActorNet, GaussianActorNet, ReadsObservation, Sampler
from rlexp.policies.numpy_sampler import NoiseStream, numpy_sampler

__all__ = ["SamplingPolicy", "sharing_features"]


class SamplingPolicy(TensorDictModuleBase):
    """Collection policy: samples actions and writes their log-prob, with plain tensor ops.

    Same parameters as the ``ProbabilisticActor``, same keys (the head's distribution parameters:
    ``loc`` / ``scale`` or ``logits``; then ``action``, ``action_log_prob``), and the same
    log-density as the distribution TorchRL's loss uses (tested).
    """

    #: Whether ``sampler`` may run in numpy where that applies (``numpy_sampler``).
    use_numpy: bool = True
    #: Where the numpy sampler's noise comes from: None, ``torch.randn`` per call; a
    #: ``NoiseStream`` (``set_noise_block``), blocks of calls from torch's generator.
    noise: NoiseStream | None = None

    def __init__(
        self,
        actor_net: GaussianActorNet | CategoricalActorNet,
        deterministic: bool = False,
        critic_net: ReadsObservation | None = None,
    ) -> None:
        """``critic_net``: also write ``state_value``, the critic's value of each observation
        (``Policy.sampling_policy(values=True)``)."""
        super().__init__()
        self.actor_net = actor_net
        self.critic_net = critic_net
        self.deterministic = deterministic
        self.in_keys = ["observation"]
        self.out_keys = [*actor_net.dist_keys, "action", "action_log_prob"]
        if critic_net is not None:
            self.out_keys.append("state_value")

    def sampler(self) -> Sampler:
        """``obs -> (*distribution parameters, action, log-probability of the action)`` for one
        rollout, in ``out_keys`` order.

        What cannot change while a rollout is collected (the clamped log-std, the log-density's
        constant, the list of layers) is computed once here; each call then runs the normaliser,
        the MLP's layers as plain functions (no ``nn.Module`` dispatch) and a few tensor ops. Build
        a new one after the parameters change shape or identity (every rollout, in practice).
        """
        layers = [_as_function(m) for m in self.actor_net.mlp]
        sampler = self.actor_net.sampler(self.deterministic, layers)
        if self.critic_net is not None:
            return _with_values(sampler, self.actor_net, self.critic_net)
        if self.deterministic or not self.use_numpy:
            # deterministic (evaluation): torch, so evaluation and an exported policy act alike
            return sampler
        # collecting with a CPU policy on a few envs: the same maths in numpy (numpy_sampler.py)
        return numpy_sampler(self.actor_net, sampler, self.noise) or sampler

    def set_noise_block(self, steps: int) -> None:
        """Draw the numpy sampler's noise ``steps`` calls at a time (a rollout's steps per env:
        ``NoiseStream``); both collection loops (rlexp's and TorchRL's) then take the same draws."""
        self.noise = NoiseStream(steps)

    def sample(self, obs: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """The ``out_keys``' tensors for a batch of observations."""
        return self.sampler()(obs)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        for key, value in zip(
            self.out_keys, self.sample(tensordict.get("observation")), strict=True
        ):
            tensordict.set(key, value)
        return tensordict


@contextlib.contextmanager
def sharing_features(*nets: ReadsObservation | None) -> Iterator[dict]:
    """Within: ``nets`` share one features cache (``inputs.encode``): an image encoder they share
    runs once per image tensor, whichever network calls it first."""
    cache: dict = {}
    nets = tuple(n for n in nets if n is not None)
    for net in nets:
        net.feature_cache = cache
    try:
        yield cache
    finally:
        for net in nets:
            net.feature_cache = None


def _with_values(
    sampler: Sampler, actor_net: ReadsObservation, critic_net: ReadsObservation
) -> Sampler:
    """``sampler``'s outputs and the critic's value of the same observation, the image features
    the two networks share computed once (the actor's, which the step computes anyway)."""

    def sample(obs: torch.Tensor | TensorDictBase) -> tuple[torch.Tensor, ...]:
        with sharing_features(actor_net, critic_net):
            out = sampler(obs)
            return (*out, critic_net(obs))

    return sample


def _as_function(module: nn.Module) -> Callable[[torch.Tensor], torch.Tensor]:
    """A layer of an MLP as a plain function of its input (same kernels as calling the module)."""
    if isinstance(module, nn.Linear):
        weight, bias = module.weight, module.bias
        return lambda x: F.linear(x, weight, bias)
    fn = _FUNCTIONAL.get(type(module))
    return fn if fn is not None else module


_FUNCTIONAL: dict[type[nn.Module], Callable[[torch.Tensor], torch.Tensor]] = {
    nn.Tanh: torch.tanh,
    nn.ReLU: torch.relu,
}
