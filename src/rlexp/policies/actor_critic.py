"""Policies: an MLP actor with an action head (``heads.py``: Gaussian for Box actions, categorical
for Discrete / MultiDiscrete / MultiBinary) and an observation normaliser; ``ActorCritic`` (PPO) adds
an MLP critic, ``ActorOnly`` (GRPO) has none. Each network reads its own selection of the env's
observation (groups, keys, images through CNN encoders: ``inputs.py``, ``encoders.py``).

The TorchRL modules (``ProbabilisticActor`` over an ``IndependentNormal`` or a ``MultiCategorical``,
``ValueOperator``) are what the loss and evaluation use. Collection uses ``SamplingPolicy``: the same
parameters, but it samples and scores actions with a few tensor ops instead of building a
distribution object per env step.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable, Iterator, Sequence

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.data import MultiCategorical as MultiCategoricalSpec
from torchrl.data import TensorSpec
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType
from torchrl.modules import IndependentNormal, ProbabilisticActor, ValueOperator

from rlexp.config.schema import BasePolicyConfig, EnvConfig, MLPConfig
from rlexp.envs.spaces import ObsLayout, ObsPart
from rlexp.policies.encoders import make_encoder
from rlexp.policies.heads import (
    CategoricalActorNet,
    GaussianActorNet,
    MultiCategorical,
    ReadsObservation,
)
from rlexp.policies.inputs import POLICY_GROUP, ObsInput, layout_of, plain_layout, select_parts
from rlexp.policies.sampling import SamplingPolicy, sharing_features

ACTIVATIONS: dict[str, type[nn.Module]] = {
    "relu": nn.ReLU,
    "elu": nn.ELU,
    "tanh": nn.Tanh,
    "gelu": nn.GELU,
    "silu": nn.SiLU,
    "swish": nn.SiLU,  # swish is SiLU
}


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
                torch.full((1,), float(x.shape[0]), dtype=torch.float64, device=x.device),
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


class CriticNet(ReadsObservation):
    """obs -> state value."""

    def __init__(
        self, normalizer: ObservationNormalizer, mlp: nn.Sequential, inputs: ObsInput | None = None
    ):
        super().__init__()
        self._set_inputs(normalizer, inputs)
        self.mlp = mlp

    def forward(
        self, obs: torch.Tensor | TensorDictBase, cache: dict | None = None
    ) -> torch.Tensor:
        with self.autocast():
            value = self.mlp(self.features(obs, cache))
        return value.float()  # (a no-op in float32)


class Policy(nn.Module):
    """The normaliser, the actor and, when the config has one, the critic; its ``state_dict`` is the
    policy part of a checkpoint.

    ``actor`` is TorchRL's ``ProbabilisticActor``: over an ``IndependentNormal`` for Box actions
    (``nvec=None``; log-prob and entropy summed over the action dimensions, no squashing), over a
    ``MultiCategorical`` for categorical ones (``nvec``: values per action component).
    ``sampling_policy`` is the fast collection policy; ``critic`` TorchRL's ``ValueOperator`` (None
    without a critic).

    ``layout`` (the env's ``ObsLayout``; None: one flat vector of ``obs_dim``) is what the networks
    select from: ``policy.actor.observations`` (default: group ``policy``) and
    ``policy.critic.observations`` (default: every group); one CNN encoder per selected image key,
    shared by actor and critic unless ``policy.share_encoder=false``."""

    def __init__(
        self,
        cfg: BasePolicyConfig,
        obs_dim: int,
        act_dim: int,
        action_spec: TensorSpec,
        normalize_observations: bool = True,
        clip_observations: float = 10.0,
        nvec: Sequence[int] | None = None,
        layout: ObsLayout | None = None,
    ) -> None:
        super().__init__()
        critic_cfg: MLPConfig | None = getattr(cfg, "critic", None)
        layout = plain_layout(obs_dim) if layout is None else layout
        if layout.dim != obs_dim:
            raise ValueError(f"obs_dim={obs_dim}, but the observation layout has {layout.dim}")
        self.obs_layout = layout
        actor_parts = select_parts(
            layout, cfg.actor.observations, "policy.actor.observations", (POLICY_GROUP,)
        )
        critic_parts: tuple[ObsPart, ...] = ()
        if critic_cfg is not None:
            critic_parts = select_parts(
                layout, critic_cfg.observations, "policy.critic.observations", None
            )
        actor_enc, critic_enc = _encoders(cfg, actor_parts, critic_parts)
        actor_in = ObsInput(layout, actor_parts, actor_enc)
        critic_in = ObsInput(layout, critic_parts, critic_enc) if critic_cfg is not None else None
        self.normalizer = ObservationNormalizer(obs_dim, clip_observations, normalize_observations)
        self.nvec = None if nvec is None else tuple(int(n) for n in nvec)
        out_dim = act_dim if self.nvec is None else sum(self.nvec)
        actor_dim, critic_dim = self._core_outputs(
            cfg, actor_in.out_dim, None if critic_in is None else critic_in.out_dim
        )
        actor_mlp = make_mlp(actor_dim, out_dim, cfg.actor, "policy.actor")
        critic_mlp = None
        if critic_cfg is not None and critic_dim is not None:
            critic_mlp = make_mlp(critic_dim, 1, critic_cfg, "policy.critic")
        if cfg.ortho_init:
            _ortho_init(actor_mlp, 0.01)
            if critic_mlp is not None:
                _ortho_init(critic_mlp, 1.0)
        self.actor_net: GaussianActorNet | CategoricalActorNet
        if self.nvec is None:
            self.actor_net = GaussianActorNet(
                self.normalizer,
                actor_mlp,
                act_dim,
                cfg.init_log_std,
                cfg.min_log_std,
                cfg.max_log_std,
                actor_in,
            )
            dist: dict = {"distribution_class": IndependentNormal}
        else:
            self.actor_net = CategoricalActorNet(self.normalizer, actor_mlp, self.nvec, actor_in)
            dist = {
                "distribution_class": MultiCategorical,
                "distribution_kwargs": {"nvec": self.nvec},
            }
        keys = list(self.actor_net.dist_keys)
        self.actor = ProbabilisticActor(
            TensorDictModule(self.actor_net, in_keys=["observation"], out_keys=keys),
            in_keys=keys,
            return_log_prob=True,
            log_prob_key="action_log_prob",
            spec=action_spec,
            default_interaction_type=ExplorationType.RANDOM,
            **dist,
        )
        self.critic_net: CriticNet | None = None
        self.critic: ValueOperator | None = None
        if critic_mlp is not None:
            self.critic_net = CriticNet(self.normalizer, critic_mlp, critic_in)
            self.critic = ValueOperator(self.critic_net, in_keys=["observation"])

    #: Whether the policy has memory (policies/memory.py: a recurrent state carried across steps).
    recurrent = False

    def _core_outputs(self, cfg, actor_dim: int, critic_dim: int | None) -> tuple[int, int | None]:
        """The MLPs' input widths: the networks' features here; a recurrent policy builds its
        cores between features and MLPs and returns their width."""
        return actor_dim, critic_dim

    @property
    def obs_structured(self) -> bool:
        """Whether the observation is a TensorDict (``vector`` and uint8 images), not a vector."""
        return self.obs_layout.structured

    @property
    def actor_input_parts(self) -> list[dict]:
        """The observation parts the actor reads, as the layout records them (export, eval)."""
        return self.actor_net.inputs.records()

    @property
    def critic_input_parts(self) -> list[dict]:
        """The observation parts the critic reads ([] without a critic)."""
        return [] if self.critic_net is None else self.critic_net.inputs.records()

    @property
    def categorical(self) -> bool:
        """Whether the actions are categorical (Discrete / MultiDiscrete / MultiBinary)."""
        return self.nvec is not None

    def sampling_policy(self, deterministic: bool = False, values: bool = False) -> SamplingPolicy:
        """The fast collection policy (``deterministic``: the mean action or the most likely one,
        for evaluation). ``values``: it also writes ``state_value`` where ``values_in_collection``
        (PPO's GAE then takes the rollout's values, ``PPO.compute_advantages``: only valid while
        nothing updates the parameters between the collection and GAE)."""
        critic = self.critic_net if values and self.values_in_collection else None
        return SamplingPolicy(self.actor_net, deterministic, critic)

    @property
    def acts_on_images(self) -> bool:
        """Whether the actor reads an image through a CNN encoder: its collection step is a
        convolution over the envs' frames, not a few small matmuls (``loop.collection_threads``)."""
        return bool(self.actor_net.inputs.encoders)

    @property
    def values_in_collection(self) -> bool:
        """Whether collection computing the critic's values pays: an image policy whose critic
        reads no image through an encoder the actor does not share (``policy.share_encoder``), so
        that a value costs the critic's head on features the actor's step computed; GAE then skips
        its critic pass over the rollout's images. Vector-only policies keep GAE's pass (the
        numpy sampler's path stays as it is)."""
        if self.critic_net is None or not self.obs_structured:
            return False
        actor_encoders = list(self.actor_net.inputs.encoders.values())
        critic_encoders = list(self.critic_net.inputs.encoders.values())
        return bool(critic_encoders) and all(
            any(e is a for a in actor_encoders) for e in critic_encoders
        )

    @contextlib.contextmanager
    def encode_once(self, enabled: bool = True) -> Iterator[dict]:
        """Within: actor and critic share one features cache (``inputs.encode``), so an image
        encoder the two share (``policy.share_encoder``) runs once per image tensor, for one loss
        call that calls ``actor_net(obs)`` and ``critic_net(obs)`` apart (TorchRL's ClipPPOLoss;
        the fused step passes its cache explicitly instead). Nothing changes for a network without
        images, nor with ``enabled=False`` (PPO's compiled ClipPPOLoss: its first call runs the
        loss twice on one minibatch, and the second must not reuse the first's features)."""
        if not enabled:
            yield {}
            return
        with sharing_features(self.actor_net, self.critic_net) as cache:
            yield cache

    def metrics(self) -> dict[str, float]:
        """What the policy itself shows after an update (the Gaussian's mean log-std)."""
        if isinstance(self.actor_net, GaussianActorNet):
            return {"loss/log_std": float(self.actor_net.log_std.detach().mean())}
        return {}


#: The name policies had when every action was a Box (kept for code that imports it).
GaussianPolicy = Policy


class ActorCritic(Policy):
    """The actor and an MLP critic sharing the normaliser (``policy.name=actor_critic``)."""

    critic_net: CriticNet
    critic: ValueOperator


class ActorOnly(Policy):
    """The actor alone (``policy.name=actor_only``, GRPO): no critic."""


#: ``policy.name`` -> the policy class.
POLICIES: dict[str, type[Policy]] = {"actor_critic": ActorCritic, "actor_only": ActorOnly}
#: A policy class -> its recurrent version (``policy.memory``), registered by policies/memory.py,
#: which the package imports.
RECURRENT: dict[type[Policy], type[Policy]] = {}


def make_policy(
    cfg: BasePolicyConfig,
    obs_dim: int,
    act_dim: int,
    action_spec: TensorSpec,
    normalize_observations: bool = True,
    clip_observations: float = 10.0,
    nvec: Sequence[int] | None = None,
    layout: ObsLayout | None = None,
) -> Policy:
    """Build the configured policy for an env with ``obs_dim`` observations and ``act_dim`` actions
    (``nvec``: categorical actions with these numbers of values per component; ``layout``: the
    env's observation layout, None for one flat vector)."""
    if cfg.name not in POLICIES:
        raise ValueError(f"policy.name={cfg.name!r}; choose from {sorted(POLICIES)}")
    cls = POLICIES[cfg.name]
    memory = getattr(cfg, "memory", None)
    if memory is not None and memory.type != "none":
        if cls not in RECURRENT:
            raise ValueError(
                f"policy.memory.type={memory.type}: recurrent policies are actor-critics (PPO); "
                f"policy.name={cfg.name!r} is not: use policy=mlp, or policy.memory.type=none"
            )
        cls = RECURRENT[cls]
    return cls(
        cfg, obs_dim, act_dim, action_spec, normalize_observations, clip_observations, nvec, layout
    )


def _encoders(
    cfg: BasePolicyConfig, actor_parts: Sequence[ObsPart], critic_parts: Sequence[ObsPart]
) -> tuple[dict[str, nn.Module], dict[str, nn.Module]]:
    """One encoder per image key each network reads: the same module for both where
    ``policy.share_encoder`` (the default), separate ones otherwise."""
    actor: dict[str, nn.Module] = {}
    critic: dict[str, nn.Module] = {}
    for parts, own, other in ((actor_parts, actor, critic), (critic_parts, critic, actor)):
        for p in parts:
            if p.kind != "image":
                continue
            if cfg.share_encoder and p.image_key in other:
                own[p.image_key] = other[p.image_key]
            else:
                where = f" {p.image_key!r}"
                own[p.image_key] = make_encoder(cfg.encoder, p.shape, cfg.ortho_init, where)
    return actor, critic


def action_nvec(action_spec: TensorSpec) -> tuple[int, ...] | None:
    """The values per component of a categorical action spec (``MultiCategorical``: int actions
    [..., K]); None for a continuous one. Other discrete specs are refused with one line."""
    if isinstance(action_spec, MultiCategoricalSpec):
        nvec = action_spec.nvec.reshape(-1, action_spec.shape[-1])[0]
        return tuple(int(n) for n in nvec)
    if action_spec.domain == "discrete":
        raise TypeError(
            f"the env's action spec is {type(action_spec).__name__}; rlexp's categorical policies "
            "take a MultiCategorical spec of int actions [..., K] (rlexp's Gymnasium adapter, "
            "env.backend=gymnasium, makes one for Discrete / MultiDiscrete / MultiBinary spaces)"
        )
    return None


def policy_for_env(cfg: BasePolicyConfig, env_cfg: EnvConfig, env: EnvBase) -> Policy:
    """The configured policy for a built env: its observation and action sizes, bounds and kind
    from the env's specs, the observation normaliser as ``env_cfg`` says (training, eval, export,
    checks). What each network reads comes from the env's observation layout (``layout_of``);
    a selection naming nothing the env has is a one-line ValueError (exit 2 at the pre-check)."""
    layout = layout_of(env)
    return make_policy(
        cfg,
        layout.dim,
        int(env.action_spec.shape[-1]),
        env.action_spec,
        env_cfg.normalize_observations,
        env_cfg.clip_observations,
        action_nvec(env.action_spec),
        layout,
    )
