"""Typed schemas of every config group, registered in Hydra's ConfigStore.

Each YAML file in ``conf/<group>/`` names its group schema first in its defaults list (e.g.
``- ppo_schema``), and the root ``config.yaml`` names ``rlexp_schema``: a misspelled key or a value of
the wrong type fails when Hydra composes the config, naming the key. Field names follow the TorchRL
constructor arguments they feed (``clip_epsilon``, ``entropy_coeff``, ``lmbda``, ``frames_per_batch``).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from datetime import datetime
from typing import Any

from omegaconf import MISSING, OmegaConf

from rlexp.config.native_task import EventTermConfig, NativeTaskConfig
from rlexp.config.schema_base import (
    BaseAlgorithmConfig,
    BasePolicyConfig,
    EncoderConfig,  # noqa: F401  (re-exported: importable from here as before)
    MemoryConfig,  # noqa: F401  (re-exported: importable from here as before)
    MLPConfig,
)
from rlexp.config.schema_offpolicy import (
    SACConfig,
    SACPolicyConfig,
    TD3Config,
    TD3PolicyConfig,
)


def file_name(value: object) -> str:
    """``${file_name:${env.name}}``: a value as one safe file-name component (run and checkpoint
    names): an env id in Gymnasium's ``module:EnvId`` form or a namespace ``ns/Env-v0`` keeps its
    letters, each run of other characters becomes ``-``."""
    return re.sub(r"[^A-Za-z0-9._=+-]+", "-", str(value)).strip("-.") or "env"


_LAUNCHED: list[datetime] = []  # this process's launch time, fixed at its first use


def launch_time(pattern: str = "%Y-%m-%d/%H-%M-%S.%f") -> str:
    """``${launch_time:%H-%M-%S.%f}``: this launch's time, the same for every use in the process
    (Hydra's ``now`` reads the clock at each first use of a pattern: a date and a time read
    apart can straddle midnight). The default run and sweep dirs end in microseconds, so
    launches in the same second (a shell loop of ``&``) get dirs of their own, which still sort
    by time. ``--distributed`` broadcasts rank 0's (``rlexp.runtime.distributed``)."""
    if not _LAUNCHED:
        _LAUNCHED.append(datetime.now())
    return _LAUNCHED[0].strftime(pattern)


# Registered on import: every process that composes or converts a config imports this module.
OmegaConf.register_new_resolver("file_name", file_name, replace=True)
# use_cache: a config resolved once keeps its value in its copies (a sweep's jobs), as Hydra's now
OmegaConf.register_new_resolver("launch_time", launch_time, replace=True, use_cache=True)


@dataclass
class TrainerConfig:
    """The training loop: budget, collection size, evaluation, checkpoints, device."""

    exp_name: str = "rlexp"  # run name: logger run name and checkpoint prefix
    total_frames: int = (
        1_000_000  # env steps to train for, summed over all envs (Collector's total_frames)
    )
    iterations: int | None = None  # if set, total_frames = iterations * frames_per_batch
    frames_per_batch: int = (
        2048  # env steps per rollout, summed over env.num_envs (Collector's frames_per_batch)
    )
    device: str = "auto"  # auto | cpu | cuda | cuda:N; auto picks CUDA when present
    strict_device: bool = (
        False  # a CUDA device on a machine without CUDA: error (true) or CPU + warning
    )
    eval_every: int = 50_000  # evaluate when global_step crosses a multiple of this (0: never)
    eval_episodes: int = 10  # episodes per evaluation, spread over env.num_eval_envs
    # evaluate in a worker process while training goes on: auto | true | false. auto: on with a
    # spare core and nothing acting on eval results (docs/performance.md, "Evaluation off the
    # critical path"); the same metrics and best.pt as in-process evaluation
    eval_async: str = "auto"
    save_every: int = (
        100_000  # checkpoint when global_step crosses a multiple of this (0: only at the end)
    )
    keep_last: int = 5  # step checkpoints kept on disk (older ones are deleted; <= 0 keeps all)
    resume: str = "auto"  # auto: continue from the newest good checkpoint in the run dir | never | a checkpoint path
    best_metric: str = "eval/episode_return"  # eval metric that best.pt follows (higher is better)
    nan_guard: bool = (
        True  # stop with a clear error on NaN/Inf in observations, losses or gradients
    )
    log_every: int = 1  # log training metrics every this many iterations
    progress: bool = True  # live progress bar on the console
    # torch intra-op threads for the update (PPO's epochs, SAC/TD3's gradient steps; collection
    # and evaluation run with one): 1 is fastest for small networks and on a machine other jobs
    # share; `auto`: the CPUs this process may use / the sweep's jobs side by side (SLURM: its
    # cpus_per_task), for a run that has the machine to itself (docs/performance.md)
    torch_threads: Any = 1
    # the policy's arithmetic: fp32 | bf16. bf16 is mixed precision (Lightning's "bf16-mixed"): the
    # networks' matmuls and convolutions under torch.autocast(bfloat16), weights, optimiser state,
    # losses and checkpoints float32 (docs/performance.md "Mixed precision (bf16)")
    precision: str = "fp32"
    # a run whose global_step has not moved for this long is `stalled` in `rlexp runs`, and the
    # longest wait for the eval worker's round or for another rank in a collective (then the run
    # fails, saving a checkpoint where one is consistent). Above the longest eval round and the
    # first iteration (start-up, torch.compile): docs/runs.md
    stall_timeout_s: float = 900.0
    # after SIGINT / SIGTERM / SIGHUP the run stops at the end of its iteration with a checkpoint;
    # one that has not reached that point this long after the signal (stuck in an env step) exits
    # anyway: 128 + N, interrupted, the last good checkpoint is the resume point
    stop_grace_s: float = 60.0


@dataclass
class PolicyConfig(BasePolicyConfig):
    """Actor-critic (PPO): the Gaussian actor and a separate MLP critic."""

    name: str = "actor_critic"
    critic: MLPConfig = field(default_factory=MLPConfig)


ActorCriticConfig = PolicyConfig


@dataclass
class ActorOnlyConfig(BasePolicyConfig):
    """The Gaussian actor alone, no critic (GRPO)."""

    name: str = "actor_only"


@dataclass
class AlgorithmConfig(BaseAlgorithmConfig):
    """PPO: TorchRL's ClipPPOLoss + GAE, Adam, epochs x minibatches."""

    name: str = "ppo"
    # GAE (torchrl.objectives.value.GAE)
    lmbda: float = 0.95  # GAE lambda
    # ClipPPOLoss (torchrl.objectives.ClipPPOLoss)
    critic_coeff: float = 0.5  # value loss weight
    loss_critic_type: str = "l2"  # l1 | l2 | smooth_l1
    normalize_advantage: bool = True  # normalise advantages per minibatch
    clip_value: float | None = None  # value clipping range (None: no value clipping)
    # The MuJoCo references' settings, on by default (docs/ppo.md, docs/results.md): linear LR
    # annealing, and reward scaling on the rollout before GAE (SB3 VecNormalize's reward part,
    # CleanRL's NormalizeReward): rewards divided by the running std of the discounted return
    # (statistics checkpointed), then clipped
    anneal_lr: bool = True
    normalize_rewards: bool = True
    clip_rewards: float | None = 10.0  # clip the (normalised) rewards to +- this (None: off)
    # rsl_rl's adaptive learning rate: per minibatch, lr / 1.5 when the KL to the behaviour policy
    # is above 2 x desired_kl, lr x 1.5 below desired_kl / 2, within [1e-5, 1e-2] (None: off)
    desired_kl: float | None = None
    # Collect the next rollout in a second process (a spare core) while the update runs; each
    # rollout is then collected by the policy one update behind (docs/performance.md "Overlap")
    overlap: bool = False
    # Recurrent policies (policy.memory): each env's rollout is cut into sequences of this many
    # steps, trained from the hidden state stored at their start (docs/policies.md "Memory")
    sequence_length: int = 32


PPOConfig = AlgorithmConfig


@dataclass
class GRPOConfig(BaseAlgorithmConfig):
    """GRPO: group-relative advantages of Monte-Carlo returns (no critic), the clipped surrogate,
    and an optional KL penalty to a frozen copy of the initial policy (docs/grpo.md)."""

    name: str = "grpo"
    kl_coeff: float = 0.02  # weight of the k3 KL estimate to the initial policy (0: no reference)
    group_size: int = 4  # envs per group: blocks of consecutive env indices; divides env.num_envs
    epsilon: float = 1e-8  # added to the group's return std before dividing
    reset_every_rollout: bool = True  # reset every env before each rollout
    truncate_at_first_done: bool = True  # mask each env's steps after its first done in a rollout


@dataclass
class EnvConfig:
    """The training (and evaluation) environment."""

    # Gymnasium id (gymnasium, gymnasium_async, envpool), native task (native), or
    # package.module:callable building a batched torch env (vecenv, torchrl)
    name: str = "HalfCheetah-v5"
    # gymnasium | gymnasium_async | envpool | native | vecenv | torchrl | torchrl_gym (docs/envs.md)
    backend: str = "gymnasium"
    num_envs: int = 1  # parallel training envs
    num_threads: int = 0  # envpool's thread pool (0: every CPU this process may use, <= num_envs)
    device: str = "cpu"  # where a vecenv / torchrl env is built and steps (auto: cuda if visible)
    num_eval_envs: int = 1  # parallel evaluation envs
    max_episode_steps: int | None = None  # time limit (None: the task's own)
    normalize_observations: bool = (
        True  # running mean/std normalisation (statistics are checkpointed)
    )
    clip_observations: float = 10.0  # normalised observations are clipped to +- this
    # Box actions: the policy acts in [-1, 1], mapped affinely onto the env's finite bounds
    # (gymnasium, gymnasium_async, envpool; docs/envs.md "Action bounds")
    rescale_actions: bool = False
    # images (gymnasium, gymnasium_async, envpool; docs/envs.md "Images"): stack each image's last
    # N frames where the env does not (0 or 1: off; newest last, a reset fills with its frame)
    frame_stack: int = 0
    # categorical actions (gymnasium, gymnasium_async; docs/envs.md "Action masks"): where the mask
    # of valid actions comes from: auto | info | observation | off
    action_mask: str = "auto"
    action_mask_key: str = "action_mask"  # the info key or Dict observation key holding the mask
    # observation keys read as images besides the detected ones (uint8 Box of rank 3 or 4), e.g. a
    # [H, W] grey image; an image at the root is "pixels"
    image_keys: list[str] = field(default_factory=list)
    # keep only these entries of a Box observation (flattened in C order), in this order, e.g.
    # [0, 2]: CartPole-v1 without its velocities (gymnasium, gymnasium_async, envpool; empty: all)
    observation_indices: list[int] = field(default_factory=list)
    kwargs: dict[str, Any] = field(
        default_factory=dict
    )  # extra keyword arguments for gymnasium.make
    native: NativeTaskConfig | None = None  # term configuration of a native task (backend=native)


@dataclass
class EventsConfig:
    """Events fired by the training and the evaluation event managers, in config order."""

    train: dict[str, EventTermConfig] = field(default_factory=dict)
    eval: dict[str, EventTermConfig] = field(default_factory=dict)


@dataclass
class HookConfig:
    """One trainer hook: a registered function or class and its parameters (docs/hooks.md)."""

    func: str = MISSING  # registered name (stop_at, stop_on_plateau, schedule, median_stop, ...)
    params: dict[str, Any] = field(default_factory=dict)


@dataclass
class TensorBoardConfig:
    enabled: bool = False  # write TensorBoard event files under <run_dir>/tensorboard


@dataclass
class WandbConfig:
    enabled: bool = False  # log to Weights & Biases
    project: str = "rlexp"
    entity: str | None = None
    mode: str = "auto"  # auto (offline when no key or network) | online | offline | disabled
    tags: list[str] = field(default_factory=list)


@dataclass
class LoggerConfig:
    """Metric sinks; several at once with ``logger=[tensorboard,wandb]``."""

    tensorboard: TensorBoardConfig = field(default_factory=TensorBoardConfig)
    wandb: WandbConfig = field(default_factory=WandbConfig)
    jsonl: bool = True  # <run_dir>/metrics.jsonl, one JSON object per logged step
    console: bool = True  # the [train] / [eval] summary lines through Python logging


@dataclass
class LoggerGroupSchema(LoggerConfig):
    """The schema the ``logger/*.yaml`` files name. Its fields are MISSING so that merging it again
    for a second selected logger (``logger=[tensorboard,wandb]``) keeps what the first one set; the
    root schema supplies the real defaults."""

    tensorboard: TensorBoardConfig = MISSING
    wandb: WandbConfig = MISSING
    jsonl: bool = MISSING
    console: bool = MISSING


@dataclass
class RootConfig:
    """The whole experiment."""

    seed: int = 0  # seeds python, numpy, torch and the envs
    trainer: TrainerConfig = MISSING
    policy: BasePolicyConfig = MISSING
    algorithm: BaseAlgorithmConfig = MISSING
    env: EnvConfig = MISSING
    events: EventsConfig = MISSING
    logger: LoggerConfig = MISSING
    #: trainer hooks by name, fired in this order at each hook point (conf/hooks/, docs/hooks.md)
    hooks: dict[str, Any] = field(default_factory=dict)  # name -> HookConfig (typed by validate)


#: group -> (schema name, schema class); each group YAML lists ``<schema name>`` in its defaults.
GROUP_SCHEMAS: dict[str, tuple[str, type]] = {
    "trainer": ("trainer_schema", TrainerConfig),
    "policy": ("policy_schema", PolicyConfig),
    "algorithm": ("algorithm_schema", AlgorithmConfig),
    "env": ("env_schema", EnvConfig),
    "events": ("events_schema", EventsConfig),
    "logger": ("logger_schema", LoggerGroupSchema),
}


#: group -> {``name`` value: its schema class}: a section's schema follows its ``name``.
VARIANTS: dict[str, dict[str, type]] = {
    "policy": {
        "actor_critic": PolicyConfig,
        "actor_only": ActorOnlyConfig,
        "sac": SACPolicyConfig,
        "td3": TD3PolicyConfig,
    },
    "algorithm": {"ppo": AlgorithmConfig, "grpo": GRPOConfig, "sac": SACConfig, "td3": TD3Config},
}
#: group -> {``name`` value: the conf/ group option that selects its schema}.
VARIANT_OPTIONS: dict[str, dict[str, str]] = {
    "policy": {"actor_critic": "mlp", "actor_only": "actor_only", "sac": "sac", "td3": "td3"},
    "algorithm": {"ppo": "ppo", "grpo": "grpo", "sac": "sac", "td3": "td3"},
}
#: ConfigStore names of the variants that are not their group's first schema (GROUP_SCHEMAS).
VARIANT_SCHEMAS: dict[str, tuple[str, type]] = {
    "actor_only_schema": ("policy", ActorOnlyConfig),
    "grpo_schema": ("algorithm", GRPOConfig),
    "sac_policy_schema": ("policy", SACPolicyConfig),
    "td3_policy_schema": ("policy", TD3PolicyConfig),
    "sac_schema": ("algorithm", SACConfig),
    "td3_schema": ("algorithm", TD3Config),
}


def variant_of(section: str, name: object) -> type | None:
    """The schema class of ``section`` (policy / algorithm) whose ``name`` is ``name``."""
    return VARIANTS.get(section, {}).get(name)  # type: ignore[call-overload]


def register_configs() -> None:
    """Register the root and group schemas in Hydra's ConfigStore (idempotent)."""
    from hydra.core.config_store import ConfigStore

    from rlexp.runtime.job_dir import register_resolver

    register_resolver()  # ${rlexp_job_dir:}: conf/config.yaml's log file
    cs = ConfigStore.instance()
    cs.store(name="rlexp_schema", node=RootConfig)
    for group, (name, node) in GROUP_SCHEMAS.items():
        cs.store(group=group, name=name, node=node)
    for name, (group, node) in VARIANT_SCHEMAS.items():
        cs.store(group=group, name=name, node=node)
