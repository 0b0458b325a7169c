"""Batched torch envs named in the config: ``env.backend=vecenv`` (rsl_rl's ``VecEnv`` contract:
Isaac Lab, mjlab, Genesis, legged_gym wrappers) and ``env.backend=torchrl`` (any TorchRL ``EnvBase``
factory), built by a callable the config names as ``env.name=package.module:callable``
(docs/batched_envs.md).

A config file cannot import arbitrary code: the callable is a name a plugin registered
(``register_env_factory``), or is a function or class defined in a module under an allowed prefix:
``rlexp.envs.`` and ``torchrl.envs.``, those a plugin adds (``allow_env_module``), and those the user's shell lists in
``RLEXP_ENV_MODULES`` (comma-separated prefixes; the shell decides, not a config file).

The callable gets ``env.kwargs`` as keywords, plus ``num_envs``, ``device`` (``env.device``
resolved: ``auto`` -> ``cuda`` when a GPU is visible) and ``seed`` where its signature names
parameters of those names. Without a ``num_envs`` parameter the env keeps its own count, which must
then be ``env.num_envs``.
"""

from __future__ import annotations

import inspect
import logging
import os
import re
from collections.abc import Callable
from typing import Any

from torchrl.envs import EnvBase

from rlexp.common.registry import (
    check_module_name,
    choices_hint,
    module_of,
    reach,
    strings_in,
    under,
)
from rlexp.config.rules import first_line
from rlexp.config.schema import EnvConfig

log = logging.getLogger(__name__)

#: Registered env factories: name -> callable (``register_env_factory``).
ENV_FACTORIES: dict[str, Callable[..., Any]] = {}
#: Module prefixes whose callables a config may name (plus ``RLEXP_ENV_MODULES``).
_ALLOWED_MODULES: list[str] = ["rlexp.envs.", "torchrl.envs."]
#: The shell variable listing more allowed module prefixes (comma-separated).
ENV_MODULES_VAR = "RLEXP_ENV_MODULES"
#: What rlexp passes when the callable's signature names it.
PASSED = ("num_envs", "device", "seed")


def register_env_factory(name: str, fn: Callable[..., Any]) -> None:
    """Make ``fn`` available to configs as ``env.name=<name>`` (a plugin's ``register``)."""
    if not callable(fn):
        raise TypeError(f"register_env_factory({name!r}, ...): {fn!r} is not callable")
    ENV_FACTORIES[name] = fn


def allow_env_module(prefix: str) -> None:
    """Let configs name env callables in modules under ``prefix`` (from Python code only)."""
    prefix = prefix if prefix.endswith(".") else prefix + "."
    if prefix not in _ALLOWED_MODULES:
        _ALLOWED_MODULES.append(prefix)


def allowed_modules() -> list[str]:
    """The allowed prefixes now: rlexp's, the plugins', and the shell's ``RLEXP_ENV_MODULES``."""
    shell = [p.strip() for p in os.environ.get(ENV_MODULES_VAR, "").split(",") if p.strip()]
    extra = [p if p.endswith(".") else p + "." for p in shell]
    return [*_ALLOWED_MODULES, *(p for p in extra if p not in _ALLOWED_MODULES)]


def _ways_to_allow(where: str, module: str) -> str:
    top = module.split(".")[0]
    return (
        f"{where}: module {module!r} is not allowed (a config may not import arbitrary code; "
        f"allowed: {allowed_modules()}); allow it from the shell with {ENV_MODULES_VAR}={top}, "
        f"from a plugin with rlexp.envs.batched.allow_env_module({top!r}), or register the "
        "callable with rlexp.envs.batched.register_env_factory(name, fn) (docs/batched_envs.md)"
    )


def resolve_env_factory(name: str, backend: str) -> Callable[..., Any]:
    """The callable ``env.name`` names: registered, or ``package.module:callable`` in an allowed
    module; a ValueError of one line naming ``env.name`` otherwise."""
    where = f"env.name={name!r} (env.backend={backend})"
    if name in ENV_FACTORIES:
        return ENV_FACTORIES[name]
    if ":" not in name:
        known = sorted(ENV_FACTORIES)
        hint = choices_hint(name, known) if known else "; no env factory is registered"
        raise ValueError(
            f"{where} is not a registered env factory{hint}; name a callable as "
            "package.module:callable (docs/batched_envs.md)"
        )
    module, _, attr = name.partition(":")
    if not module or not attr or ":" in attr:
        raise ValueError(f"{where}: expected package.module:callable (one ':')")
    check_module_name(module, where, None)  # public parts, not the standard library
    if not under(module, allowed_modules()):
        raise ValueError(_ways_to_allow(where, module))
    fn = reach(module, attr, where, allowed_modules())
    if backend == "torchrl" and inspect.isclass(fn) and not issubclass(fn, EnvBase):
        raise ValueError(
            f"{where}: {module}.{attr} is a class but not a TorchRL EnvBase; name an EnvBase "
            "subclass or a function that returns one"
        )
    return fn


def resolve_env_device(device: str) -> str:
    """``env.device`` as a torch device string: ``auto`` -> ``cuda`` where a GPU is visible
    (``cuda:<local rank>`` in a distributed run); ``cuda`` on a machine without one -> ``cpu`` with
    one warning (a run's saved config still evaluates and exports there)."""
    from rlexp.runtime import distributed
    from rlexp.runtime.devices import resolve_device

    resolved = resolve_device(device, key="env.device")
    dist = distributed.info()
    if resolved == "cuda" and dist.enabled:  # each rank's envs on its own GPU, as its policy
        return f"cuda:{dist.local_rank}"
    return resolved


def factory_arguments(
    fn: Callable[..., Any], cfg: EnvConfig, num_envs: int, device: str, seed: int
) -> tuple[dict[str, Any], bool]:
    """The keywords to call ``fn`` with (``env.kwargs`` and those of ``PASSED`` it names), and
    whether it takes ``num_envs``; a TypeError of one line for a kwarg it does not take."""
    where = f"env.name={cfg.name!r}"
    kwargs = dict(cfg.kwargs or {})
    for key in PASSED:
        if key in kwargs:
            raise TypeError(
                f"{where}: env.kwargs.{key} is set by rlexp (env.num_envs, env.device, seed); "
                "remove it from env.kwargs"
            )
    try:
        params = inspect.signature(fn).parameters
    except (TypeError, ValueError):  # a builtin or C callable: pass env.kwargs alone
        return kwargs, False
    named = {n for n, p in params.items() if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)}
    if not any(p.kind is p.VAR_KEYWORD for p in params.values()):
        unknown = sorted(set(kwargs) - named)
        if unknown:
            raise TypeError(
                f"{where}: env.kwargs.{unknown[0]} is not a parameter of the callable (its "
                f"parameters: {sorted(named)})"
            )
    given = {"num_envs": num_envs, "device": device, "seed": seed}
    kwargs.update({k: v for k, v in given.items() if k in named})
    return kwargs, "num_envs" in named


def make_batched_env(cfg: EnvConfig, num_envs: int, seed: int) -> EnvBase:
    """``num_envs`` copies of the env ``env.name`` builds, on ``env.device``, as an rlexp env
    (``VecEnvAdapter`` or ``TorchRLAdapter``): flat float32 observations, rlexp's action spec,
    autoreset with the true final observation in ``"next"``, resume through the env's state."""
    where = f"env.name={cfg.name!r}"
    if cfg.max_episode_steps is not None:
        raise ValueError(
            f"{where}: env.max_episode_steps={cfg.max_episode_steps} applies to Gymnasium envs; "
            f"an env.backend={cfg.backend} env keeps its own time limit (pass it in env.kwargs)"
        )
    fn = resolve_env_factory(cfg.name, cfg.backend)
    for key, value in strings_in(cfg.kwargs or {}):  # torchrl.envs:GymEnv's env_name='mod:Id'
        module = module_of(value)
        if module is not None:
            check_module_name(module, f"{where}: env.kwargs.{key}={value!r}", None)
    device = resolve_env_device(cfg.device)
    kwargs, takes_count = factory_arguments(fn, cfg, num_envs, device, seed)
    try:
        raw = fn(**kwargs)
    except Exception as exc:
        unexpected = re.search(r"unexpected keyword argument '([^']+)'", first_line(exc))
        if isinstance(exc, TypeError) and unexpected and unexpected.group(1) in cfg.kwargs:
            raise TypeError(
                f"{where}: env.kwargs.{unexpected.group(1)} is not a parameter of the callable "
                f"(it passed it on to something that refused it: {first_line(exc)})"
            ) from None
        raise ValueError(
            f"{where}: building the env failed ({type(exc).__name__}: {first_line(exc)})"
        ) from None
    if cfg.backend == "vecenv":
        from rlexp.envs.vecenv import VecEnvAdapter

        if isinstance(raw, EnvBase):
            raise TypeError(
                f"{where} built a TorchRL {type(raw).__name__}; use env.backend=torchrl for a "
                "TorchRL EnvBase"
            )
        env: EnvBase = VecEnvAdapter(raw, cfg.name, cfg.action_mask, cfg.action_mask_key)
    else:
        from rlexp.envs.torchrl_env import TorchRLAdapter

        if not isinstance(raw, EnvBase):
            raise TypeError(
                f"{where} built a {type(raw).__name__}, not a TorchRL EnvBase; use "
                "env.backend=vecenv for an rsl_rl-style VecEnv"
            )
        # An EnvBase already in rlexp's shape (its own step_action / autoreset_observation and
        # observation layout, e.g. a TensorDict observation of vector + uint8 images) as it is.
        native = all(
            hasattr(raw, a) for a in ("step_action", "autoreset_observation", "obs_layout")
        )
        env = raw if native else TorchRLAdapter(raw, cfg.name)
    count = env.num_envs
    if not takes_count and count != cfg.num_envs:
        env.close()
        raise ValueError(
            f"{where} builds {count} env{'' if count == 1 else 's'} (the callable takes no "
            f"num_envs parameter: its own count) but env.num_envs={cfg.num_envs}; set "
            f"env.num_envs={count} or give the "
            "callable a num_envs parameter"
        )
    if takes_count and count != num_envs:
        env.close()
        raise ValueError(f"{where}: asked for num_envs={num_envs}, the env has {count}")
    return env
