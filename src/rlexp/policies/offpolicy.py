"""The off-policy learners' networks (``policy=sac``, ``policy=td3``): an actor that squashes its
action into the env's Box bounds with tanh, and a Q network on ``[observation, action]`` that the
learner copies ``policy.num_qvalue_nets`` times (TorchRL's SACLoss / TD3Loss hold the twin
parameters and their targets: ``algorithms/sac.py``).

- ``policy=sac``: the tanh-squashed Gaussian (TorchRL's ``TanhNormal`` through a
  ``ProbabilisticActor``); the MLP gives the mean and a state-dependent log-std (clamped to
  ``[min_log_std, max_log_std]``, SB3's -20 and 2). The action is ``low + (high - low) *
  (tanh(u) + 1) / 2``; the deterministic action (evaluation, export) ``tanh(mean)`` scaled alike.
- ``policy=td3``: the deterministic actor ``low + (high - low) * (tanh(mlp(obs)) + 1) / 2``;
  collection adds Gaussian noise of ``algorithm.exploration_noise`` x half the range, clipped to the
  bounds.

Before ``algorithm.learning_starts`` env steps, collection draws uniform actions in the bounds
(``uniform_actions``, a buffer the learner sets, so a resumed run continues as it was).

The observation normaliser (``policy.normalize_observations`` and ``env.normalize_observations``,
off by default) is shared and read by reference, never as a parameter of the networks: the loss's
twin Q copies and targets all see its current statistics.
"""

from __future__ import annotations

import torch
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.data import TensorSpec
from torchrl.envs.utils import ExplorationType
from torchrl.modules import ProbabilisticActor, TanhNormal, ValueOperator

from rlexp.config.schema_offpolicy import SACPolicyConfig
from rlexp.envs.spaces import ObsLayout
from rlexp.policies.actor_critic import (
    POLICIES,
    ObservationNormalizer,
    SamplingPolicy,
    make_mlp,
)
from rlexp.policies.heads import Sampler
from rlexp.policies.inputs import POLICY_GROUP, ObsInput, plain_layout, select_parts
from rlexp.policies.sampling import _as_function
from rlexp.runtime.precision import Mixed


class _ReadsRaw(Mixed, nn.Module):
    """A network that normalises its observation with a normaliser it does not own (not in its
    parameters or buffers: functional copies of it keep reading the live statistics). Its MLP runs
    under ``self.autocast()`` (``trainer.precision``), its output float32."""

    def _set_normalizer(self, normalizer: ObservationNormalizer, inputs: ObsInput) -> None:
        self.__dict__["_normalizer"] = normalizer
        self.inputs = inputs

    @property
    def normalizer(self) -> ObservationNormalizer:
        return self.__dict__["_normalizer"]

    def features(self, obs: torch.Tensor) -> torch.Tensor:
        x = self.__dict__["_normalizer"](obs)
        return x if self.inputs.index is None else x.index_select(-1, self.inputs.index)


class TanhGaussianActorNet(_ReadsRaw):
    """obs -> (loc, scale) of the pre-tanh Gaussian; the log-std is state-dependent and clamped."""

    dist_keys = ("loc", "scale")

    def __init__(self, normalizer, inputs, mlp: nn.Sequential, min_log_std, max_log_std) -> None:
        super().__init__()
        self._set_normalizer(normalizer, inputs)
        self.mlp = mlp
        self.min_log_std, self.max_log_std = float(min_log_std), float(max_log_std)

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        with self.autocast():
            out = self.mlp(self.features(obs))
        loc, log_std = out.float().chunk(2, -1)
        return loc, log_std.clamp(self.min_log_std, self.max_log_std).exp()


class DeterministicActorNet(_ReadsRaw):
    """obs -> the action in the bounds: ``low + (high - low) * (tanh(mlp(obs)) + 1) / 2``."""

    def __init__(self, normalizer, inputs, mlp: nn.Sequential, low, high) -> None:
        super().__init__()
        self._set_normalizer(normalizer, inputs)
        self.mlp = mlp
        self.register_buffer("low", low.clone())
        self.register_buffer("high", high.clone())

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        with self.autocast():
            u = self.mlp(self.features(obs))
        return squash(u.float(), self.low, self.high)


class QNet(_ReadsRaw):
    """(obs, action) -> Q value [..., 1]."""

    def __init__(self, normalizer, inputs, mlp: nn.Sequential) -> None:
        super().__init__()
        self._set_normalizer(normalizer, inputs)
        self.mlp = mlp

    def forward(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        with self.autocast():
            q = self.mlp(torch.cat([self.features(obs), action], -1))
        return q.float()


def squash(u: torch.Tensor, low: torch.Tensor, high: torch.Tensor) -> torch.Tensor:
    """``low + (high - low) * (tanh(u) + 1) / 2``: an unbounded value into the Box."""
    return low + (high - low) * (torch.tanh(u) + 1.0) * 0.5


class OffPolicySampler(SamplingPolicy):
    """Collection and evaluation: writes ``action`` (and a 0 ``action_log_prob``: nothing reads it).

    ``deterministic``: the actor's mean (SAC) or action (TD3); otherwise a sample (SAC), the action
    plus Gaussian noise (TD3), or, while the policy's ``uniform_actions`` is set, uniform actions."""

    use_numpy = False

    def __init__(self, policy: OffPolicyPolicy, deterministic: bool = False) -> None:
        super(SamplingPolicy, self).__init__()  # (SamplingPolicy's own needs a Gaussian head)
        self.policy = policy
        self.actor_net = policy.actor_net
        self.deterministic = deterministic
        self.in_keys = ["observation"]
        # (the log-prob is a 0 placeholder: evaluation reads (..., action, log-prob); the replay
        # buffer keeps the action alone)
        self.out_keys = ["action", "action_log_prob"]

    def sampler(self) -> Sampler:
        p = self.policy
        low, high = p.action_low, p.action_high
        if not self.deterministic and bool(p.uniform_actions):

            def uniform(obs: torch.Tensor) -> tuple[torch.Tensor, ...]:
                shape = (*obs.shape[:-1], low.shape[-1])
                action = low + (high - low) * torch.rand(shape, device=low.device)
                return action, action.new_zeros(shape[:-1])

            return uniform
        # the actor's MLP as plain functions (no nn.Module dispatch: SAC acts on one observation
        # per env step), the same kernels as ``actor_net``'s forward
        net, layers = p.actor_net, [_as_function(m) for m in p.actor_net.mlp]

        def mlp(obs: torch.Tensor) -> torch.Tensor:
            with net.autocast():  # trainer.precision, as the network's forward
                x = net.features(obs)
                for layer in layers:
                    x = layer(x)
            return x.float()

        if p.kind == "sac":
            min_log_std, max_log_std = net.min_log_std, net.max_log_std

            def sac(obs: torch.Tensor) -> tuple[torch.Tensor, ...]:
                loc, log_std = mlp(obs).chunk(2, -1)  # TanhGaussianActorNet.forward
                scale = log_std.clamp(min_log_std, max_log_std).exp()
                u = loc if self.deterministic else loc + scale * torch.randn_like(loc)
                return squash(u, low, high), loc.new_zeros(loc.shape[:-1])

            return sac
        noise = p.exploration_noise * (high - low) * 0.5

        def td3(obs: torch.Tensor) -> tuple[torch.Tensor, ...]:
            action = squash(mlp(obs), net.low, net.high)  # DeterministicActorNet.forward
            if not self.deterministic:
                action = action + noise * torch.randn_like(action)
                action = torch.maximum(torch.minimum(action, high), low)
            return action, action.new_zeros(action.shape[:-1])

        return td3


class OffPolicyPolicy(nn.Module):
    """The normaliser, the actor (``actor``: what the loss uses; ``actor_net`` its network) and a
    Q network maker (``make_q``: TorchRL's ``ValueOperator`` on ``observation`` and ``action``; the
    learner makes ``num_qvalue_nets`` independently initialised ones, which its loss holds with
    their targets). Its ``state_dict``: the actor, the normaliser, the bounds and the collection
    state."""

    categorical = False
    critic_net = None

    def __init__(
        self,
        cfg: SACPolicyConfig,
        obs_dim: int,
        act_dim: int,
        action_spec: TensorSpec,
        normalize_observations: bool = False,
        clip_observations: float = 10.0,
        nvec=None,
        layout: ObsLayout | None = None,
    ) -> None:
        super().__init__()
        kind = cfg.name
        if nvec is not None:
            raise ValueError(
                f"policy={kind}: the env's actions are discrete ({type(action_spec).__name__}); "
                f"{kind.upper()} here acts in a Box: use algorithm=ppo or algorithm=grpo"
            )
        layout = plain_layout(obs_dim) if layout is None else layout
        if layout.structured:
            raise ValueError(
                f"policy={kind}: the env's observation holds images; {kind.upper()} here reads "
                "vector observations only: use algorithm=ppo (docs/sac.md)"
            )
        low, high = _bounds(action_spec, kind)
        self.kind = kind
        self.obs_layout = layout
        self.cfg = cfg
        self.act_dim = act_dim
        self.exploration_noise = 0.1  # TD3's collection noise (x half range): set by the learner
        self.normalizer = ObservationNormalizer(
            obs_dim, clip_observations, normalize_observations and cfg.normalize_observations
        )
        self.register_buffer("action_low", low)
        self.register_buffer("action_high", high)
        # whether collection draws uniform actions (before algorithm.learning_starts)
        self.register_buffer("uniform_actions", torch.zeros((), dtype=torch.bool))
        parts = select_parts(
            layout, cfg.actor.observations, "policy.actor.observations", (POLICY_GROUP,)
        )
        actor_in = ObsInput(layout, parts, {})
        out = 2 * act_dim if kind == "sac" else act_dim
        mlp = make_mlp(actor_in.out_dim, out, cfg.actor, "policy.actor")
        self.actor_net: TanhGaussianActorNet | DeterministicActorNet
        if kind == "sac":
            self.actor_net = TanhGaussianActorNet(
                self.normalizer, actor_in, mlp, cfg.min_log_std, cfg.max_log_std
            )
            self.actor = ProbabilisticActor(
                TensorDictModule(
                    self.actor_net, in_keys=["observation"], out_keys=["loc", "scale"]
                ),
                in_keys=["loc", "scale"],
                distribution_class=TanhNormal,
                distribution_kwargs={"low": low, "high": high, "tanh_loc": False},
                spec=action_spec,
                default_interaction_type=ExplorationType.RANDOM,
            )
        else:
            self.actor_net = DeterministicActorNet(self.normalizer, actor_in, mlp, low, high)
            self.actor = TensorDictModule(
                self.actor_net, in_keys=["observation"], out_keys=["action"]
            )
        self._critic_parts = select_parts(
            layout, cfg.critic.observations, "policy.critic.observations", None
        )

    def _apply(self, fn, recurse=True):
        """``.to(device)``: the TanhNormal's bounds follow the buffers."""
        out = super()._apply(fn, recurse)
        if self.kind == "sac":
            kwargs = self.actor.module[-1].distribution_kwargs
            kwargs["low"], kwargs["high"] = self.action_low, self.action_high
        return out

    def make_q(self) -> ValueOperator:
        """A freshly initialised Q network (the learner makes one per twin)."""
        q_in = ObsInput(self.obs_layout, self._critic_parts, {})
        mlp = make_mlp(q_in.out_dim + self.act_dim, 1, self.cfg.critic, "policy.critic")
        q = QNet(self.normalizer, q_in, mlp).to(self.action_low.device)
        # the policy's precision (trainer.precision: set_precision ran before the learner made it)
        q.autocast_dtype = self.actor_net.autocast_dtype
        q.autocast_device = self.actor_net.autocast_device
        return ValueOperator(q, in_keys=["observation", "action"])

    @property
    def obs_structured(self) -> bool:
        return False

    @property
    def actor_input_parts(self) -> list[dict]:
        return self.actor_net.inputs.records()

    @property
    def critic_input_parts(self) -> list[dict]:
        return []

    def sampling_policy(
        self, deterministic: bool = False, values: bool = False
    ) -> OffPolicySampler:
        """The collection (or, ``deterministic``, evaluation) policy; ``values`` is PPO's (the
        critic's values written while collecting) and means nothing for SAC / TD3."""
        del values
        return OffPolicySampler(self, deterministic)

    def deterministic_action(self, obs: torch.Tensor) -> torch.Tensor:
        """The action evaluation and export take: ``tanh(mean)`` (SAC) / the actor's (TD3), scaled."""
        if self.kind == "sac":
            loc, _ = self.actor_net(obs)
            return squash(loc, self.action_low, self.action_high)
        return self.actor_net(obs)

    def metrics(self) -> dict[str, float]:
        return {}


def _bounds(action_spec: TensorSpec, kind: str) -> tuple[torch.Tensor, torch.Tensor]:
    """The Box's finite bounds [act_dim] (a one-line ValueError for infinite ones)."""
    space = getattr(action_spec, "space", None)
    low, high = getattr(space, "low", None), getattr(space, "high", None)
    if low is None or high is None:
        raise ValueError(f"policy={kind}: the env's action spec has no bounds to squash into")
    low = low.reshape(-1, low.shape[-1])[0].float().clone()
    high = high.reshape(-1, high.shape[-1])[0].float().clone()
    if not (torch.isfinite(low).all() and torch.isfinite(high).all()):
        raise ValueError(
            f"policy={kind} squashes actions into the env's Box bounds, but they are infinite "
            f"(low {low.tolist()}, high {high.tolist()}); use algorithm=ppo"
        )
    return low, high


class SACPolicy(OffPolicyPolicy):
    """``policy.name=sac``: the tanh-Gaussian actor and twin Q networks."""


class TD3Policy(OffPolicyPolicy):
    """``policy.name=td3``: the deterministic actor and twin Q networks."""


POLICIES.update({"sac": SACPolicy, "td3": TD3Policy})  # type: ignore[dict-item]
