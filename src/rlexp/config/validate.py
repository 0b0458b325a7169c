"""Convert the composed DictConfig into typed dataclasses once, and check every value.

Below the entry point no code reads a DictConfig: it gets a ``RootConfig`` and its parts.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import os
import re
from typing import Any

from omegaconf import DictConfig, OmegaConf

from rlexp.config.aliases import alias_hint
from rlexp.config.memory import memory_problem
from rlexp.config.offpolicy_checks import (
    derive_frames_per_batch,
    is_off_policy,
    off_policy_problem,
)
from rlexp.config.rules import (
    ACTIVATIONS,
    FIELD_RULES,
    IMAGE_BACKENDS,
    MASK_BACKENDS,
    MAX_NAME,
    MUTABLE_HYPERPARAMETERS,
    OVERLAP_BACKENDS,
    RESCALE_BACKENDS,
    available_cpus,
    get,
    is_safe_name,
)
from rlexp.config.schema import (
    VARIANT_OPTIONS,
    VARIANTS,
    GRPOConfig,
    HookConfig,
    RootConfig,
)

_ABSENT = object()


class ConfigError(ValueError):
    """A config value that cannot run; the message names the dotted key, the value and the fix."""


def to_root_config(cfg: DictConfig | dict[str, Any]) -> RootConfig:
    """Typed, validated config from Hydra's composed config (or a plain dict, e.g. a checkpoint's)."""
    if not isinstance(cfg, DictConfig):  # a plain dict (a checkpoint's): its strings are data
        cfg = OmegaConf.merge(structured_root(cfg), escape_interpolations(cfg))
    check_known_keys(cfg)
    config = OmegaConf.to_object(cfg)
    if not isinstance(config, RootConfig):
        raise ConfigError("the composed config does not use the rlexp_schema root schema")
    config.hooks = typed_hooks(config.hooks)
    derive_frames_per_batch(config)  # sac / td3: env.num_envs * algorithm.train_freq
    validate(config)
    return config


def typed_hooks(hooks: Any) -> dict[str, HookConfig]:
    """``hooks`` (name -> ``{func, params}``, as the command line's ``+hooks.x.func=...`` adds it)
    as HookConfigs; a key other than func / params, or a missing func, names the hook."""
    if not isinstance(hooks, dict):
        raise ConfigError(f"hooks={hooks!r} must be a mapping of hook names to {{func, params}}")
    out: dict[str, HookConfig] = {}
    fields = [f.name for f in dataclasses.fields(HookConfig)]
    for name, value in hooks.items():
        where = f"hooks.{name}"
        if isinstance(value, HookConfig):
            value = dataclasses.asdict(value)
        if not isinstance(value, dict):
            raise ConfigError(f"{where}={value!r} must be {{func: <hook>, params: {{...}}}}")
        for key in value:
            if key not in fields:
                close = difflib.get_close_matches(str(key), fields, n=1)
                raise ConfigError(
                    f"{where}.{key} is not a hook key (a hook has {fields})"
                    + (f"; did you mean {where}.{close[0]}?" if close else "")
                )
        if not isinstance(value.get("func"), str) or not value["func"]:
            raise ConfigError(
                f"{where}.func is missing: name the hook's function, e.g. "
                f"+{where}.func=stop_at +{where}.params.threshold=3000"
            )
        params = value.get("params") or {}
        if not isinstance(params, dict):
            raise ConfigError(f"{where}.params={params!r} must be a mapping of parameters")
        out[str(name)] = HookConfig(func=value["func"], params=dict(params))
    return out


def structured_root(plain: dict[str, Any]) -> DictConfig:
    """The root schema for the plain dict ``plain``, its policy and algorithm sections typed by the
    schema their ``name`` names (``grpo`` -> GRPOConfig), so that their own keys merge."""
    root = OmegaConf.structured(RootConfig)
    for section, variants in VARIANTS.items():
        node = plain.get(section) if isinstance(plain, dict) else None
        name = node.get("name") if isinstance(node, dict) else None
        if name in variants:
            root[section] = OmegaConf.structured(variants[name])
    return root


def to_dict(config: RootConfig) -> dict[str, Any]:
    """Plain-dict form of a config (for checkpoints, loggers and JSON). Its strings are the values
    themselves: a ``${...}`` a JSON file gave stays those characters (OmegaConf would resolve it)."""
    return dataclasses.asdict(config)


def total_frames(config: RootConfig, world_size: int = 1) -> int:
    """Env steps to train for, summed over envs and processes (``iterations`` counts batches of
    ``frames_per_batch`` per process)."""
    t = config.trainer
    return (
        t.iterations * t.frames_per_batch * world_size
        if t.iterations is not None
        else t.total_frames
    )


#: Typed float fields that may be infinite (every other float must be finite).
INFINITE_OK: tuple[str, ...] = ()


def check_known_keys(cfg: DictConfig, prefix: str = "") -> None:
    """Keys that the schema does not have: ``+trainer.foo=1`` (Hydra adds it past the schema, and
    ``to_object`` would drop it silently) or a key in an experiment file."""
    obj_type = OmegaConf.get_type(cfg)
    if dataclasses.is_dataclass(obj_type):
        fields = [f.name for f in dataclasses.fields(obj_type)]
        for key in cfg.keys():
            if key not in fields:
                where = f"{prefix}{key}"
                close = difflib.get_close_matches(str(key), fields, n=1)
                hint = f"; did you mean {prefix}{close[0]}?" if close else ""
                known = alias_hint(where)  # another library's name: its key here, not a guess
                hint = f"; {known}" if known else hint
                raise ConfigError(
                    f"{where} is not a config key (the {prefix.rstrip('.') or 'root'} section has "
                    f"{sorted(fields)}){hint}"
                )
    for key in cfg.keys():
        node = cfg._get_node(key)
        if isinstance(node, DictConfig) and not node._is_none() and not node._is_missing():
            check_known_keys(node, f"{prefix}{key}.")


def _check_floats(obj: Any, where: str, typed: bool) -> None:
    """NaN anywhere, and infinity in a typed float field, is an error naming the key."""
    if isinstance(obj, float):
        if math.isnan(obj) or (typed and math.isinf(obj) and where not in INFINITE_OK):
            raise ConfigError(f"{where}={obj} must be a finite number")
    elif dataclasses.is_dataclass(obj):
        for f in dataclasses.fields(obj):
            _check_floats(getattr(obj, f.name), f"{where}.{f.name}".lstrip("."), True)
    elif isinstance(obj, dict):
        for k, v in obj.items():
            _check_floats(v, f"{where}.{k}", False)
    elif isinstance(obj, (list, tuple)):
        for i, v in enumerate(obj):
            _check_floats(v, f"{where}[{i}]", False)


def check_name(key: str, value: str) -> None:
    """``value`` becomes part of a file name: one safe path component, of a sane length."""
    if not isinstance(value, str) or not is_safe_name(value[:MAX_NAME]):
        raise ConfigError(
            f"{key}={value!r} is not a safe file name: use letters, digits and . _ = + - "
            "(starting with a letter or digit, no '/' or '..')"
        )
    if len(value) > MAX_NAME:
        raise ConfigError(f"{key} is {len(value)} characters long; at most {MAX_NAME}")


def validate(config: RootConfig) -> None:
    """Every field against its rule (``rlexp.config.rules``), then the rules between fields."""
    t, e, a, p = config.trainer, config.env, config.algorithm, config.policy
    _check_floats(config, "", True)
    check_name("trainer.exp_name", t.exp_name)
    for part in ("actor", "critic"):
        if not hasattr(p, part):
            continue
        act = getattr(p, part).activation
        if act not in ACTIVATIONS:
            close = difflib.get_close_matches(str(act), ACTIVATIONS, n=1)
            raise ConfigError(
                f"policy.{part}.activation={act!r}; choose from {list(ACTIVATIONS)}"
                + (f"; did you mean {close[0]!r}?" if close else "")
            )
    _check_variants(config)
    for key, rule in FIELD_RULES.items():
        value = get(config, key, _ABSENT)
        if value is _ABSENT:  # a key of another variant (algorithm.lmbda under GRPO)
            continue
        if not rule.check(value):
            if key == "trainer.torch_threads":
                raise ConfigError(
                    f"trainer.torch_threads={value} must be auto or in [1, {available_cpus()}]: "
                    "this process may use that many CPUs (more threads only slow it down, and very "
                    "many crash torch)"
                )
            raise ConfigError(f"{key}={value!r} must be {rule.text}")
    # -- between fields --
    _check_async_workers(e)
    if t.frames_per_batch % e.num_envs:
        raise ConfigError(
            f"trainer.frames_per_batch={t.frames_per_batch} must be a positive multiple of "
            f"env.num_envs={e.num_envs} (each env contributes frames_per_batch / num_envs steps)"
        )
    problem = off_policy_problem(config)
    if problem is not None:
        raise ConfigError(problem)
    if a.mini_batch_size > t.frames_per_batch and not is_off_policy(a):
        raise ConfigError(
            f"algorithm.mini_batch_size={a.mini_batch_size} must be in "
            f"[1, trainer.frames_per_batch={t.frames_per_batch}]"
        )
    if isinstance(a, GRPOConfig) and e.num_envs % a.group_size:
        raise ConfigError(
            f"algorithm.group_size={a.group_size} must divide env.num_envs={e.num_envs}: groups "
            "are blocks of consecutive envs (envs 0..group_size-1 are group 0); set env.num_envs "
            f"to a multiple of {a.group_size} (e.g. env.num_envs={a.group_size * 4})"
        )
    if str(t.eval_async).strip().lower() == "true" and config.events.eval:
        raise ConfigError(
            f"trainer.eval_async=true: events.eval ({', '.join(config.events.eval)}) run in the "
            "training process's eval env, not in the eval worker; use trainer.eval_async=auto "
            "(evaluates in-process for such configs) or false"
        )
    if t.best_metric == "eval/success_rate" and e.backend != "native":
        raise ConfigError(
            f"trainer.best_metric=eval/success_rate: {e.name} ({e.backend}) defines no success, "
            "so no eval round reports it; use trainer.best_metric=eval/episode_return"
        )
    desired_kl = getattr(a, "desired_kl", None)
    if desired_kl is not None and a.anneal_lr:
        raise ConfigError(
            f"algorithm.desired_kl={desired_kl} and algorithm.anneal_lr=true both set the learning "
            "rate; use one: algorithm.anneal_lr=false or algorithm.desired_kl=null (docs/ppo.md)"
        )
    if e.rescale_actions and e.backend not in RESCALE_BACKENDS:
        raise ConfigError(
            f"env.rescale_actions=true maps the policy's [-1, 1] onto a Gymnasium Box's bounds; "
            f"env.backend={e.backend!r} does not: use one of {list(RESCALE_BACKENDS)}, or "
            "env.rescale_actions=false"
        )
    if e.action_mask in ("info", "observation") and e.backend not in MASK_BACKENDS:
        raise ConfigError(
            f"env.action_mask={e.action_mask}: env.backend={e.backend!r} does not read action "
            f"masks; use one of {list(MASK_BACKENDS)}, or env.action_mask=off"
        )
    if (e.frame_stack > 1 or e.image_keys) and e.backend not in IMAGE_BACKENDS:
        what = f"env.frame_stack={e.frame_stack}" if e.frame_stack > 1 else "env.image_keys"
        raise ConfigError(
            f"{what}: env.backend={e.backend!r} does not read images; use one of "
            f"{list(IMAGE_BACKENDS)} (a torchrl env's uint8 entries are images as they are), or "
            f"drop {what.split('=')[0]}"
        )
    if e.observation_indices and e.backend not in IMAGE_BACKENDS:
        raise ConfigError(
            f"env.observation_indices={list(e.observation_indices)}: env.backend={e.backend!r} "
            f"builds its observation itself; use one of {list(IMAGE_BACKENDS)}, or choose the "
            "entries where the env is defined (a native task's env.native.observations, a "
            "vecenv / torchrl factory's own observation), and drop env.observation_indices"
        )
    if getattr(a, "overlap", False) and e.backend not in OVERLAP_BACKENDS:
        raise ConfigError(
            f"algorithm.overlap=true steps the training envs in a collection process; "
            f"env.backend={e.backend!r} cannot move there: use one of {list(OVERLAP_BACKENDS)}, "
            "or algorithm.overlap=false"
        )
    cameras = [
        k for k, t in ((e.native.observations or {}) if e.native is not None else {}).items()
        if (t.get("func") if isinstance(t, dict) else getattr(t, "func", None)) == "camera_image"
    ]  # fmt: skip
    if getattr(a, "overlap", False) and e.backend == "native" and cameras:
        raise ConfigError(
            f"algorithm.overlap=true: env.native.observations.{cameras[0]} renders with OpenGL, "
            "which does not survive the fork into the collection process; set "
            "algorithm.overlap=false"
        )
    if getattr(a, "overlap", False) and config.events.train:
        raise ConfigError(
            f"algorithm.overlap=true: events.train ({', '.join(config.events.train)}) act on the "
            "training envs, which the collection process owns; remove them or set "
            "algorithm.overlap=false"
        )
    if a.name == "ppo" and getattr(p, "critic", None) is None:
        raise ConfigError(
            f"algorithm=ppo needs a critic, but policy.name={p.name!r} has none; use "
            "policy=mlp (actor_critic), or algorithm=grpo"
        )
    if not p.min_log_std < p.max_log_std:
        raise ConfigError(
            f"policy.min_log_std={p.min_log_std} must be below policy.max_log_std={p.max_log_std}"
        )
    if not p.min_log_std <= p.init_log_std <= p.max_log_std:
        raise ConfigError(
            f"policy.init_log_std={p.init_log_std} must be in [policy.min_log_std={p.min_log_std}, "
            f"policy.max_log_std={p.max_log_std}]"
        )
    _check_encoder(p)
    memory = memory_problem(config)
    if memory is not None:
        raise ConfigError(memory)
    if e.backend == "native" and e.native is None:
        raise ConfigError(
            f"env.backend=native needs env.native (env.name={e.name!r}); use env=push_cube or "
            "env=cart_pole"
        )
    if e.kwargs and e.backend == "native":
        raise ConfigError(
            f"env.kwargs={dict(e.kwargs)} is for Gymnasium envs (gymnasium.make's keyword "
            f"arguments); the native task {e.name!r} takes its settings under env.native "
            "(docs/native_tasks.md)"
        )
    _check_render_mode(e.kwargs)
    _check_events(config)
    _check_hooks(config)


def _check_encoder(p: Any) -> None:
    """The Nature CNN's conv layers: one channel count, kernel size and stride each."""
    enc = p.encoder
    if enc.name != "nature":
        if enc.kernel_sizes is not None or enc.strides is not None:
            raise ConfigError(
                f"policy.encoder.kernel_sizes / strides are the nature encoder's; "
                f"policy.encoder.name={enc.name!r} has fixed 3x3 convs: set them to null"
            )
        return
    lengths = {
        "channels": len(enc.channels or (32, 64, 64)),
        "kernel_sizes": len(enc.kernel_sizes or (8, 4, 3)),
        "strides": len(enc.strides or (4, 2, 1)),
    }
    if len(set(lengths.values())) > 1:
        given = ", ".join(f"policy.encoder.{k}={getattr(enc, k)}" for k in lengths)
        raise ConfigError(
            f"{given}: the nature encoder needs one entry per conv layer in each (the defaults "
            "have 3: [32, 64, 64], [8, 4, 3], [4, 2, 1]); give all three lists the same length"
        )


def _check_async_workers(e: Any) -> None:
    """``env.backend=gymnasium_async`` starts one process per copy: at most ``async_worker_cap()``."""
    from rlexp.config.rules import async_worker_cap

    if e.backend != "gymnasium_async":
        return
    cap = async_worker_cap()
    for key, n in (("env.num_envs", e.num_envs), ("env.num_eval_envs", e.num_eval_envs)):
        if n > cap:
            raise ConfigError(
                f"{key}={n} with env.backend=gymnasium_async would start {n} worker processes "
                f"(one per copy); the cap here is {cap} (4 per CPU, at least 64): use {key}<={cap}, "
                "or env.backend=gymnasium (every copy in the training process)"
            )


def _check_variants(config: RootConfig) -> None:
    """``policy.name`` / ``algorithm.name`` must be the name of the section's schema: the schema is
    chosen with the group (``algorithm=grpo``), and setting only the name cannot change it."""
    for section in VARIANTS:
        node = getattr(config, section)
        name = node.name
        expected = next((n for n, cls in VARIANTS[section].items() if type(node) is cls), None)
        if name == expected:
            continue
        options = VARIANT_OPTIONS[section]
        if name in VARIANTS[section]:
            raise ConfigError(
                f"{section}.name={name!r}, but the {section} section was composed for {expected!r}: "
                f"choose {section}={options[name]} instead of setting the name"
            )
        raise ConfigError(f"{section}.name={name!r} must be one of {sorted(VARIANTS[section])}")


def _check_render_mode(kwargs: dict[str, Any]) -> None:
    mode = kwargs.get("render_mode")
    if mode in (None, "rgb_array", "depth_array", "rgbd_tuple"):
        return
    if mode == "human" and (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        return
    raise ConfigError(
        f"env.kwargs.render_mode={mode!r} cannot work here"
        + (" (no display: DISPLAY is not set)" if mode == "human" else "")
        + "; rlexp renders offscreen: use render_mode=rgb_array, or events=eval_video for videos"
    )


def _check_events(config: RootConfig) -> None:
    """Every event names a known function and mode (the registry imports torch: only when used)."""
    events = {"events.train": config.events.train, "events.eval": config.events.eval}
    if not any(events.values()):
        return
    from rlexp.events.manager import check_event

    for where, group in events.items():
        for name, ev in group.items():
            try:
                check_event(ev, f"{where}.{name}")
            except (ValueError, KeyError, TypeError) as exc:
                raise ConfigError(str(exc.args[0] if exc.args else exc)) from None


def _check_hooks(config: RootConfig) -> None:
    """Every hook names a registered function (or allowlisted path) and its parameters fit it."""
    if not config.hooks:
        return
    from rlexp.hooks import check_hook

    a = config.algorithm
    mutable = [
        n
        for n in MUTABLE_HYPERPARAMETERS[a.name]
        if n != "kl_coeff" or getattr(a, "kl_coeff", 0.0) > 0
    ]
    for name, hook in config.hooks.items():
        where = f"hooks.{name}"
        if not is_safe_name(name):
            raise ConfigError(f"{where}: a hook name must be a safe name (letters, digits, _)")
        try:
            check_hook(hook.func, hook.params, where)
        except (ValueError, KeyError, TypeError) as exc:
            raise ConfigError(str(exc.args[0] if exc.args else exc)) from None
        if hook.func == "pbt":
            check_pbt_names(hook.params, where, mutable, a.name)
        if hook.func not in ("schedule", "piecewise"):
            continue
        target = hook.params.get("name")
        if target not in mutable:
            close = difflib.get_close_matches(str(target), mutable, n=1)
            raise ConfigError(
                f"{where}.params.name={target!r} is not a mutable hyperparameter of "
                f"algorithm={a.name}; choose from {mutable}"
                + (f"; did you mean {close[0]!r}?" if close else "")
            )
        if target == "lr" and getattr(a, "desired_kl", None) is not None:
            raise ConfigError(
                f"algorithm.desired_kl={a.desired_kl} and {where} (a schedule of lr) both set the "
                "learning rate; use one: drop the hook or set algorithm.desired_kl=null "
                "(docs/ppo.md)"
            )
        if target == "lr" and a.anneal_lr and hook.func == "schedule":  # piecewise: a PBT replay
            raise ConfigError(
                f"{where} schedules lr while algorithm.anneal_lr=true: that anneals the learning "
                "rate twice; use one of them"
            )


def check_pbt_names(params: Any, where: str, mutable: list[str], algorithm: str) -> None:
    """PBT tunes mutable hyperparameters only (``hooks.<name>.params.hyperparameters``)."""
    from rlexp.pbt.config import PBTConfig

    for name in PBTConfig.from_params(dict(params), where).hyperparameters:
        if name not in mutable:
            close = difflib.get_close_matches(name, mutable, n=1)
            raise ConfigError(
                f"{where}.params.hyperparameters.{name} is not a mutable hyperparameter of "
                f"algorithm={algorithm}; choose from {mutable}"
                + (f"; did you mean {close[0]!r}?" if close else "")
            )


_INTERPOLATION = re.compile(r"(\\*)\$\{")


def escape_interpolations(value: Any) -> Any:
    """``value`` with every string escaped so that OmegaConf reads it back literally: a string from
    a file is data, and ``"${oc.env:WANDB_API_KEY}"`` must stay those characters, not become the key
    (nor a path outside the run dir). OmegaConf reads ``\\${`` as a literal ``${`` and ``\\\\`` before
    ``${`` as one backslash: a run of n backslashes before ``${`` becomes 2n + 1."""
    if isinstance(value, str):
        return _INTERPOLATION.sub(lambda m: "\\" * (2 * len(m.group(1)) + 1) + "${", value)
    if isinstance(value, dict):
        return {k: escape_interpolations(v) for k, v in value.items()}
    if isinstance(value, list):
        return [escape_interpolations(v) for v in value]
    return value
