"""What a (re-)run of an Optuna sweep does before and after its jobs: the work plan (which trials
are re-run, retried, new, and their job dirs), a job's return or dir as a trial's value, the checks
of a pruner against the jobs' evaluations, and ``study.tell``."""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hydra.core.utils import JobReturn, JobStatus
from omegaconf import OmegaConf

from rlexp.launch.optuna_study import StudyConfigError, job_of, jobs_of
from rlexp.run.rundir import final_value

log = logging.getLogger(__name__)

#: What rlexp's task function returns for a trial (``rlexp.app._task``): its final eval return.
OBJECTIVE = "eval/episode_return"

#: The states of a job dir whose run ended with a result (a pruned one is told PRUNED).
ENDED = ("finished", "stopped_early", "pruned")


@dataclass
class Work:
    """One trial to launch: a killed trial re-run in place, a failed one retried, or a new one."""

    kind: str  # "resume" | "retry" | "new"
    job: int  # the first of its job dirs
    jobs: list[int] = field(default_factory=list)  # one per seed (hydra.sweeper.trial_seeds)
    trial: Any = None  # resume: the RUNNING FrozenTrial
    retry_of: Any = None  # retry: the failed FrozenTrial


def plan_work(
    trials: Sequence[Any], n_trials: int, n_seeds: int = 1
) -> tuple[list[Work], dict[int, Any]]:
    """What a (re-)run of the study does: per job dir its latest trial decides (RUNNING: killed,
    re-run in place; FAIL: retried; COMPLETE/PRUNED: kept), then new trials (``n_seeds`` job dirs
    each) up to ``n_trials`` trials. Returns (the work in job order, the latest trial of every
    trial's first job dir)."""
    from optuna.trial import TrialState

    heads: dict[int, Any] = {}
    for t in sorted(trials, key=lambda t: t.number):
        job = job_of(t)
        if job is not None:
            heads[job] = t
    work = []
    for job, t in sorted(heads.items()):
        if t.state == TrialState.RUNNING:
            work.append(Work("resume", job, jobs_of(t), trial=t))
        elif t.state == TrialState.FAIL:
            work.append(Work("retry", job, jobs_of(t), retry_of=t))
    used = [j for t in trials for j in jobs_of(t)]
    start = max(used) + 1 if used else 0
    for i in range(max(0, n_trials - len(heads))):
        first = start + i * n_seeds
        work.append(Work("new", first, list(range(first, first + n_seeds))))
    return work, heads


def batches(work: list[Work], size: int) -> list[list[Work]]:
    """Runs of at most ``size`` items with consecutive job numbers: a launcher numbers one call's
    jobs from its first (``initial_job_idx``), and the job number is the job dir."""
    out: list[list[Work]] = []
    for item in work:
        last = out[-1] if out else None
        if last and len(last) < size and item.job == last[-1].job + len(last[-1].jobs or [0]):
            last.append(item)
        else:
            out.append([item])
    return out


def trial_value(ret: JobReturn, n_objectives: int) -> list[float] | None:
    """The job's return as the trial's values; None (a failed trial) for rlexp's None (the job
    failed and said why), a job that raised, or anything not finite."""
    if ret.status != JobStatus.COMPLETED:
        return None
    value = ret.return_value
    try:
        values = [float(value)] if n_objectives == 1 else [float(v) for v in value]
    except (TypeError, ValueError):
        return None
    if len(values) != n_objectives or not all(math.isfinite(v) for v in values):
        return None
    return values


def finished_value(job_dir: Path, overrides: Sequence[str] = ()) -> float | None:
    """The final :data:`OBJECTIVE` of a job dir whose ``status.json`` says it ran to its end
    (finished, or stopped early by a hook) with ``overrides`` (its trial's parameters) among its
    ``.hydra/overrides.yaml``; None otherwise: then the trial is run again in its dir, where the
    job skips only if its ``config.yaml`` proves the same config (``rlexp.run.proof``)."""
    try:
        status = json.loads((job_dir / "status.json").read_text())
    except (OSError, ValueError):
        return None
    value = final_value(status, OBJECTIVE, ("finished", "stopped_early"))
    if value is None:
        return None
    missing = sorted(set(overrides) - set(_job_overrides(job_dir)))
    if missing:
        log.warning("job dir %s did not run with %s: its result is not taken", job_dir, missing)
        return None
    return value


def _job_overrides(job_dir: Path) -> list[str]:
    """The job dir's ``.hydra/overrides.yaml`` ([] when missing or not a list of strings)."""
    try:
        listed = OmegaConf.to_container(OmegaConf.load(job_dir / ".hydra" / "overrides.yaml"))
    except Exception:
        return []
    return [str(o) for o in listed] if isinstance(listed, list) else []


#: What a trial's job needs for intermediate values: evaluations before its budget ends.
EVAL_KEYS = ("trainer.eval_every", "trainer.eval_episodes", "env.num_eval_envs")


def check_evaluates(pruner: dict[str, Any], spec: Any, job_cfg: Any) -> None:
    """A pruner judges a trial by the evaluations it reports while it trains: refused, in one
    line naming the key, where the jobs evaluate never or only at their end."""

    def value(key: str) -> Any:
        if key in spec.fixed:
            text = spec.fixed[key].split("=", 1)[1]
            return int(text) if text.lstrip("-").isdigit() else text
        return OmegaConf.select(job_cfg, key, default=None)

    if any(k in spec.dists for k in (*EVAL_KEYS, "trainer.total_frames")):
        return  # searched: each job's own check
    name = f"hydra.sweeper.pruner={pruner['_target_'].rsplit('.', 1)[-1]}"
    for key in EVAL_KEYS:
        if value(key) == 0:
            raise StudyConfigError(
                f"{name}: {key}=0, so the trials never evaluate and report no intermediate "
                f"values for the pruner to judge; set {key} above 0 or hydra.sweeper.pruner=null"
            )
    every, total = value("trainer.eval_every"), value("trainer.total_frames")
    if isinstance(every, int) and isinstance(total, int) and every >= total:
        raise StudyConfigError(
            f"{name}: trainer.eval_every={every} >= trainer.total_frames={total}: the trials "
            "evaluate only at their end, so the pruner has no intermediate value to stop one "
            "early; set trainer.eval_every below trainer.total_frames or hydra.sweeper.pruner=null"
        )


def tell(study: Any, number: int, values: Any = None, state: Any = None) -> None:
    """``study.tell``; the grid and brute-force samplers call ``study.stop()`` once every point is
    asked, which Optuna refuses outside ``optimize`` (the trial is recorded all the same)."""
    try:
        study.tell(number, values, state=state)
    except RuntimeError as exc:
        if "Study.stop" not in str(exc):
            raise


def override_value(value: Any) -> str:
    """``value`` (a string, number, bool, None, list or dict) as Hydra's override grammar reads it
    back: strings quoted, dicts and lists in its flow syntax."""
    if isinstance(value, dict):
        return "{" + ",".join(f"{k}:{override_value(v)}" for k, v in value.items()) + "}"
    if isinstance(value, (list, tuple)):
        return "[" + ",".join(override_value(v) for v in value) + "]"
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    return "'" + str(value).replace("\\", "\\\\").replace("'", "\\'") + "'"
