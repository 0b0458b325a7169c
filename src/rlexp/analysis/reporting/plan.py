"""The jobs a sweep was to run, from its ``multirun.yaml`` (the basic sweeper's grid, Optuna's
``n_trials``), matched against the job dirs found: which never started, which are extra."""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from rlexp.analysis.reporting.jobs import DEFAULT_METRIC, Job, find_jobs, first_line

#: A plan's source when Hydra's parser could not expand the sweep's overrides.
UNEXPANDED = "the sweep's overrides could not be expanded"
#: ``hydra.sweep.subdir`` that names each job dir after its job number (conf/config.yaml).
JOB_NUM_SUBDIR = "${hydra.job.num}"


@dataclass(frozen=True)
class ExpectedJob:
    """A job that the sweep's ``multirun.yaml`` says it launches."""

    num: int  # hydra.job.num
    overrides: tuple[str, ...] | None  # None where the sweeper picks them as it goes (Optuna)

    @property
    def label(self) -> str:
        return " ".join(self.overrides) if self.overrides is not None else "(chosen by the sweeper)"


@dataclass
class Plan:
    """The jobs a sweep was to launch (None: not known), and where that number comes from."""

    jobs: list[ExpectedJob] | None
    source: str
    numbered_dirs: bool = True  # job dirs are named by job number (hydra.sweep.subdir)


@dataclass
class Sweep:
    """A sweep dir's job dirs against its plan."""

    jobs: list[Job]  # every job dir found
    plan: Plan
    never_started: list[ExpectedJob]  # planned, no job dir
    extra: list[Job]  # job dirs the plan does not name (an earlier sweep into the same dir)

    @property
    def planned(self) -> list[Job]:
        """The job dirs of this sweep (all of them when the plan is unknown)."""
        extra = {id(j) for j in self.extra}
        return [j for j in self.jobs if id(j) not in extra]


def _plain(cfg: DictConfig, key: str) -> Any:
    """``cfg[key]`` as plain Python, resolved where it can be (a ``${now:}`` in a saved config
    cannot be: then as written)."""
    node = OmegaConf.select(cfg, key, throw_on_resolution_failure=False)
    if not OmegaConf.is_config(node):
        return node
    try:
        return OmegaConf.to_container(node, resolve=True)
    except Exception:  # an interpolation that only resolves inside the sweep
        return OmegaConf.to_container(node, resolve=False)


def plan_from_config(cfg: DictConfig, config_loader: Any = None) -> Plan:
    """The jobs a sweep launches, from its config (``multirun.yaml``): the basic sweeper's grid,
    expanded by Hydra's own ``BasicSweeper.split_arguments`` (job N = the N-th combination); Optuna:
    ``n_trials`` jobs. ``config_loader`` expands ``glob(...)`` over config groups."""
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra.core.override_parser.overrides_parser import OverridesParser

    sweep = OmegaConf.select(cfg, "hydra.sweep")
    raw = OmegaConf.to_container(sweep, resolve=False) if isinstance(sweep, DictConfig) else {}
    numbered = raw.get("subdir") == JOB_NUM_SUBDIR
    target = str(_plain(cfg, "hydra.sweeper._target_") or "")
    if target.endswith(".BasicSweeper"):
        params = _plain(cfg, "hydra.sweeper.params") or {}
        task = _plain(cfg, "hydra.overrides.task") or []
        if not isinstance(params, dict) or not isinstance(task, list):
            return Plan(None, "hydra.sweeper.params / hydra.overrides.task are of the wrong shape")
        lines = [f"{k}={v}" for k, v in params.items()] + [str(o) for o in task]
        try:
            parsed = OverridesParser.create(config_loader=config_loader).parse_overrides(lines)
            batches = BasicSweeper.split_arguments(parsed, None)[0]
        except Exception as exc:  # Hydra's parser: a sweep it cannot expand without the configs
            return Plan(None, f"{UNEXPANDED} ({first_line(exc)})")
        jobs = [ExpectedJob(i, tuple(o)) for i, o in enumerate(batches)]
        return Plan(jobs, "the grid of the sweep's overrides", numbered)
    if "optuna" in target.lower():
        n = _plain(cfg, "hydra.sweeper.n_trials")
        if isinstance(n, bool) or not isinstance(n, int) or n < 0:
            return Plan(None, f"hydra.sweeper.n_trials={n!r} is not a number of trials")
        jobs = [ExpectedJob(i, None) for i in range(n)]
        return Plan(jobs, "hydra.sweeper.n_trials", numbered)
    return Plan(None, f"the sweeper {target or '(none)'} does not say how many jobs it launches")


def read_plan(sweep_dir: Path) -> Plan:
    """The plan of the sweep in ``sweep_dir``, from its ``multirun.yaml``."""
    from omegaconf._utils import get_yaml_loader

    from rlexp.files import safe_read

    path = sweep_dir / "multirun.yaml"
    try:  # as OmegaConf.load, but bounded and without YAML aliases (rlexp.files.safe_read)
        data = safe_read.load_yaml(path, loader=get_yaml_loader())
        if data is None and not os.path.lexists(path):
            return Plan(None, "no multirun.yaml in the sweep dir")
        cfg = OmegaConf.create(data if data is not None else {})
    except Exception as exc:  # a YAML error, a torn file: the report goes on without a plan
        return Plan(None, f"multirun.yaml is not readable ({first_line(exc)})")
    if not isinstance(cfg, DictConfig):
        return Plan(None, "multirun.yaml is not a mapping")
    plan = plan_from_config(cfg)
    if plan.jobs is None and plan.source.startswith(UNEXPANDED):
        plan = _plan_with_rlexp_configs(cfg) or plan
    return plan


def _plan_with_rlexp_configs(cfg: DictConfig) -> Plan | None:
    """The plan with rlexp's ``conf/`` at hand: a ``glob(...)`` over a config group lists the
    group's options (as the sweep did). None where Hydra is already set up in this process."""
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from rlexp.config.paths import CONF_DIR
    from rlexp.config.schema import register_configs

    if GlobalHydra.instance().is_initialized():
        return None
    register_configs()  # the schemas are group options too, as in the sweep
    try:
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            return plan_from_config(cfg, GlobalHydra.instance().config_loader())
    except Exception:  # Hydra's own errors: the plan stays unknown, with the first reason
        return None
    finally:
        GlobalHydra.instance().clear()


def match_plan(sweep_dir: Path, jobs: list[Job], plan: Plan) -> Sweep:
    """Which planned jobs have a dir: matched by overrides (a grid: Hydra writes each job's own
    overrides into its ``.hydra/overrides.yaml``), else by job number (the dir name)."""
    if plan.jobs is None:
        return Sweep(jobs, plan, [], [])
    by_overrides: dict[tuple[str, ...], list[Job]] = {}
    for job in jobs:
        by_overrides.setdefault(tuple(job.overrides), []).append(job)
    by_name = {job.path.relative_to(sweep_dir).as_posix(): job for job in jobs}
    in_order = iter(jobs)  # other dir names: trials start in job-number order
    never: list[ExpectedJob] = []
    claimed: set[int] = set()
    for expected in plan.jobs:
        if expected.overrides is not None:
            same = by_overrides.get(expected.overrides)
            found = same.pop(0) if same else None
        elif plan.numbered_dirs:
            found = by_name.get(str(expected.num))
        else:
            found = next(in_order, None)
        if found is None:
            never.append(expected)
        else:
            claimed.add(id(found))
    extra = [j for j in jobs if id(j) not in claimed]
    return Sweep(jobs, plan, never, extra)


def read_sweep(
    sweep_dir: Path,
    metric: str | None = DEFAULT_METRIC,
    plan: Plan | None = None,
    other_metrics: Sequence[str] = (),
) -> Sweep:
    """The job dirs of ``sweep_dir`` against ``plan`` (default: from its ``multirun.yaml``)."""
    jobs = find_jobs(sweep_dir, metric, other_metrics)
    return match_plan(sweep_dir, jobs, plan if plan is not None else read_plan(sweep_dir))
