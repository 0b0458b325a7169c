"""The schemas every policy and algorithm option builds on (``BasePolicyConfig``,
``BaseAlgorithmConfig``) and the network pieces they hold; ``schema.py`` (PPO, GRPO) and
``schema_offpolicy.py`` (SAC, TD3) subclass them. Importable from ``rlexp.config.schema`` too."""

from __future__ import annotations

from dataclasses import dataclass, field

from omegaconf import MISSING


@dataclass
class MLPConfig:
    """A plain Linear/activation stack, and what it reads of the observation."""

    hidden_sizes: list[int] = field(default_factory=lambda: [64, 64])  # widths of the hidden layers
    activation: str = "tanh"  # relu | elu | tanh | gelu | silu | swish
    # observation keys, key prefixes ("goal" selects "goal/position") or group names this network
    # reads (None: the actor reads group "policy", the critic every group; docs/policies.md)
    observations: list[str] | None = None


@dataclass
class EncoderConfig:
    """The CNN that turns each image observation into features (one per image key; docs/policies.md).
    Images are uint8 and scaled by 1/255 inside it; unused when the env has no images."""

    name: str = "nature"  # nature (SB3's / CleanRL's Atari CNN) | impala (Espeholt et al.'s ResNet)
    # conv channels per layer (nature) or per stage (impala); None: nature [32, 64, 64], impala
    # [16, 32, 32]
    channels: list[int] | None = None
    # nature only: kernel size and stride per conv layer (None: [8, 4, 3] and [4, 2, 1])
    kernel_sizes: list[int] | None = None
    strides: list[int] | None = None
    num_res_blocks: int = 2  # impala only: residual blocks per stage
    features_dim: int | None = (
        None  # the Linear layer after the convs (None: nature 512, impala 256)
    )


@dataclass
class MemoryConfig:
    """A recurrent core between each network's input features and its MLP (docs/policies.md,
    "Memory"); type none is the plain MLP policy."""

    type: str = "none"  # none | lstm | gru
    hidden_size: int = 256  # units of the LSTM / GRU (its output is the MLP's input)
    num_layers: int = 1  # stacked recurrent layers
    # true: one core (the actor's, reading the actor's observations) feeds actor and critic MLPs;
    # false: actor and critic each own a core
    shared: bool = False


@dataclass
class BasePolicyConfig:
    """A Gaussian actor: MLP for the action mean, a learned state-independent log-std (clamped),
    no squashing. The policy group's options are the subclasses (``policy.name`` says which)."""

    name: str = MISSING  # actor_critic | actor_only
    actor: MLPConfig = field(default_factory=MLPConfig)
    init_log_std: float = 0.0  # initial log standard deviation of the actions
    min_log_std: float = -5.0  # log-std is clamped to [min_log_std, max_log_std]
    max_log_std: float = 2.0
    ortho_init: bool = (
        True  # orthogonal init (gain sqrt(2), 0.01 for the action mean, 1 for the value)
    )
    encoder: EncoderConfig = field(default_factory=EncoderConfig)  # image observations' CNN
    # actor and critic use the same image encoders (trained by both losses); false: one each
    share_encoder: bool = True
    memory: MemoryConfig = field(default_factory=MemoryConfig)  # recurrent policies (PPO)


@dataclass
class BaseAlgorithmConfig:
    """What every algorithm has: discount, clipped ratio, entropy bonus, Adam, epochs x minibatches.
    The algorithm group's options are the subclasses (``algorithm.name`` says which)."""

    name: str = MISSING  # ppo | grpo
    gamma: float = 0.99  # discount
    clip_epsilon: float = 0.2  # ratio clip
    entropy_coeff: float = 0.0  # entropy bonus weight
    # Optimisation
    lr: float = 3e-4  # Adam learning rate
    adam_eps: float = 1e-5  # Adam epsilon
    anneal_lr: bool = False  # linearly anneal the learning rate to 0 over the run
    max_grad_norm: float = 0.5  # gradient-norm clipping (<= 0: off)
    num_epochs: int = 10  # passes over each rollout
    mini_batch_size: int = 64  # transitions per minibatch
    # torch.compile of the loss (forward and backward): auto | true | false. auto compiles when the
    # run is long enough to win back the compile time (docs/performance.md)
    compile: str = "auto"
