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


def _experiment_env(loader: Any, experiment: str) -> str | None:
    """The env option an experiment file picks (``override /env: X`` in its defaults), if any."""
    found = _raw(loader, f"experiment/{experiment}")
    for entry in getattr(found, "defaults_list", None) or []:
        if str(getattr(entry, "group", "")).lstrip("/") == "env" and getattr(entry, "value", None):
            return str(entry.value)
    return None


def _bare(name: str) -> str:
    return name.split(":", 1)[-1]


def check_preset_env(choices: Mapping[str, Any], name: str, loader: Any, where: str = "") -> None:
    """A ValueError of one line when a per-task preset chosen in ``choices`` (Hydra's group
    choices) is for another env id than ``name`` (``env.name``); ``where``: a sweep job's label."""
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
        if expected is None or _bare(expected) == _bare(name):
            continue
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
        if job_name is not None:
            check_preset_env(mine, job_name, loader, f"job {job.num} ({job.label}): ")
