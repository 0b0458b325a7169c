"""Per-task presets hold one task's values: ``+experiment=tuned`` / ``+experiment=rl_zoo`` (the
values of ``conf/<group>/<env>.yaml`` for the chosen env option) and the experiment files that pick
their env (``+experiment=pendulum_ppo``). Applied to another env id (``+experiment=tuned env=hopper
env.name=Walker2d-v5``) they would train that task with Hopper's settings without a word, so the
config check refuses it in one line (exit 2), for a single run and for every job of a sweep.

The id a preset is for is the ``name`` of the env option it belongs to (``conf/env/hopper.yaml``:
``Hopper-v5``); Gymnasium's ``module:`` prefix is not part of the id.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

#: The preset groups (rlexp.launch.precheck.PRESET_GROUPS; repeated: that module imports this one).
GROUPS = ("tuned", "rl_zoo", "sac_zoo", "td3_zoo")


def _raw(loader: Any, path: str) -> Any:
    try:
        return loader.repository.load_config(path)
    except Exception:  # an unreadable or missing file: Hydra's own compose reports it
        return None


def env_id(loader: Any, option: str) -> str | None:
    """The env id ``conf/env/<option>.yaml`` sets (None: no such file, or no plain name in it)."""
    found = _raw(loader, f"env/{option}")
    name = found.config.get("name") if found is not None else None
    return name if isinstance(name, str) and "${" not in name else None


#: ``indices`` when the observation entries a run keeps are not known (nothing to compare).
UNKNOWN = "unknown"


def env_indices(loader: Any, option: str) -> list[int] | None | str:
    """The ``observation_indices`` ``conf/env/<option>.yaml`` sets (None: all entries; ``UNKNOWN``:
    no such file, or not a plain list of ints)."""
    found = _raw(loader, f"env/{option}")
    if found is None:
        return UNKNOWN
    value = found.config.get("observation_indices")
    if value is None or (not isinstance(value, (str, bytes)) and len(value) == 0):
        return None  # [] (the schema's default) and None: every entry
    items = list(value) if not isinstance(value, (str, bytes)) else None
    if items is None or not all(isinstance(i, int) and not isinstance(i, bool) for i in items):
        return UNKNOWN
    return [int(i) for i in items]


def _experiment_env(loader: Any, experiment: str) -> str | None:
    """The env option an experiment file picks (``override /env: X`` in its defaults), if any."""
    found = _raw(loader, f"experiment/{experiment}")
    for entry in getattr(found, "defaults_list", None) or []:
        if str(getattr(entry, "group", "")).lstrip("/") == "env" and getattr(entry, "value", None):
            return str(entry.value)
    return None


def _bare(name: str) -> str:
    return name.split(":", 1)[-1]


def check_preset_env(
    choices: Mapping[str, Any],
    name: str,
    loader: Any,
    where: str = "",
    indices: Sequence[int] | None | str = UNKNOWN,
) -> None:
    """A ValueError of one line when a per-task preset chosen in ``choices`` (Hydra's group
    choices) is for another env id than ``name`` (``env.name``), or for the same id with other
    observation entries (``indices``: the run's ``env.observation_indices``; a preset for
    CartPoleNoVel is not CartPole's); ``where``: a sweep job's label."""
    experiment = choices.get("experiment")
    presets: list[tuple[str, str]] = []  # (what the user chose, the env option it is for)
    for group in GROUPS:
        option = choices.get(group)
        if option not in (None, "none"):
            what = f"+experiment={group}" if experiment == group else f"{group}={option}"
            if experiment not in (None, *GROUPS):  # an experiment file chose it
                what = f"+experiment={experiment} ({group}={option}"
            else:
                what += " ("
            presets.append((f"{what}: conf/{group}/{option}.yaml)", str(option)))
    if experiment not in (None, *GROUPS):
        option = _experiment_env(loader, str(experiment))
        if option is not None:
            presets.append((f"+experiment={experiment}", option))
    for what, option in presets:
        expected = env_id(loader, option)
        if expected is None:
            continue
        if _bare(expected) == _bare(name):
            kept = env_indices(loader, option)
            given = indices if indices in (None, UNKNOWN) else [int(i) for i in indices] or None
            if UNKNOWN in (kept, given) or kept == given:
                continue
            raise ValueError(
                f"{where}{what} is the preset for {expected} with env.observation_indices={kept} "
                f"(env={option}), but this run has env.observation_indices={given}: its values "
                f"were chosen for that observation, not this one; use env={option} or leave out "
                "the preset"
            )
        raise ValueError(
            f"{where}{what} is the preset for {expected} (env={option}), but env.name={name!r}: "
            f"its values were chosen for {expected}, not this task; choose the env option of "
            f"{name!r} (its own preset, where it has one) or leave out the preset"
        )


def check_sweep_presets(
    choices: Mapping[str, Any], name: str, jobs: Sequence[Any], loader: Any
) -> None:
    """:func:`check_preset_env` for every job of a sweep (``jobs``: the plan's, each with
    ``overrides``, ``num`` and ``label``), before any job starts."""
    base_env = choices.get("env")
    for job in jobs:
        given = dict(o.lstrip("+~").split("=", 1) for o in job.overrides or () if "=" in o)
        env_option = given.get("env", base_env)
        mine = dict(choices)
        mine["env"] = env_option
        mine["experiment"] = given.get("experiment", choices.get("experiment"))
        for group in GROUPS:
            if group in given:
                mine[group] = given[group]
            elif mine["experiment"] == group or (
                choices.get(group) not in (None, "none") and choices.get(group) == base_env
            ):
                mine[group] = env_option  # +experiment=<group> picks the env's own preset
        job_name = given.get("env.name")
        if job_name is None:
            job_name = env_id(loader, env_option) if "env" in given else name
        kept = UNKNOWN if "env.observation_indices" in given else env_indices(loader, env_option)
        if job_name is not None:
            check_preset_env(mine, job_name, loader, f"job {job.num} ({job.label}): ", kept)
