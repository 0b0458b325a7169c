"""The command line, checked before Hydra creates a run dir: one line and exit 2 for a bad input.

``python train.py`` composes ``conf/`` here first, with the same overrides Hydra will use: an
unknown key ("did you mean"), a misspelled group option, a key that ``+`` would add past the typed
schema, a value the validation refuses, or a config that cannot be built (unknown env, activation,
event, a resume checkpoint that does not fit) fails now, before anything is written. In a sweep
(``-m``) the keys and options of every override are checked; the values of sweep overrides are
checked by each job, and a job that fails records it in its own dir (docs/faults.md).
"""

from __future__ import annotations

import dataclasses
import difflib
import typing
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from rlexp.config.aliases import alias_hint
from rlexp.config.schema import RootConfig
from rlexp.config.validate import ConfigError

#: Hydra flags after which rlexp leaves the command line to Hydra alone (it prints, not runs, or it
#: composes another primary config). ``--config-dir`` (a user's configs) is checked like the rest.
_HYDRA_ONLY = ("help", "hydra_help", "cfg", "info", "shell_completion", "config_path",
               "config_name", "experimental_rerun")  # fmt: skip


def _unwrap(tp: Any) -> Any:
    """``X | None`` -> ``X``."""
    args = [a for a in typing.get_args(tp) if a is not type(None)]
    if typing.get_origin(tp) in (typing.Union, getattr(__import__("types"), "UnionType", None)):
        return args[0] if len(args) == 1 else Any
    return tp


def check_key(key: str, add: bool = False) -> None:
    """``key`` (dotted) must name a field of the typed schema; below a free dict anything goes."""
    tp: Any = RootConfig
    parts = key.split(".")
    for i, part in enumerate(parts):
        where = ".".join(parts[: i + 1])
        tp = _unwrap(tp)
        if dataclasses.is_dataclass(tp):
            hints = typing.get_type_hints(tp)
            for variant in _variants(
                tp
            ):  # algorithm.kl_coeff: a key of one of the sections' schemas
                hints = {**typing.get_type_hints(variant), **hints}
            if part not in hints:
                section = ".".join(parts[:i]) or "the root"
                close = difflib.get_close_matches(part, list(hints), n=1)
                hint = f"; did you mean {'.'.join([*parts[:i], close[0]])}?" if close else ""
                known = alias_hint(where)  # another library's name: its key here, not a guess
                hint = f"; {known}" if known else hint
                extra = " ('+' adds keys only below free dicts such as env.kwargs)" if add else ""
                raise ConfigError(
                    f"{where} is not a config key ({section} has {sorted(hints)}){hint}{extra}"
                )
            tp = hints[part]
        elif typing.get_origin(tp) is dict:
            tp = typing.get_args(tp)[1]  # a free name (an event, a kwarg): its value's type next
        elif tp is Any or typing.get_origin(tp) is list:
            return
        else:
            raise ConfigError(f"{'.'.join(parts[:i])} is a value, not a section: cannot set {key}")


def _variants(tp: Any) -> list[type]:
    """The schemas a section typed ``tp`` may hold (GRPOConfig for BaseAlgorithmConfig)."""
    from rlexp.config.schema import VARIANTS

    return [
        cls
        for group in VARIANTS.values()
        for cls in group.values()
        if cls is not tp and issubclass(cls, tp)
    ]


def _check_option(loader: Any, group: str, option: str) -> None:
    options = [o for o in loader.get_group_options(group) if not o.endswith("_schema")]
    if option in options:
        return
    close = difflib.get_close_matches(option, options, n=1)
    raise ConfigError(
        f"{group}={option} is not an option of {group}; choose from {options}"
        + (f"; did you mean {group}={close[0]}?" if close else "")
    )


def check_overrides(overrides: Sequence[str], loader: Any) -> list[str]:
    """Check every override's key (or group option); return the overrides to compose with (sweep
    overrides replaced by their first value where Hydra can enumerate them, else left out)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    try:
        parsed = OverridesParser.create().parse_overrides(list(overrides))
    except HydraException as exc:
        raise ConfigError(str(exc).strip().splitlines()[0]) from None
    compose_with = []
    for o in parsed:
        key = o.key_or_group
        if key.startswith("hydra") or o.package is not None:
            compose_with.append(o.input_line)
            continue
        values: list[Any] = []
        if o.is_sweep_override():
            try:
                values = list(o.sweep_string_iterator())
            except HydraException:  # interval sweeps (Optuna): keys are checked, values by the jobs
                values = []
        elif not o.is_delete():
            values = [o.value()]
        if loader.repository.group_exists(key):
            for value in values:
                for option in value if isinstance(value, list) else [value]:
                    _check_option(loader, key, str(option))
        elif not o.is_delete():
            check_key(key, add=o.is_add())
        if o.is_sweep_override():
            if values:
                prefix = "+" if o.is_add() else ""
                compose_with.append(f"{prefix}{key}={_quote(values[0])}")
        else:
            compose_with.append(o.input_line)
    return compose_with


def _quote(value: Any) -> str:
    text = str(value)
    return text if text.replace(".", "").replace("-", "").replace("_", "").isalnum() else repr(text)


def precheck(argv: Sequence[str], conf_dir: Path) -> RootConfig | None:
    """Check the command line of ``python train.py``; the validated config in a single run, None in
    a sweep or when Hydra alone handles the command (``--cfg``, ``--help``, ``-cp``...)."""
    from hydra import compose
    from hydra._internal.utils import get_args_parser
    from hydra.core.global_hydra import GlobalHydra
    from hydra.errors import HydraException
    from omegaconf import OmegaConf, open_dict
    from omegaconf.errors import OmegaConfBaseException

    from rlexp.config.paths import initialize_hydra
    from rlexp.config.schema import register_configs
    from rlexp.config.validate import to_root_config
    from rlexp.envs.native.render import GL_FIX, gl_problem
    from rlexp.run.writable import check_planned_dir, planned_dir

    problem = gl_problem(rendering=False)  # before anything imports MuJoCo, which would abort
    if problem:
        raise ConfigError(f"{problem}; {GL_FIX}")
    try:
        args = get_args_parser().parse_args(list(argv))
    except SystemExit:
        return None  # argparse's own message; Hydra prints it again
    if any(getattr(args, name, None) for name in _HYDRA_ONLY):
        return None
    register_configs()
    GlobalHydra.instance().clear()
    loader = None
    try:
        with initialize_hydra(conf_dir, args.config_dir):  # and the user's --config-dir after it
            loader = GlobalHydra.instance().config_loader()
            overrides = check_overrides(args.overrides, loader)
            cfg = compose(config_name="config", overrides=overrides, return_hydra_config=True)
        run_dir = _run_dir(cfg)
        planned = planned_dir(cfg, args.multirun)  # where it will write (rlexp.run.writable)
        sweeper = OmegaConf.to_container(cfg.hydra.sweeper, resolve=False)
        if args.multirun:
            check_pbt(cfg, loader, args.overrides)
            check_tuned_sweep(cfg, loader, args.overrides)
        _check_presets(cfg, loader, args.overrides, args.multirun)
        from rlexp.config.hydra_targets import check_hydra_targets

        try:  # what Hydra itself would call: callbacks, logging classes
            check_hydra_targets(OmegaConf.to_container(cfg.hydra, resolve=False))
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
        with open_dict(cfg):
            del cfg["hydra"]
        if args.multirun:
            from rlexp.config.validate import check_known_keys

            check_known_keys(OmegaConf.merge(OmegaConf.structured(RootConfig), cfg))
            check_sweeper(sweeper, args.overrides, cfg)
            check_planned_dir(planned)  # before Hydra creates the sweep dir
            return None
        config = to_root_config(cfg)
        if any(h.func == "pbt" for h in config.hooks.values()):
            raise ConfigError(
                "hooks.pbt: Population Based Training runs a population as a sweep: add -m "
                "(python train.py -m +sweep=pbt ..., docs/pbt.md)"
            )
    except (HydraException, OmegaConfBaseException) as exc:
        message = missing_tuned_preset(exc, loader) or _variant_key_message(exc)
        raise ConfigError(message or _first_line(exc)) from None
    finally:
        GlobalHydra.instance().clear()
    from rlexp.config.offpolicy_checks import distributed_refusal, is_off_policy
    from rlexp.runtime import distributed

    if distributed.info().enabled and is_off_policy(config.algorithm):
        raise ConfigError(distributed_refusal(config.algorithm))  # before building anything
    from rlexp.launch.checks import check_buildable

    check_buildable(config)

    # Before Hydra writes .hydra/ and its log there; rank 0 alone (it takes the lock right after,
    # and another rank would find that lock).
    if distributed.info().is_main:
        check_planned_dir(planned)  # a traceback from Hydra, or a failed first save, otherwise
    if run_dir is not None and run_dir.is_dir() and distributed.info().is_main:
        from rlexp.config.validate import to_dict
        from rlexp.run.rundir import RunDirLock, check_run_dir

        RunDirLock(run_dir).check()
        check_run_dir(run_dir, to_dict(config), config.trainer.resume)
        if config.trainer.resume == "auto":  # what the dir's files prove (rlexp.run.proof)
            from rlexp.run.proof import precheck_run_dir

            precheck_run_dir(run_dir, config)
    return config


def check_sweeper(sweeper: Any, overrides: Sequence[str], job_cfg: Any = None) -> None:
    """rlexp's Optuna sweeper: its extra is installed and its search space, sampler, pruner,
    storage and direction are usable (``rlexp.launch.optuna_sweeper.check_spec``), before Hydra
    creates the sweep dir."""
    import re

    if not str(sweeper.get("_target_", "")).startswith("hydra_plugins.rlexp_sweeper."):
        for key in ("confirm", "pruner", "trial_seeds", "trial_objective", "async_trials"):
            if key in sweeper:  # Hydra's own sweepers would fail on it with a traceback
                raise ConfigError(
                    f"hydra.sweeper.{key}: only rlexp's Optuna sweeper has it (hydra/sweeper="
                    f"optuna, or +sweep=ppo_optuna); this sweep's sweeper "
                    f"{sweeper.get('_target_')!r} keeps no study of trials"
                )
        return
    from rlexp.extras import require

    require("optuna", "hydra/sweeper=optuna (rlexp's Optuna sweeper)")
    from rlexp.launch.optuna_sweeper import check_spec

    task = [o for o in overrides if not re.match(r"[+~]*hydra[./]", o)]
    try:
        check_spec(sweeper, task, job_cfg)
    except ValueError as exc:  # StudyConfigError, SearchSpaceError: one line naming the key
        raise ConfigError(str(exc)) from None


def check_pbt(cfg: Any, loader: Any, overrides: Sequence[str]) -> None:
    """A PBT sweep runs its members side by side, as many as its population
    (``rlexp.pbt.config.check_pbt_sweep``); ``cfg``: composed with its ``hydra`` node,
    ``overrides``: the command line's (sweeps unexpanded)."""

    from omegaconf import OmegaConf

    from rlexp.pbt.config import PBTConfig, check_pbt_subdir, check_pbt_sweep, pbt_hooks

    hooks = OmegaConf.to_container(cfg.hooks, resolve=True) if "hooks" in cfg else {}
    if not pbt_hooks(hooks):
        return

    launcher = {
        key: OmegaConf.select(cfg, f"hydra.launcher.{key}", default=None)
        for key in ("_target_", "n_jobs", "array_parallelism")
    }
    launcher = {k: v for k, v in launcher.items() if v is not None}
    plan = _sweep_plan(cfg, overrides, loader)
    try:
        for name, params in pbt_hooks(hooks):  # the same for every member: checked once, here
            PBTConfig.from_params(params, f"hooks.{name}")
            _check_pbt_names(params, f"hooks.{name}", cfg.algorithm)
        check_pbt_sweep(launcher, len(plan.jobs) if plan.jobs is not None else None, hooks)
        sweep = OmegaConf.select(cfg, "hydra.sweep")
        raw = OmegaConf.to_container(sweep, resolve=False) if sweep is not None else {}
        check_pbt_subdir(raw.get("subdir") if isinstance(raw, dict) else None, hooks)
    except (ValueError, TypeError) as exc:
        raise ConfigError(str(exc)) from None


def _check_pbt_names(params: Any, where: str, algorithm: Any) -> None:
    from rlexp.config.rules import MUTABLE_HYPERPARAMETERS
    from rlexp.config.validate import check_pbt_names as check

    mutable = list(MUTABLE_HYPERPARAMETERS.get(str(algorithm.name), ()))
    check(params, where, mutable, str(algorithm.name))


def _run_dir(cfg: Any) -> Path | None:
    """``hydra.run.dir`` as this command would resolve it (None where it can't be resolved here)."""
    from omegaconf import OmegaConf

    try:
        return Path(str(OmegaConf.select(cfg, "hydra.run.dir", throw_on_resolution_failure=True)))
    except Exception:
        return None


#: The config groups of the per-task presets (conf/<group>/<env>.yaml), each selected for the env
#: chosen by ``+experiment=<group>``: the tuned ones (the best measured) and rl-baselines3-zoo's.
TUNED_GROUP = "tuned"
PRESET_GROUPS = (TUNED_GROUP, "rl_zoo", "sac_zoo", "td3_zoo")
#: The experiment that selects a preset group named otherwise (``+experiment=sac``: ``sac_zoo``).
PRESET_EXPERIMENT = {"sac_zoo": "sac", "td3_zoo": "td3"}
#: The env option of a --config-json run (``rlexp.launch.json_entry.ENV_NODE``; not imported: the
#: entry imports rlexp.app, which imports this module).
JSON_ENV_OPTION = "json_task"


def missing_tuned_preset(exc: BaseException, loader: Any = None) -> str | None:
    """``+experiment=tuned`` (or ``rl_zoo``) with an env that has no ``conf/<group>/<env>.yaml``:
    one line naming the env and the tasks that have a preset, not Hydra's "Could not find
    'tuned/<env>'" and its search path."""
    import re

    groups = "|".join(PRESET_GROUPS)
    found = re.search(rf"Could not find '({groups})/([^']+)'", str(exc))
    if found is None:
        return None
    return no_tuned_preset(found.group(2), loader, group=found.group(1))


def no_tuned_preset(env: str, loader: Any = None, group: str = TUNED_GROUP) -> str:
    """The line for an env option without a preset in ``group`` (``loader``: lists the ones there
    are)."""
    what = (
        f"env={env}" if env != JSON_ENV_OPTION else "a --config-json run's env (from its JSON file)"
    )
    tasks: list[str] = []
    if loader is not None:
        tasks = [o for o in loader.get_group_options(group) if o != "none"]
    experiment = PRESET_EXPERIMENT.get(group, group)
    return (
        f"+experiment={experiment} has no preset for {what} (no conf/{group}/{env}.yaml); the "
        f"tasks with one: {tasks}: choose one of them with env=..., or leave out "
        f"+experiment={experiment}"
    )


def check_tuned_sweep(cfg: Any, loader: Any, overrides: Sequence[str]) -> None:
    """A sweep with per-task presets (``+experiment=tuned``, ``+sweep=tuned_1m``, and the same for
    ``rl_zoo``) over envs: every env it launches must have a preset, checked before any job starts
    (Hydra composes the jobs' configs one batch at a time, so a later job's missing preset would
    stop the sweep midway, in Hydra's words). ``cfg``: composed with its ``hydra`` node for the
    sweep's first job."""
    from omegaconf import OmegaConf

    choices = OmegaConf.select(cfg, "hydra.runtime.choices", default={}) or {}
    groups = [g for g in PRESET_GROUPS if choices.get(g) not in (None, "none")]
    groups = [g for g in groups if choices.get(g) == choices.get("env")]  # not one task's preset
    if not groups:
        return
    plan = _sweep_plan(cfg, overrides, loader)
    presets = {g: set(loader.get_group_options(g)) for g in groups}
    for job in plan.jobs or []:
        pairs = (o.lstrip("+").split("=", 1) for o in job.overrides or () if "=" in o)
        env = dict(pairs).get("env")
        for group in groups:
            if env is not None and env not in presets[group]:
                raise ConfigError(
                    f"job {job.num} ({job.label}): {no_tuned_preset(env, loader, group)}"
                )


def _check_presets(cfg: Any, loader: Any, overrides: Sequence[str], multirun: bool) -> None:
    """A per-task preset applied to another env id: one line (rlexp.config.presets)."""
    from omegaconf import OmegaConf

    from rlexp.config.presets import GROUPS, check_preset_env, check_sweep_presets

    choices = dict(OmegaConf.select(cfg, "hydra.runtime.choices", default={}) or {})
    if all(choices.get(g) in (None, "none") for g in GROUPS) and not choices.get("experiment"):
        return
    name = str(OmegaConf.select(cfg, "env.name", default="") or "")
    try:
        if multirun:
            check_sweep_presets(
                choices, name, _sweep_plan(cfg, overrides, loader).jobs or [], loader
            )
        else:
            kept = OmegaConf.select(cfg, "env.observation_indices", default=None)
            kept = list(kept) if kept is not None else None
            check_preset_env(choices, name, loader, indices=kept)
    except ValueError as exc:
        raise ConfigError(str(exc)) from None


def _variant_key_message(exc: BaseException) -> str | None:
    """``algorithm.lmbda=0.9`` with ``algorithm=grpo``: say which option has the key, not that the
    class ``GRPOConfig`` lacks it."""
    import re

    from rlexp.config.schema import VARIANT_OPTIONS, VARIANTS

    while exc is not None:
        found = re.search(r"Key '(\w+)' not in '(\w+)'", str(exc))
        for section, variants in VARIANTS.items():
            for name, cls in variants.items():
                if found and found.group(2) == cls.__name__:
                    key = found.group(1)
                    have = [
                        f"{section}={VARIANT_OPTIONS[section][n]}"
                        for n, c in variants.items()
                        if key in {f.name for f in dataclasses.fields(c)}
                    ]
                    fields = sorted(f.name for f in dataclasses.fields(cls))
                    return (
                        f"{section}.{key} is not a key of {section}={VARIANT_OPTIONS[section][name]} "
                        f"(it has {fields})"
                        + (f"; {section}.{key} belongs to {' and '.join(have)}" if have else "")
                    )
        exc = exc.__cause__ or exc.__context__
    return None


def _first_line(exc: BaseException) -> str:
    """Hydra's message, and the cause it wraps (``Error merging override X`` says not why)."""
    parts = []
    while exc is not None and len(parts) < 3:
        lines = [ln.strip() for ln in str(exc).strip().splitlines() if ln.strip()]
        lines = [
            ln for ln in lines if not ln.startswith(("full_key:", "object_type", "reference_type"))
        ]
        if lines and lines[0] not in parts:
            parts.append(lines[0])
        exc = exc.__cause__ or exc.__context__
    return ": ".join(parts) if parts else "invalid config"


def _sweep_plan(cfg: Any, overrides: list[str], loader: Any) -> Any:
    """The jobs this sweep command will launch (its task overrides over the sweeper's params)."""
    import re

    from omegaconf import OmegaConf

    from rlexp.analysis.reporting.plan import plan_from_config

    task = [o for o in overrides if not re.match(r"[+~]*hydra[./]", o)]
    sweep = {
        "sweep": OmegaConf.to_container(cfg.hydra.sweep, resolve=False),
        "sweeper": OmegaConf.to_container(cfg.hydra.sweeper, resolve=False),
        "overrides": {"task": task},
    }
    return plan_from_config(OmegaConf.create({"hydra": sweep}), loader)
