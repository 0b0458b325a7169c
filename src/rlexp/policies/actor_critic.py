"""Gaussian policies: MLP actor with a state-independent log-std and an observation normaliser;
``ActorCritic`` (PPO) adds an MLP critic, ``ActorOnly`` (GRPO) has none.

The TorchRL modules (``ProbabilisticActor`` over an ``IndependentNormal``, ``ValueOperator``) are what
the loss and evaluation use. Collection uses ``SamplingPolicy``: the same parameters, but it samples
and scores actions with three tensor ops instead of building a distribution object per env step.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase
from torch import nn
from torch.nn import functional as F
from torchrl.data import TensorSpec
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType
from torchrl.modules import IndependentNormal, ProbabilisticActor, ValueOperator

from rlexp.config.schema import BasePolicyConfig, EnvConfig, MLPConfig

ACTIVATIONS: dict[str, type[nn.Module]] = {
    "relu": nn.ReLU,
    "elu": nn.ELU,
    "tanh": nn.Tanh,
    "gelu": nn.GELU,
    "silu": nn.SiLU,
    "swish": nn.SiLU,  # swish is SiLU
}
_LOG_SQRT_2PI = 0.5 * math.log(2 * math.pi)


class ObservationNormalizer(nn.Module):
    """Running mean / variance of observations (parallel Welford), applied as (x - mean) / std.

    The statistics are buffers, so they are part of every ``state_dict`` and checkpoint. They are
    updated once per rollout, after the PPO update, so that collection, GAE and the update of one
    iteration all see the same normalisation.
    """

    def __init__(
        self, dim: int, clip: float = 10.0, enabled: bool = True, eps: float = 1e-8
    ) -> None:
        super().__init__()
        self.enabled = enabled
        self.clip = clip
        self.eps = eps
        self.register_buffer("mean", torch.zeros(dim, dtype=torch.float64))
        self.register_buffer("var", torch.ones(dim, dtype=torch.float64))
        self.register_buffer("count", torch.zeros((), dtype=torch.float64))
        self.register_buffer("_scale", torch.ones(dim))
        self.register_buffer("_shift", torch.zeros(dim))

    @torch.no_grad()
    def update(
        self, obs: torch.Tensor, reduce_sum: Callable[[torch.Tensor], torch.Tensor] | None = None
    ) -> None:
        """Fold a batch into the statistics (``reduce_sum``: sums over ranks, so all ranks agree)."""
        if not self.enabled:
            return
        x = obs.reshape(-1, obs.shape[-1]).to(torch.float64)
        # count, sum and sum of squared deviations from the current mean (stable, and reducible)
        centred = x - self.mean
        stats = torch.cat(
            [
                torch.tensor([float(x.shape[0])], dtype=torch.float64),
                centred.sum(0),
                centred.pow(2).sum(0),
            ]
        )
        if reduce_sum is not None:
            stats = reduce_sum(stats)
        n, dim = stats[0], x.shape[-1]
        if n == 0:
            return
        b_mean_c = stats[1 : 1 + dim] / n  # batch mean, relative to the current mean
        b_var = stats[1 + dim :] / n - b_mean_c.pow(2)
        total = self.count + n
        new_mean = self.mean + b_mean_c * n / total
        m2 = self.var * self.count + b_var * n + b_mean_c.pow(2) * self.count * n / total
        self.mean.copy_(new_mean)
        self.var.copy_(m2 / total)
        self.count.copy_(total)
        std = torch.sqrt(self.var + self.eps)
        self._scale.copy_((1.0 / std).to(self._scale.dtype))
        self._shift.copy_((-self.mean / std).to(self._shift.dtype))

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        if not self.enabled:
            return obs
        return torch.clamp(torch.addcmul(self._shift, obs, self._scale), -self.clip, self.clip)


def make_mlp(in_dim: int, out_dim: int, cfg: MLPConfig, key: str) -> nn.Sequential:
    """Linear/activation stack ``in_dim -> hidden_sizes -> out_dim`` (no output activation)."""
    if cfg.activation not in ACTIVATIONS:
        raise ValueError(f"{key}.activation={cfg.activation!r}; choose from {sorted(ACTIVATIONS)}")
    layers: list[nn.Module] = []
    last = in_dim
    for width in cfg.hidden_sizes:
        layers += [nn.Linear(last, width), ACTIVATIONS[cfg.activation]()]
        last = width
    layers.append(nn.Linear(last, out_dim))
    return nn.Sequential(*layers)


def _ortho_init(mlp: nn.Sequential, last_gain: float) -> None:
    linears = [m for m in mlp if isinstance(m, nn.Linear)]
    for i, lin in enumerate(linears):
        nn.init.orthogonal_(lin.weight, gain=last_gain if i == len(linears) - 1 else math.sqrt(2))
        nn.init.zeros_(lin.bias)


class GaussianActorNet(nn.Module):
    """obs -> (loc, scale) with a learned state-independent log-std, clamped to its bounds."""

    def __init__(
        self,
        normalizer: ObservationNormalizer,
        mlp: nn.Sequential,
        act_dim: int,
        cfg: BasePolicyConfig,
    ):
        super().__init__()
        self.normalizer = normalizer
        self.mlp = mlp
        self.log_std = nn.Parameter(torch.full((act_dim,), float(cfg.init_log_std)))
        self.min_log_std = cfg.min_log_std
        self.max_log_std = cfg.max_log_std

    def log_scale(self) -> torch.Tensor:
        """The clamped log standard deviation, [act_dim]."""
        return torch.clamp(self.log_std, self.min_log_std, self.max_log_std)

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        loc = self.mlp(self.normalizer(obs))
        scale = self.log_scale().exp().expand_as(loc)
        return loc, scale


class CriticNet(nn.Module):
    """obs -> state value."""

    def __init__(self, normalizer: ObservationNormalizer, mlp: nn.Sequential):
        super().__init__()
        self.normalizer = normalizer
        self.mlp = mlp

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.mlp(self.normalizer(obs))


SampleFn = Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]]


class SamplingPolicy(TensorDictModuleBase):
    """Collection policy: samples a ~ N(loc, scale) and writes its log-prob, with plain tensor ops.

    Same parameters as the ``ProbabilisticActor``, same keys (``loc``, ``scale``, ``action``,
    ``action_log_prob``), and the same log-density as ``IndependentNormal`` (tested).
    """

    def __init__(self, actor_net: GaussianActorNet, deterministic: bool = False) -> None:
        super().__init__()
        self.actor_net = actor_net
        self.deterministic = deterministic
        self.in_keys = ["observation"]
        self.out_keys = ["loc", "scale", "action", "action_log_prob"]

    def sampler(self) -> SampleFn:
        """``obs -> (loc, scale, action, log-probability of the action)`` for one rollout.

        What cannot change while a rollout is collected (the clamped log-std, the log-density's
        constant, the list of layers) is computed once here; each call then runs the normaliser,
        the MLP's layers as plain functions (no ``nn.Module`` dispatch) and five tensor ops. Build
        a new one after the parameters change shape or identity (every rollout, in practice).
        """
        net = self.actor_net
        norm = net.normalizer
        log_scale = net.log_scale().detach()
        scale = log_scale.exp()
        log_norm = (log_scale + _LOG_SQRT_2PI).sum()  # -log of the density's normalising constant
        layers = [_as_function(m) for m in net.mlp]
        deterministic = self.deterministic

        def sample(
            obs: torch.Tensor,
        ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
            x = norm(obs)
            for layer in layers:
                x = layer(x)
            loc = x
            scales = scale.expand_as(loc)
            if deterministic:
                return loc, scales, loc, (-log_norm).expand(loc.shape[:-1])
            noise = torch.randn_like(loc)
            action = torch.addcmul(loc, scales, noise)
            log_prob = noise.pow(2).sum(-1).mul(-0.5) - log_norm
            return loc, scales, action, log_prob

        return sample

    def sample(
        self, obs: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """(loc, scale, action, log-probability of the action) for a batch of observations."""
        return self.sampler()(obs)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        loc, scale, action, log_prob = self.sample(tensordict.get("observation"))
        tensordict.set("loc", loc)
        tensordict.set("scale", scale)
        tensordict.set("action", action)
        tensordict.set("action_log_prob", log_prob)
        return tensordict


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


class GaussianPolicy(nn.Module):
    """The normaliser, the Gaussian actor and, when the config has one, the critic; its
    ``state_dict`` is the policy part of a checkpoint.

    ``actor`` is TorchRL's ``ProbabilisticActor`` (``IndependentNormal``: log-prob and entropy summed
    over the action dimensions, no squashing); ``sampling_policy`` the fast collection policy;
    ``critic`` TorchRL's ``ValueOperator`` (None without a critic)."""

    def __init__(
        self,
        cfg: BasePolicyConfig,
        obs_dim: int,
        act_dim: int,
        action_spec: TensorSpec,
        normalize_observations: bool = True,
        clip_observations: float = 10.0,
    ) -> None:
        super().__init__()
        critic_cfg: MLPConfig | None = getattr(cfg, "critic", None)
        self.normalizer = ObservationNormalizer(obs_dim, clip_observations, normalize_observations)
        actor_mlp = make_mlp(obs_dim, act_dim, cfg.actor, "policy.actor")
        critic_mlp = None
        if critic_cfg is not None:
            critic_mlp = make_mlp(obs_dim, 1, critic_cfg, "policy.critic")
        if cfg.ortho_init:
            _ortho_init(actor_mlp, 0.01)
            if critic_mlp is not None:
                _ortho_init(critic_mlp, 1.0)
        self.actor_net = GaussianActorNet(self.normalizer, actor_mlp, act_dim, cfg)
        self.actor = ProbabilisticActor(
            TensorDictModule(self.actor_net, in_keys=["observation"], out_keys=["loc", "scale"]),
            in_keys=["loc", "scale"],
            distribution_class=IndependentNormal,
            return_log_prob=True,
            log_prob_key="action_log_prob",
            spec=action_spec,
            default_interaction_type=ExplorationType.RANDOM,
        )
        self.critic_net: CriticNet | None = None
        self.critic: ValueOperator | None = None
        if critic_mlp is not None:
            self.critic_net = CriticNet(self.normalizer, critic_mlp)
            self.critic = ValueOperator(self.critic_net, in_keys=["observation"])

    def sampling_policy(self, deterministic: bool = False) -> SamplingPolicy:
        """The fast collection policy (``deterministic``: the mean action, for evaluation)."""
        return SamplingPolicy(self.actor_net, deterministic)


class ActorCritic(GaussianPolicy):
    """The Gaussian actor and an MLP critic sharing the normaliser (``policy.name=actor_critic``)."""

    critic_net: CriticNet
    critic: ValueOperator


class ActorOnly(GaussianPolicy):
    """The Gaussian actor alone (``policy.name=actor_only``, GRPO): no critic."""


#: ``policy.name`` -> the policy class.
POLICIES: dict[str, type[GaussianPolicy]] = {"actor_critic": ActorCritic, "actor_only": ActorOnly}


def make_policy(
    cfg: BasePolicyConfig,
    obs_dim: int,
    act_dim: int,
    action_spec: TensorSpec,
    normalize_observations: bool = True,
    clip_observations: float = 10.0,
) -> GaussianPolicy:
    """Build the configured policy for an env with ``obs_dim`` observations and ``act_dim`` actions."""
    if cfg.name not in POLICIES:
        raise ValueError(f"policy.name={cfg.name!r}; choose from {sorted(POLICIES)}")
    return POLICIES[cfg.name](
        cfg, obs_dim, act_dim, action_spec, normalize_observations, clip_observations
    )


def policy_for_env(cfg: BasePolicyConfig, env_cfg: EnvConfig, env: EnvBase) -> GaussianPolicy:
    """The configured policy for a built env: its observation and action sizes and bounds from the
    env's specs, the observation normaliser as ``env_cfg`` says (training, eval, export, checks)."""
    return make_policy(
        cfg,
        int(env.observation_spec["observation"].shape[-1]),
        int(env.action_spec.shape[-1]),
        env.action_spec,
        env_cfg.normalize_observations,
        env_cfg.clip_observations,
    )
