"""What the confirmation of an Optuna search on fresh seeds found (``<sweep dir>/confirm.json``,
written by ``rlexp.launch.optuna_confirm``; the jobs' ``status.json``): the configurations ranked
by their IQM over the fresh seeds (with a 95% bootstrap CI), the search's optimism (the best
trial's own score against its confirmed one), and the winner as a preset file.

Read by the sweep's end log, ``rlexp report`` (section "Confirmation on fresh seeds") and
``rlexp report --write-preset PATH``. Imports nothing from the launch layer.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

#: The confirmation plan in the sweep dir.
CONFIRM_FILE = "confirm.json"
#: The objective a job's ``status.json`` holds (``final_eval``): what the search maximised.
OBJECTIVE = "eval/episode_return"
#: Keys of a run's config that are the run's own, never a preset's: its seed and name, where it
#: ran (a device resolved from ``auto``) and where it logged.
NOT_PRESET = ("seed", "exp_name", "run_dir", "resume", "logger", "trainer.device", "env.device")


class ConfirmError(ValueError):
    """``--write-preset`` (or the report) cannot use this sweep dir: one line."""


@dataclass
class Confirmed:
    """One configuration re-run on the fresh seeds."""

    trial: int
    search_rank: int
    search_value: float
    params: dict[str, Any]
    overrides: list[str]
    jobs: list[int]
    values: list[float]  # the finished jobs' final objective, in seed order
    iqm: float = math.nan
    ci: tuple[float, float] = (math.nan, math.nan)


def _job_value(job_dir: Path) -> float | None:
    from rlexp.run.rundir import final_value, read_status

    return final_value(read_status(job_dir), OBJECTIVE, ("finished", "stopped_early"))


def read_confirmation(sweep_dir: Path) -> tuple[dict[str, Any], list[Confirmed]] | None:
    """The plan and its configurations, ranked best first by confirmed IQM (None: no plan)."""
    from rlexp.analysis.stats import bootstrap_ci, iqm
    from rlexp.files.safe_read import load_json

    path = Path(sweep_dir) / CONFIRM_FILE
    if not path.is_file():
        return None
    try:
        plan = load_json(path)
    except Exception as exc:
        raise ConfirmError(f"{path}: not readable ({exc})") from None
    if not isinstance(plan, dict) or not isinstance(plan.get("candidates"), list):
        raise ConfirmError(f"{path}: not a confirmation plan (no 'candidates' list)")
    rows = []
    for c in plan["candidates"]:
        jobs = [int(j["job"]) for j in c.get("jobs", [])]
        values = [v for v in (_job_value(Path(sweep_dir) / str(j)) for j in jobs) if v is not None]
        row = Confirmed(
            int(c["trial"]),
            int(c["search_rank"]),
            float(c["search_value"]),
            dict(c.get("params", {})),
            list(c.get("overrides", [])),
            jobs,
            values,
        )
        if values:
            x = np.asarray(values, dtype=np.float64)
            row.iqm = float(iqm(x))
            row.ci = bootstrap_ci(x, iqm)
        rows.append(row)
    sign = -1.0 if plan.get("direction") == "minimize" else 1.0
    rows.sort(key=lambda r: (math.isnan(r.iqm), -sign * r.iqm if not math.isnan(r.iqm) else 0))
    return plan, rows


def optimism(plan: Mapping[str, Any], rows: Sequence[Confirmed]) -> tuple[float, float] | None:
    """(the search's best trial's own score, its confirmed IQM); None if not confirmed yet."""
    best = next((r for r in rows if r.search_rank == 1), None)
    if best is None or math.isnan(best.iqm):
        return None
    return best.search_value, best.iqm


def _fmt(x: float) -> str:
    return "n/a" if math.isnan(x) else f"{x:.4g}"


def confirm_lines(sweep_dir: Path) -> list[str]:
    """The report's section (markdown lines; [] without a confirmation plan)."""
    try:
        found = read_confirmation(sweep_dir)
    except ConfirmError as exc:
        return ["", "## Confirmation on fresh seeds", "", f"{exc}."]
    if found is None:
        return []
    plan, rows = found
    seeds = plan.get("seeds", [])
    out = [
        "",
        f"## Confirmation on fresh seeds ({len(rows)} configuration(s) x {len(seeds)} seed(s): "
        f"{', '.join(map(str, seeds))})",
        "",
        "| rank | trial | search rank | search score | confirmed IQM | 95% CI | seeds done | "
        "parameters |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for rank, r in enumerate(rows, 1):
        params = ", ".join(f"{k}={v}" for k, v in r.params.items())
        out.append(
            f"| {rank} | {r.trial} | {r.search_rank} | {_fmt(r.search_value)} | {_fmt(r.iqm)} | "
            f"[{_fmt(r.ci[0])}, {_fmt(r.ci[1])}] | {len(r.values)}/{len(r.jobs)} | {params} |"
        )
    gap = optimism(plan, rows)
    if gap is not None:
        out += [
            "",
            f"Optimism of the search: its best trial scored {_fmt(gap[0])} on its own seed(s) "
            f"and {_fmt(gap[1])} (IQM) on the fresh seeds: {_fmt(gap[0] - gap[1])} "
            f"({plan.get('direction', 'maximize')}).",
        ]
    return out


# -- the winner as a preset --------------------------------------------------------------------


def _diff(run: Any, base: Any, path: str = "") -> dict[str, Any]:
    """The keys of ``run`` whose value differs from ``base`` (nested dicts compared key by key)."""
    out: dict[str, Any] = {}
    for key, value in run.items():
        where = f"{path}.{key}" if path else str(key)
        if where in NOT_PRESET:
            continue
        old = base.get(key, object()) if isinstance(base, Mapping) else object()
        if isinstance(value, Mapping) and isinstance(old, Mapping):
            sub = _diff(value, old, where)
            if sub:
                out[key] = sub
        elif value != old:
            out[key] = value
    return out


def _env_choice(job_dir: Path) -> str | None:
    from omegaconf import OmegaConf

    try:
        hydra = OmegaConf.load(job_dir / ".hydra" / "hydra.yaml")
        choice = OmegaConf.select(hydra, "hydra.runtime.choices.env")
    except Exception:
        return None
    return str(choice) if choice else None


def base_config(env_choice: str | None) -> dict[str, Any]:
    """rlexp's default config for the env option (``python train.py env=<option>``), as a run
    dir's ``config.yaml`` holds it."""
    from hydra import compose
    from omegaconf import OmegaConf

    from rlexp.config.paths import find_conf_dir, initialize_hydra
    from rlexp.config.schema import register_configs
    from rlexp.config.validate import to_root_config

    register_configs()  # the schemas are group options too, as in a run
    with initialize_hydra(find_conf_dir()):
        cfg = compose("config", overrides=[f"env={env_choice}"] if env_choice else [])
    root = to_root_config(cfg)
    return OmegaConf.to_container(OmegaConf.structured(root), resolve=True)


def preset_text(sweep_dir: Path) -> str:
    """The winner's preset: the keys of its run config that differ from rlexp's default for its
    env option, with where they came from."""
    from omegaconf import OmegaConf

    found = read_confirmation(sweep_dir)
    if found is None:
        raise ConfirmError(
            f"{sweep_dir} has no {CONFIRM_FILE}: run the sweep with hydra.sweeper.confirm="
            "{top_k:K,seeds:S} (an Optuna sweep) first"
        )
    plan, rows = found
    if not rows or math.isnan(rows[0].iqm):
        raise ConfirmError(
            f"{sweep_dir}: no confirmation job finished yet: run the sweep's command again"
        )
    win = rows[0]
    job = next(Path(sweep_dir) / str(j) for j in win.jobs if _job_value(Path(sweep_dir) / str(j)) is not None)  # fmt: skip
    run = OmegaConf.to_container(OmegaConf.load(job / "config.yaml"), resolve=True)
    choice = _env_choice(job)
    values = _diff(run, base_config(choice))
    head = [
        "# @package _global_",
        f"# Written by `rlexp report {sweep_dir} --write-preset` on "
        f"{time.strftime('%Y-%m-%d %H:%M:%S')}: the winner of the Optuna study "
        f"{plan.get('study')!r}, confirmed on fresh seeds.",
        f"# Trial {win.trial} (search rank {win.search_rank}, search score "
        f"{_fmt(win.search_value)}); confirmed IQM {_fmt(win.iqm)}, 95% CI "
        f"[{_fmt(win.ci[0])}, {_fmt(win.ci[1])}] over seeds {plan.get('seeds')}.",
        f"# Its parameters: {', '.join(f'{k}={v}' for k, v in win.params.items())}",
        f"# The keys below differ from rlexp's default for env={choice} (from job dir {job}).",
        f"#   python train.py env={choice} tuned=<this file's name> seed=0"
        if choice
        else "#   python train.py tuned=<this file's name> seed=0",
    ]
    return "\n".join(head) + "\n" + OmegaConf.to_yaml(OmegaConf.create(values))


def write_preset(sweep_dir: Path, path: Path, force: bool = False) -> Path:
    """Write the winner's preset to ``path`` (refused when it exists, unless ``force``)."""
    path = Path(path)
    if path.suffix not in (".yaml", ".yml"):
        raise ConfirmError(f"--write-preset {path}: a .yaml file (e.g. conf/tuned/<env>.yaml)")
    if path.exists() and not force:
        raise ConfirmError(f"--write-preset {path}: the file exists (add --force to replace it)")
    text = preset_text(Path(sweep_dir))
    from rlexp.files.fsutil import atomic_write_text

    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, text)
    return path
