"""One rule for every config field: the range, choices or shape a value must have.

``validate`` checks each rule and reports ``key=value must be <rule>``; the table in
docs/config_rules.md is :func:`rules_markdown` (a test keeps the two equal, and another checks that
every field of the schema has a rule). Types are the schema's job (Hydra refuses a string for an
int); these rules say which values of the right type make sense. Sections whose contents depend on
another choice (``env.kwargs``, ``env.native``, ``events.*``) are checked by building them once
before the run writes anything (``rlexp.launch.checks``).
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

#: Every name a run writes into a file name: a single safe path component (no "/", no "..").
SAFE_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._=+-]*")
MAX_NAME = 128  # checkpoint names add ~20 characters; file systems allow 255
#: Seeds are used with numpy's legacy seeding and added to per-rank / eval offsets.
MAX_SEED = 2**31 - 1
DEVICE = re.compile(r"auto|cpu|cuda(:\d+)?")
#: Activation names the MLP builder accepts (rlexp.policies.actor_critic.ACTIVATIONS; a test keeps
#: the two in step). Here so that a typo fails before torch is imported.
ACTIVATIONS = ("elu", "gelu", "relu", "silu", "swish", "tanh")
#: Image encoders (rlexp.policies.encoders.ENCODERS; a test keeps the two in step).
ENCODERS = ("nature", "impala")
#: ``trainer.precision`` values (rlexp.runtime.precision.PRECISIONS; a test keeps the two in step).
PRECISIONS = ("fp32", "bf16")
#: Recurrent cores of ``policy.memory.type`` (rlexp.policies.memory; none: the MLP policy).
MEMORY_TYPES = ("none", "lstm", "gru")
#: Backends whose envs a recurrent policy can collect from: rlexp's own stepping (``step_action``),
#: where the collector carries the hidden state; torchrl_gym goes through TorchRL's generic loop.
MEMORY_BACKENDS = ("gymnasium", "gymnasium_async", "envpool", "native", "vecenv", "torchrl")
#: Env backends (rlexp.envs.factory builds them; docs/envs.md). gymnasium: Gymnasium copies stepped
#: in the training process; gymnasium_async: Gymnasium's AsyncVectorEnv (a worker process per copy);
#: envpool: EnvPool's C++ thread pool; native: rlexp's batched MuJoCo tasks; vecenv: a batched torch
#: env of rsl_rl's VecEnv contract; torchrl: a TorchRL EnvBase factory; torchrl_gym: TorchRL's GymEnv
#: (the reference path).
BACKENDS = ("gymnasium", "gymnasium_async", "envpool", "native", "vecenv", "torchrl", "torchrl_gym")
#: Backends whose envs are stepped in the training process, so that ``algorithm.overlap``'s forked
#: collection process owns a full copy (envpool's threads, worker processes, GPUs do not fork).
OVERLAP_BACKENDS = ("gymnasium", "native")
#: Backends whose envs can rescale Box actions from [-1, 1] to the env's bounds (env.rescale_actions):
#: the Gymnasium-shaped adapters (rlexp.envs.adapter).
RESCALE_BACKENDS = ("gymnasium", "gymnasium_async", "envpool")
#: Backends that detect image observations and stack frames (env.frame_stack, env.image_keys): the
#: Gymnasium-shaped adapters; a torchrl env's uint8 entries pass as they are.
IMAGE_BACKENDS = ("gymnasium", "gymnasium_async", "envpool")
#: Backends that read action masks from the env (env.action_mask: info | observation; docs/envs.md;
#: vecenv: its extras, info only).
MASK_BACKENDS = ("gymnasium", "gymnasium_async", "vecenv")
#: Backends whose env is built by a callable the config names (``env.name=package.module:callable``).
CALLABLE_BACKENDS = ("vecenv", "torchrl")
#: The metrics an evaluation round logs: what ``trainer.best_metric`` may follow.
EVAL_METRICS = (
    "eval/episode_return",
    "eval/episode_return_std",
    "eval/episode_length",
    "eval/success_rate",
)
#: The hyperparameters hooks may change while a run trains, per algorithm (``kl_coeff``: GRPO with a
#: reference policy, i.e. kl_coeff > 0 at the start). rlexp.algorithms uses the same lists.
MUTABLE_HYPERPARAMETERS = {
    "ppo": ("lr", "clip_epsilon", "entropy_coeff", "max_grad_norm", "critic_coeff"),
    "grpo": ("lr", "clip_epsilon", "entropy_coeff", "max_grad_norm", "kl_coeff"),
    "sac": ("lr", "critic_lr", "alpha_lr", "tau", "target_entropy"),
    "td3": ("lr", "critic_lr", "tau", "target_policy_noise", "exploration_noise"),
}
MAX_ENVS = 65_536  # per process; far above what fits in memory for MuJoCo tasks here


def available_cpus() -> int:
    """CPUs this process may run on (its affinity mask: SLURM's cpus_per_task, taskset)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def torch_threads_for(value: Any, cpus: int, jobs: int = 1) -> int:
    """``trainer.torch_threads`` as a count: an int as it is; ``auto``, this process's ``cpus``
    shared among the ``jobs`` a sweep runs side by side on the machine (at least 1)."""
    if value == "auto":
        return max(1, cpus // max(1, jobs))
    return int(value)


def async_worker_cap() -> int:
    """The most worker processes ``env.backend=gymnasium_async`` may start for one env (one per
    copy, ~50 MB each): 4 per CPU this process may use, at least 64. Beyond, copies wait for CPUs
    anyway and memory runs out (``env.num_envs=65536`` was accepted)."""
    return max(64, 4 * available_cpus())


@dataclass(frozen=True)
class Rule:
    """``check(value)`` is True for a good value; ``text`` completes "must be ..."."""

    check: Callable[[Any], bool]
    text: str


def _num(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def at_least(low: float, note: str = "") -> Rule:
    return Rule(lambda v: _num(v) and v >= low, f">= {low}{note}")


def above(low: float, note: str = "") -> Rule:
    return Rule(lambda v: _num(v) and v > low, f"> {low}{note}")


def between(low: float, high: float, note: str = "") -> Rule:
    return Rule(lambda v: _num(v) and low <= v <= high, f"in [{low}, {high}]{note}")


def one_of(*choices: str) -> Rule:
    return Rule(lambda v: v in choices, f"one of {list(choices)}")


def optional(rule: Rule, meaning: str) -> Rule:
    return Rule(lambda v: v is None or rule.check(v), f"null ({meaning}) or {rule.text}")


FLAG = Rule(lambda v: isinstance(v, bool), "true or false")
FINITE = Rule(_num, "a finite number")


def first_line(exc: BaseException) -> str:
    """An exception as one line (a KeyError's message without its quotes)."""
    text = str(exc.args[0] if isinstance(exc, KeyError) and exc.args else exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def is_safe_name(v: Any) -> bool:
    """One safe file-name component: what every name a run puts in a file name must be."""
    return (
        isinstance(v, str) and bool(SAFE_NAME.fullmatch(v)) and ".." not in v and len(v) <= MAX_NAME
    )


def _widths(v: Any) -> bool:
    return isinstance(v, list) and all(isinstance(w, int) and 1 <= w <= 65_536 for w in v)


def _names(v: Any) -> bool:
    return isinstance(v, list) and bool(v) and all(isinstance(n, str) and n.strip() for n in v)


def _sizes(low: int, high: int) -> Callable[[Any], bool]:
    return lambda v: (
        isinstance(v, list) and bool(v) and all(isinstance(w, int) and low <= w <= high for w in v)
    )


def _tags(v: Any) -> bool:
    return isinstance(v, list) and all(isinstance(t, str) and 0 < len(t) <= 64 for t in v)


SAFE = Rule(
    is_safe_name,
    f"a safe file name: letters, digits and . _ = + - (starting with a letter or digit, no '/' "
    f"or '..', at most {MAX_NAME} characters)",
)
BUILT = Rule(lambda v: True, "checked by building it once before the run starts")

#: dotted key -> rule. Every leaf field of the schema has an entry (tests/test_config_rules.py).
FIELD_RULES: dict[str, Rule] = {
    "seed": Rule(lambda v: isinstance(v, int) and 0 <= v <= MAX_SEED, f"in [0, {MAX_SEED}]"),
    # trainer
    "trainer.exp_name": SAFE,
    "trainer.total_frames": at_least(1),
    "trainer.iterations": optional(at_least(1), "use total_frames"),
    "trainer.frames_per_batch": at_least(1, ", a multiple of env.num_envs"),
    "trainer.device": Rule(
        lambda v: isinstance(v, str) and bool(DEVICE.fullmatch(v)), "auto, cpu, cuda or cuda:N"
    ),
    "trainer.strict_device": FLAG,
    "trainer.eval_every": at_least(0, " (0: no evaluation)"),
    "trainer.eval_episodes": at_least(0, " (0: no evaluation)"),
    "trainer.eval_async": Rule(
        lambda v: str(v).strip().lower() in ("auto", "true", "false"), "auto, true or false"
    ),
    "trainer.save_every": at_least(0, " (0: checkpoints only at the end and on a stop)"),
    "trainer.keep_last": Rule(lambda v: isinstance(v, int), "an integer (<= 0: keep all)"),
    "trainer.resume": Rule(
        lambda v: isinstance(v, str),
        "auto, never, or the path of a checkpoint of this env and policy (read before training)",
    ),
    "trainer.best_metric": one_of(*EVAL_METRICS),
    "trainer.nan_guard": FLAG,
    "trainer.log_every": at_least(1, " (iterations)"),
    "trainer.progress": FLAG,
    "trainer.torch_threads": Rule(
        lambda v: (
            v == "auto"
            or (isinstance(v, int) and not isinstance(v, bool) and 1 <= v <= available_cpus())
        ),
        "auto or in [1, the CPUs this process may use] (more threads than CPUs only slow it down)",
    ),
    "trainer.precision": Rule(
        lambda v: v in PRECISIONS,
        f"one of {list(PRECISIONS)} (bf16: mixed precision, float32 weights and loss maths, "
        "Lightning's 'bf16-mixed'; not with policy.memory)",
    ),
    "trainer.stall_timeout_s": above(
        0, " seconds (longer than an eval round and the first iteration)"
    ),
    "trainer.stop_grace_s": above(0, " seconds"),
    # policy
    "policy.name": one_of("actor_critic", "actor_only", "sac", "td3"),
    "policy.actor.hidden_sizes": Rule(_widths, "a list of widths in [1, 65536] ([]: linear)"),
    "policy.actor.activation": one_of(*ACTIVATIONS),
    "policy.critic.hidden_sizes": Rule(
        _widths, "a list of widths in [1, 65536] ([]: linear); actor_critic, sac and td3 only"
    ),
    "policy.critic.activation": Rule(
        lambda v: v in ACTIVATIONS, f"one of {list(ACTIVATIONS)}; actor_critic, sac and td3 only"
    ),
    "policy.init_log_std": Rule(_num, "a finite number in [min_log_std, max_log_std]"),
    "policy.min_log_std": between(-20.0, 20.0, ", below max_log_std"),
    "policy.max_log_std": between(-20.0, 20.0),
    "policy.ortho_init": FLAG,
    "policy.actor.observations": optional(
        Rule(_names, "a non-empty list of observation keys, key prefixes or group names"),
        "group 'policy'",
    ),
    "policy.critic.observations": optional(
        Rule(_names, "a non-empty list of observation keys, key prefixes or group names"),
        "every group; actor_critic only",
    ),
    "policy.encoder.name": one_of(*ENCODERS),
    "policy.encoder.channels": optional(
        Rule(_sizes(1, 4096), "a non-empty list of channel counts in [1, 4096]"),
        "nature [32, 64, 64], impala [16, 32, 32]",
    ),
    "policy.encoder.kernel_sizes": optional(
        Rule(
            _sizes(1, 64), "a list of kernel sizes in [1, 64], one per channels entry; nature only"
        ),
        "[8, 4, 3]",
    ),
    "policy.encoder.strides": optional(
        Rule(_sizes(1, 64), "a list of strides in [1, 64], one per channels entry; nature only"),
        "[4, 2, 1]",
    ),
    "policy.encoder.num_res_blocks": between(0, 16, " (impala: residual blocks per stage)"),
    "policy.encoder.features_dim": optional(between(1, 65_536), "nature 512, impala 256"),
    "policy.share_encoder": FLAG,
    "policy.memory.type": one_of(*MEMORY_TYPES),
    "policy.memory.hidden_size": between(1, 65_536),
    "policy.memory.num_layers": between(1, 16),
    "policy.memory.shared": FLAG,
    "policy.num_qvalue_nets": between(
        1, 16, " (Q networks; the target takes their minimum); sac, td3"
    ),
    "policy.normalize_observations": Rule(
        FLAG.check, "true or false (with env.normalize_observations); sac and td3 only"
    ),
    # algorithm
    "algorithm.name": Rule(
        lambda v: v in ("ppo", "grpo", "sac", "td3"),
        "one of ['ppo', 'grpo', 'sac', 'td3'] (chosen with algorithm=ppo / grpo / sac / td3; ppo "
        "needs policy.name=actor_critic, sac policy.name=sac, td3 policy.name=td3)",
    ),
    "algorithm.gamma": between(0.0, 1.0),
    "algorithm.lmbda": between(0.0, 1.0, "; ppo only"),
    "algorithm.clip_epsilon": above(0.0),
    "algorithm.entropy_coeff": at_least(0.0),
    "algorithm.critic_coeff": at_least(0.0, "; ppo only"),
    "algorithm.loss_critic_type": Rule(
        lambda v: v in ("l1", "l2", "smooth_l1"), "one of ['l1', 'l2', 'smooth_l1']; ppo only"
    ),
    "algorithm.normalize_advantage": Rule(FLAG.check, "true or false; ppo only"),
    "algorithm.clip_value": optional(above(0.0), "no value clipping; ppo only"),
    "algorithm.normalize_rewards": Rule(FLAG.check, "true or false; ppo only"),
    "algorithm.clip_rewards": optional(above(0.0), "no reward clipping; ppo only"),
    "algorithm.desired_kl": optional(
        above(0.0), "a fixed learning rate; ppo only, not with anneal_lr"
    ),
    "algorithm.overlap": Rule(
        FLAG.check,
        f"true or false; ppo only, env.backend one of {list(OVERLAP_BACKENDS)}, no events.train",
    ),
    "algorithm.sequence_length": Rule(
        lambda v: isinstance(v, int) and not isinstance(v, bool) and 1 <= v <= 65_536,
        "in [1, 65536] (steps per training sequence of a recurrent policy); ppo only",
    ),
    "algorithm.kl_coeff": at_least(0.0, " (0: no reference policy); grpo only"),
    "algorithm.group_size": between(2, MAX_ENVS, ", a divisor of env.num_envs; grpo only"),
    "algorithm.epsilon": above(0.0, "; grpo only"),
    "algorithm.reset_every_rollout": Rule(FLAG.check, "true or false; grpo only"),
    "algorithm.truncate_at_first_done": Rule(FLAG.check, "true or false; grpo only"),
    # sac and td3 (docs/sac.md, docs/td3.md)
    "algorithm.critic_lr": at_least(0.0, "; sac and td3 only"),
    "algorithm.tau": between(0.0, 1.0, " (1: hard target copies); sac and td3 only"),
    "algorithm.buffer_size": at_least(1, ", at least algorithm.batch_size; sac and td3 only"),
    "algorithm.buffer_storage": Rule(
        lambda v: v in ("auto", "memory", "memmap"),
        "one of ['auto', 'memory', 'memmap']; sac and td3 only",
    ),
    "algorithm.batch_size": at_least(1, ", at most algorithm.buffer_size; sac and td3 only"),
    "algorithm.learning_starts": at_least(0, " env steps; sac and td3 only"),
    "algorithm.updates_per_step": above(0.0, " (gradient steps per env step); sac and td3 only"),
    "algorithm.train_freq": at_least(1, " (env steps per env between updates); sac and td3 only"),
    "algorithm.n_step": between(1, 1000, "; sac and td3 only"),
    "algorithm.alpha_lr": at_least(0.0, "; sac only"),
    "algorithm.alpha_init": above(0.0, "; sac only"),
    "algorithm.fixed_alpha": Rule(FLAG.check, "true or false; sac only"),
    "algorithm.target_entropy": Rule(
        lambda v: v == "auto" or _num(v), "auto (-act_dim) or a finite number; sac only"
    ),
    "algorithm.policy_delay": at_least(1, "; td3 only"),
    "algorithm.target_policy_noise": at_least(0.0, "; td3 only"),
    "algorithm.target_noise_clip": at_least(0.0, "; td3 only"),
    "algorithm.exploration_noise": at_least(0.0, "; td3 only"),
    "algorithm.lr": at_least(0.0, " (0: the policy does not learn, a baseline)"),
    "algorithm.adam_eps": above(0.0),
    "algorithm.anneal_lr": FLAG,
    "algorithm.max_grad_norm": Rule(_num, "a finite number (<= 0: no clipping)"),
    "algorithm.num_epochs": at_least(1),
    "algorithm.mini_batch_size": at_least(1, ", at most trainer.frames_per_batch"),
    "algorithm.compile": Rule(
        lambda v: str(v).strip().lower() in ("auto", "true", "false"), "auto, true or false"
    ),
    # env
    "env.name": Rule(
        lambda v: isinstance(v, str) and bool(v.strip()),
        "a registered Gymnasium id (env=gym takes any: env=gym env.name=mymod:MyEnv-v0), a native "
        "task, or (vecenv, torchrl) package.module:callable (checked by building one env)",
    ),
    "env.backend": one_of(*BACKENDS),
    "env.num_threads": between(0, 1024, " (0: every CPU the process may use; envpool only)"),
    "env.device": Rule(
        lambda v: isinstance(v, str) and bool(DEVICE.fullmatch(v)),
        "auto, cpu, cuda or cuda:N (where a vecenv / torchrl env is built; cpu for the others)",
    ),
    "env.num_envs": between(1, MAX_ENVS),
    "env.num_eval_envs": between(0, MAX_ENVS, " (0: no evaluation)"),
    "env.max_episode_steps": optional(at_least(1), "the task's own limit"),
    "env.normalize_observations": FLAG,
    "env.clip_observations": above(0.0),
    "env.rescale_actions": Rule(
        lambda v: isinstance(v, bool),
        f"true or false; true only with env.backend one of {list(RESCALE_BACKENDS)} and a Box "
        "action space with finite bounds (checked by building one env)",
    ),
    "env.frame_stack": Rule(
        lambda v: isinstance(v, int) and 0 <= v <= 64,
        f"0 to 64 (0 or 1: off); above 1 only with env.backend one of {list(IMAGE_BACKENDS)} "
        "and an image observation (checked by building one env)",
    ),
    "env.action_mask": Rule(
        lambda v: v in ("auto", "info", "observation", "off"),
        "one of ['auto', 'info', 'observation', 'off'] (where the mask of valid categorical actions "
        f"comes from; info and observation only with env.backend one of {list(MASK_BACKENDS)})",
    ),
    "env.action_mask_key": Rule(
        lambda v: isinstance(v, str) and bool(v),
        "a non-empty info key or Dict observation key (the action mask's; default action_mask)",
    ),
    "env.image_keys": Rule(
        lambda v: isinstance(v, list | tuple) and all(isinstance(k, str) and k for k in v),
        "a list of observation keys (a Dict key path like cam/front, or pixels for the root) that "
        "are uint8 images; checked by building one env",
    ),
    "env.observation_indices": Rule(
        lambda v: (
            isinstance(v, list | tuple)
            and all(isinstance(i, int) and not isinstance(i, bool) and i >= 0 for i in v)
            and len(set(v)) == len(v)
        ),
        f"distinct indices >= 0 of a Box observation's entries, kept in the order given (empty: "
        f"every entry); only with env.backend one of {list(IMAGE_BACKENDS)} (each below the "
        "observation's width: checked by building one env)",
    ),
    "env.kwargs": Rule(
        lambda v: isinstance(v, dict),
        "keyword arguments the env accepts (checked by building one env; render_mode=human "
        "only where a display exists)",
    ),
    "env.native": Rule(
        lambda v: True,
        "the native task's terms (docs/native_tasks.md), checked by building one env",
    ),
    # events
    "events.train": Rule(
        lambda v: isinstance(v, dict),
        "events whose func is registered (or allowlisted), mode one of startup/reset/interval/"
        "step/trigger, interval_step >= 1, params as docs/events.md says",
    ),
    "events.eval": Rule(lambda v: isinstance(v, dict), "as events.train"),
    # hooks
    "hooks": Rule(
        lambda v: isinstance(v, dict),
        "hooks whose func is registered (or allowlisted): stop_at, stop_on_plateau, schedule, "
        "median_stop, piecewise, pbt or your own; params as docs/hooks.md (pbt: docs/pbt.md) "
        "says; a pbt hook only in a sweep (`-m`) of exactly `population_size` jobs on a parallel "
        "launcher",
    ),
    # logger
    "logger.tensorboard.enabled": FLAG,
    "logger.wandb.enabled": FLAG,
    "logger.wandb.project": Rule(
        lambda v: isinstance(v, str) and 0 < len(v) <= 128 and not set(v) & set("/\\#?%:"),
        "a non-empty W&B project name (at most 128 characters, none of / \\ # ? % :)",
    ),
    "logger.wandb.entity": optional(
        Rule(lambda v: isinstance(v, str) and bool(v.strip()), "a non-empty name"), "your default"
    ),
    "logger.wandb.mode": one_of("auto", "online", "offline", "disabled"),
    "logger.wandb.tags": Rule(_tags, "a list of tags of 1 to 64 characters"),
    "logger.jsonl": FLAG,
    "logger.console": FLAG,
}


_ABSENT = object()


def get(config: Any, key: str, default: Any = _ABSENT) -> Any:
    """The value at dotted ``key`` of a config dataclass (``default`` where a section does not have
    the key: ``algorithm.lmbda`` of GRPO's section; without a default that is an AttributeError)."""
    value = config
    for part in key.split("."):
        if default is not _ABSENT and not hasattr(value, part):
            return default
        value = getattr(value, part)
    return value


def rules_markdown() -> str:
    """The table of docs/config_rules.md."""
    rows = ["| key | rule |", "|---|---|"]
    rows += [f"| `{key}` | {rule.text} |" for key, rule in FIELD_RULES.items()]
    return "\n".join(rows) + "\n"
