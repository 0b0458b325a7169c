"""Typed schemas of the off-policy learners (``algorithm=sac``, ``algorithm=td3``) and their
networks (``policy=sac``, ``policy=td3``): docs/sac.md, docs/td3.md.

Field names follow TorchRL's ``SACLoss`` / ``TD3Loss`` arguments where they have one (``alpha_init``,
``fixed_alpha``, ``target_entropy``, ``num_qvalue_nets``) and SB3's names otherwise
(``buffer_size``, ``learning_starts``, ``train_freq``, ``policy_delay``, ``target_policy_noise``).

The learners inherit ``BaseAlgorithmConfig``'s fields; the on-policy ones among them
(``clip_epsilon``, ``entropy_coeff``, ``num_epochs``, ``mini_batch_size``) mean nothing here and a
value other than their default is refused in one line (``validate``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from rlexp.config.schema_base import BaseAlgorithmConfig, BasePolicyConfig, MLPConfig

#: ``algorithm.name`` values of the off-policy learners.
OFF_POLICY = ("sac", "td3")
#: Fields of ``BaseAlgorithmConfig`` that only PPO / GRPO read: refused on SAC / TD3 when changed.
ON_POLICY_ONLY = ("clip_epsilon", "entropy_coeff", "num_epochs", "mini_batch_size")


def _mlp_256() -> MLPConfig:
    return MLPConfig(hidden_sizes=[256, 256], activation="relu")


@dataclass
class OffPolicyConfig(BaseAlgorithmConfig):
    """What SAC and TD3 share: the replay buffer, the update-to-data ratio, targets."""

    name: str = "sac"
    lr: float = 3e-4  # the actor's Adam learning rate (SB3 learning_rate, CleanRL policy_lr)
    critic_lr: float = 3e-4  # the Q networks' Adam learning rate (CleanRL q_lr)
    adam_eps: float = 1e-8  # Adam epsilon (torch's and SB3's default)
    max_grad_norm: float = 0.0  # gradient-norm clipping per network (<= 0: off, as SB3)
    tau: float = 0.005  # soft target update: target <- tau * online + (1 - tau) * target
    buffer_size: int = 1_000_000  # replay capacity in transitions (summed over envs)
    # memory: a TorchRL LazyTensorStorage; memmap: memory-mapped files in the run dir; auto: memmap
    # above 100k transitions (the replay buffer's own docs, docs/sac.md)
    buffer_storage: str = "auto"
    batch_size: int = 256  # transitions per gradient step
    # env steps (summed over envs) of uniform random actions and no gradient steps first
    learning_starts: int = 10_000
    # gradient steps per env step collected (summed over envs): the update-to-data ratio; SB3's
    # gradient_steps / (train_freq * n_envs); fractions accumulate across rollouts
    updates_per_step: float = 1.0
    # env steps per env between updates: trainer.frames_per_batch becomes env.num_envs * train_freq
    train_freq: int = 1
    n_step: int = 1  # n-step returns (1: one-step TD targets), never across an episode's end


@dataclass
class SACConfig(OffPolicyConfig):
    """SAC: TorchRL's SACLoss (twin Q, tanh-Gaussian actor, automatic entropy tuning)."""

    name: str = "sac"
    alpha_lr: float = 3e-4  # Adam learning rate of log(alpha) (SB3 uses learning_rate)
    alpha_init: float = 1.0  # initial entropy coefficient (SB3 ent_coef="auto": 1.0)
    fixed_alpha: bool = False  # keep alpha at alpha_init (SB3 ent_coef=<number>)
    # entropy the temperature is tuned towards: "auto" (-act_dim, SB3 / TorchRL) or a number
    target_entropy: Any = "auto"


@dataclass
class TD3Config(OffPolicyConfig):
    """TD3: TorchRL's TD3Loss (twin Q, target policy smoothing, delayed actor and target updates)."""

    name: str = "td3"
    lr: float = 1e-3  # actor (rl-zoo's MuJoCo learning_rate)
    critic_lr: float = 1e-3  # critics
    policy_delay: int = 2  # actor and target updates every this many critic updates
    target_policy_noise: float = 0.2  # std of the target action's smoothing noise (x half range)
    target_noise_clip: float = 0.5  # the smoothing noise is clipped to +- this (x half range)
    exploration_noise: float = 0.1  # std of the collection noise (x half the action range)


@dataclass
class SACPolicyConfig(BasePolicyConfig):
    """SAC's networks: a tanh-squashed Gaussian actor (state-dependent log-std) and twin Q
    networks reading observation and action; 256x256 ReLU (SB3, CleanRL, rl-zoo)."""

    name: str = "sac"
    actor: MLPConfig = field(default_factory=_mlp_256)
    critic: MLPConfig = field(default_factory=_mlp_256)  # each Q network
    num_qvalue_nets: int = 2  # twin Q (the minimum is the target)
    min_log_std: float = -20.0  # SB3's clamp of the actor's log-std
    max_log_std: float = 2.0
    ortho_init: bool = False  # PyTorch's default init, as SB3 / CleanRL
    # observation normalisation for these networks, on top of env.normalize_observations (both
    # must be true): SAC and TD3 usually train on raw observations
    normalize_observations: bool = False


@dataclass
class TD3PolicyConfig(SACPolicyConfig):
    """TD3's networks: a deterministic tanh actor and twin Q networks."""

    name: str = "td3"
