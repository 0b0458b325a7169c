"""Confirmation on fresh seeds (``hydra.sweeper.confirm``): after an Optuna search, the ``top_k``
best trials' configurations are trained again on ``seeds`` seeds that no trial of the study used,
as jobs of the sweep, on the sweep's launcher. The best of N noisy trials is biased upward (it won
partly by luck on its own seed); the confirmed score, on seeds the search never saw, is not.

- The fresh seeds are the same for every configuration (common random numbers: the comparison is
  between configurations, not seeds) and derived from the study name alone:
  ``FRESH_SEED_BASE + crc32(study name) % FRESH_SEED_BASE``, counting up and skipping every seed a
  trial of the study recorded (``rlexp_seeds``, ``trial_seeds`` included; a searched ``seed``
  too). The same study always gets the same fresh seeds, so a re-run re-uses them.
- The jobs are numbered from :data:`CONFIRM_JOB_BASE` (their dirs ``<sweep dir>/10000``, ...),
  far above the search's own job dirs, so that a search continued with a larger ``n_trials``
  never lands in a confirmation job's dir. The plan (which trial, which seed, which job) is
  ``<sweep dir>/confirm.json``, written before the jobs start; a re-run of the command keeps the
  plan's job numbers for the (trial, seed) pairs it already had, and a job whose dir holds its
  finished run returns that result without training again (rlexp's task function): nothing is
  trained twice.
- The ranking (by the IQM over the fresh seeds, with a bootstrap CI), the search's optimism and
  the preset of the winner are ``rlexp.analysis.reporting.confirm``: the sweep's end log, ``rlexp
  report`` and ``rlexp report --write-preset``.
"""

from __future__ import annotations

import json
import logging
import re
import zlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rlexp.analysis.reporting.confirm import CONFIRM_FILE, confirm_lines
from rlexp.files.fsutil import atomic_write_text
from rlexp.launch.optuna_space import trial_overrides
from rlexp.launch.optuna_study import (
    StudyConfigError,
    jobs_of,
    overrides_of,
    seeds_of,
)

log = logging.getLogger(__name__)

#: The first job number of the confirmation jobs.
CONFIRM_JOB_BASE = 10_000
#: Fresh seeds start at FRESH_SEED_BASE + (crc32(study name) % FRESH_SEED_BASE).
FRESH_SEED_BASE = 1_000_000
#: The seed override every confirmation job gets.
SEED_KEY = "seed"


@dataclass(frozen=True)
class ConfirmSettings:
    """``hydra.sweeper.confirm``: re-run the ``top_k`` best trials on ``seeds`` fresh seeds."""

    top_k: int
    seeds: int


def confirm_settings(value: Any, n_objectives: int) -> ConfirmSettings | None:
    """``hydra.sweeper.confirm`` checked (None: no confirmation); ``StudyConfigError`` (one line,
    exit 2) naming the key otherwise."""
    if value is None:
        return None
    if not isinstance(value, Mapping):
        raise StudyConfigError(
            f"hydra.sweeper.confirm={value!r}: a mapping {{top_k: K, seeds: S}}, or null"
        )
    unknown = sorted(set(map(str, value)) - {"top_k", "seeds"})
    if unknown:
        raise StudyConfigError(
            f"hydra.sweeper.confirm.{unknown[0]}: no such key (confirm takes top_k and seeds)"
        )
    out = {}
    for key, default in (("top_k", 1), ("seeds", 5)):
        v = value.get(key, default)
        if isinstance(v, bool) or not isinstance(v, int) or v < 1:
            raise StudyConfigError(f"hydra.sweeper.confirm.{key}={v!r}: a whole number >= 1")
        out[key] = v
    if n_objectives != 1:
        raise StudyConfigError(
            f"hydra.sweeper.confirm: the study has {n_objectives} objectives; confirmation ranks "
            "one objective (a multi-objective study has a Pareto front, not one best trial)"
        )
    return ConfirmSettings(out["top_k"], out["seeds"])


def fresh_seeds(study_name: str, used: set[int], n: int) -> list[int]:
    """``n`` seeds none of ``used``, derived from the study name alone (module docstring)."""
    seed = FRESH_SEED_BASE + zlib.crc32(study_name.encode()) % FRESH_SEED_BASE
    out: list[int] = []
    while len(out) < n:
        if seed not in used:
            out.append(seed)
        seed += 1
    return out


def _searched_seed(trial: Any) -> list[int]:
    value = trial.params.get(SEED_KEY)
    return [value] if isinstance(value, int) and not isinstance(value, bool) else []


def used_seeds(trials: list[Any], base_seed: int) -> set[int]:
    """Every seed the study's trials ran with (recorded, or searched), and the config's own."""
    used = {base_seed}
    for t in trials:
        used.update(seeds_of(t))
        used.update(_searched_seed(t))
    return used


def plan(
    trials: list[Any],
    all_trials: list[Any],
    settings: ConfirmSettings,
    study_name: str,
    direction: str,
    base_seed: int,
    previous: Mapping[str, Any] | None,
    space: Sequence[str] | None = None,
    fixed: Mapping[str, str] | None = None,
) -> dict[str, Any]:
    """The confirmation plan: the ``top_k`` best COMPLETE trials of ``trials`` (this sweep's),
    seeds fresh for ``all_trials`` (the whole study), job numbers kept from ``previous`` (an
    earlier ``confirm.json``) for the (trial, seed) pairs it already had.

    ``space`` (the sweep's search-space names) and ``fixed`` (its fixed overrides): a job's
    overrides are made from the trial's parameters inside ``space`` and ``fixed``, never taken as
    text from the storage (a study file is data: an override written there could reach Hydra's
    own keys); a trial with a parameter outside ``space`` is not confirmed. None (tests): the
    trial's recorded overrides."""
    from optuna.trial import TrialState

    done = [t for t in trials if t.state == TrialState.COMPLETE and t.value is not None]
    if space is not None:
        outside = [t.number for t in done if not _in_space(t.params, space)]
        if outside:
            log.warning(
                "hydra.sweeper.confirm: trial(s) %s have parameters outside this sweep's search "
                "space: not confirmed",
                outside,
            )
        done = [t for t in done if _in_space(t.params, space)]
    best = sorted(done, key=lambda t: t.value, reverse=direction == "maximize")
    top = best[: settings.top_k]
    if len(top) < settings.top_k:
        log.warning(
            "hydra.sweeper.confirm.top_k=%d: only %d trial(s) completed; confirming those",
            settings.top_k,
            len(top),
        )
    seeds = fresh_seeds(study_name, used_seeds(all_trials, base_seed), settings.seeds)
    known: dict[tuple[int, int], int] = {}
    for c in (previous or {}).get("candidates", []):
        for j in c.get("jobs", []):
            known[(int(c["trial"]), int(j["seed"]))] = int(j["job"])
    above = max([CONFIRM_JOB_BASE - 1, *known.values()]) + 1
    candidates = []
    for rank, t in enumerate(top, 1):
        jobs = []
        for seed in seeds:
            job = known.get((t.number, seed))
            if job is None:
                job, above = above, above + 1
            jobs.append({"job": job, "seed": seed})
        candidates.append(
            {
                "search_rank": rank,
                "trial": t.number,
                "search_value": float(t.value),
                "search_jobs": jobs_of(t),
                "search_seeds": seeds_of(t),
                "params": {k: _plain(v) for k, v in t.params.items()},
                "overrides": overrides_of(t)
                if space is None
                else list(trial_overrides(t.params, space, fixed or {})),
                "jobs": jobs,
            }
        )
    return {
        "version": 1,
        "study": study_name,
        "direction": direction,
        "top_k": settings.top_k,
        "seeds": seeds,
        "candidates": candidates,
    }


#: A parameter a custom search space (``custom_search_space``) suggested: a config key, not Hydra's.
_CONFIG_KEY = re.compile(r"(?!hydra\.)[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*")


def _in_space(params: Mapping[str, Any], space: Sequence[str]) -> bool:
    """Every parameter is one of the search space's, or a plain config key outside ``hydra.``
    (what a ``custom_search_space`` function suggests)."""
    return all(n in space or _CONFIG_KEY.fullmatch(str(n)) for n in params)


def _plain(value: Any) -> Any:
    return value if isinstance(value, (int, float, str, bool)) or value is None else str(value)


def job_overrides(candidate: Mapping[str, Any], seed: int) -> list[str]:
    """A confirmation job's overrides: the trial's (no ``seed=``, no pruning hook) and the seed."""
    own = [o for o in candidate["overrides"] if o.split("=", 1)[0].lstrip("+~") != SEED_KEY]
    return [*own, f"{SEED_KEY}={seed}"]


def read_plan(sweep_dir: Path) -> dict[str, Any] | None:
    """The sweep dir's ``confirm.json`` (None when absent or not a plan: a new plan replaces it)."""
    try:
        data = json.loads((sweep_dir / CONFIRM_FILE).read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) and data.get("version") == 1 else None


def confirm(
    sweep: Any, settings: ConfirmSettings, direction: str, base_seed: int, spec: Any = None
) -> None:
    """Plan, write ``confirm.json``, run the jobs not finished on the sweep's launcher
    (``sweep.run_jobs``), and log the ranking (``rlexp.analysis.reporting.confirm``)."""
    study = sweep.study
    mine, everyone = sweep.mine(study), study.get_trials(deepcopy=False)
    if not any(t.value is not None for t in mine):
        log.warning("hydra.sweeper.confirm: no trial completed; nothing to confirm")
        return
    sweep_dir = Path(sweep.sweep_dir)
    found = plan(
        mine,
        everyone,
        settings,
        study.study_name,
        direction,
        base_seed,
        read_plan(sweep_dir),
        list(spec.dists) if spec is not None else None,
        dict(spec.fixed) if spec is not None else None,
    )
    atomic_write_text(sweep_dir / CONFIRM_FILE, json.dumps(found, indent=2) + "\n")
    # no pruning hook: a confirmation job trains to its end
    jobs = [(j["job"], job_overrides(c, j["seed"])) for c in found["candidates"] for j in c["jobs"]]
    log.info(
        "confirming the %d best trial(s) on %d fresh seed(s) %s: %d job(s) from %d",
        len(found["candidates"]),
        len(found["seeds"]),
        found["seeds"],
        len(jobs),
        min(j for j, _ in jobs),
    )
    sweep.run_jobs(jobs)
    for line in confirm_lines(sweep_dir):
        log.info("%s", line)
