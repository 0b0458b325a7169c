"""The Optuna sweeper's trial loop: each of ``n_jobs`` workers takes the next trial from the study
as soon as its previous job ended (``hydra.sweeper.async_trials=true``, the default), or the
batches of before (``false``: ``n_jobs`` trials asked, all awaited, all told).

A trial is one job, or ``hydra.sweeper.trial_seeds=N`` jobs (one per seed, job dirs numbered
together); it is told once its last job is back: ``FAIL`` if a job failed, ``PRUNED`` if a job's
``status.json`` says ``pruned`` (the ``optuna_prune`` hook stopped it), else the job's value, or
the mean / IQM of its jobs' values (``hydra.sweeper.trial_objective``). A trial whose job a stop
signal interrupted (``status.json``: ``interrupted``) is not told: it stays RUNNING and the same
command resumes it in place, as one the sweep was killed in.

The launcher runs the jobs: ``launch_stream(n_jobs, take, done)`` where it has one (rlexp's
``hydra/launcher=local`` and ``slurm``: a job starts the moment a slot is free), else its ``launch``
one job at a time (Hydra's basic launcher runs jobs in this process, one after the other). Every
ask and tell happens in the sweep's main thread: the study has one writer of trial states.

``hydra.sweeper.max_failure_rate``: asynchronously, no new trial is asked once more than that
share of the trials this run told (``n_jobs`` of them at least) failed; the trials in flight end.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rlexp.launch.optuna_plan import batches, tell, trial_value
from rlexp.launch.optuna_space import trial_overrides
from rlexp.launch.optuna_study import (
    JOBS_ATTR,
    OVERRIDES_ATTR,
    SEEDS_ATTR,
)

log = logging.getLogger(__name__)

#: What ``take`` returns when no job may start until a running one ends (a batch's barrier).
WAIT = "wait"
#: How a trial of several seeds scores (``hydra.sweeper.trial_objective``).
TRIAL_OBJECTIVES = ("mean", "iqm")
#: The config key a trial's seeds go to.
SEED_KEY = "seed"


@dataclass
class Trial:
    """A trial in flight: its number, its jobs and what each returned so far."""

    number: int
    jobs: list[int]
    overrides: dict[int, list[str]]  # job -> its overrides
    values: dict[int, list[float] | None] = field(default_factory=dict)  # None: the job failed


def aggregate(values: Sequence[Sequence[float]], how: str) -> list[float]:
    """Per objective, the ``mean`` or the ``iqm`` (interquartile mean, ``rlexp.analysis.stats``)
    of the seeds' values."""
    if len(values) == 1:
        return list(values[0])
    out = []
    for column in zip(*values, strict=True):
        if how == "iqm":
            import numpy as np

            from rlexp.analysis.stats import iqm

            out.append(float(iqm(np.asarray(column, dtype=float))))
        else:
            out.append(sum(column) / len(column))
    return out


def job_state(job_dir: Path) -> str | None:
    """The ``state`` of a job dir's ``status.json`` (None when it has none)."""
    try:
        status = json.loads((job_dir / "status.json").read_text())
    except (OSError, ValueError):
        return None
    return status.get("state") if isinstance(status, dict) else None


class TrialLoop:
    """Hands the launcher jobs (``take``) and takes their returns (``done``) for the sweep's work
    plan: ``sweep`` is the ``OptunaSweep`` (its ``_ask``, ``seeds_for``, ``unit_overrides``)."""

    def __init__(self, sweep: Any, study: Any, spec: Any, work: list[Any], batch: bool) -> None:
        self.sweep, self.study, self.spec = sweep, study, spec
        self.groups = batches(work, sweep.n_jobs) if batch else [work]
        self.batch = batch
        self.pending: list[tuple[int, list[str]]] = []  # jobs of asked trials not started yet
        self.trials: dict[int, Trial] = {}  # job -> its trial in flight
        self.in_flight = 0  # jobs started, not back
        self.told: list[tuple[int, Any]] = []  # batch: told once the batch is back
        self.ended = self.failed = 0
        self.stopped = False

    # -- what the launcher calls ----------------------------------------------------------------
    def take(self) -> tuple[int, list[str]] | str | None:
        """The next job to start; :data:`WAIT` behind a batch's barrier; None: no more."""
        while not self.pending:
            if self.batch and self.in_flight:
                return WAIT
            self._tell_batch()
            if self.stopped or not self.groups:
                return None
            group = self.groups[0]
            if not group:
                self.groups.pop(0)
                continue
            if self.batch:  # the whole batch asked at once, as before
                self.groups.pop(0)
                for w in group:
                    self._start_trial(w)
            else:
                self._start_trial(group.pop(0))
        self.in_flight += 1
        return self.pending.pop(0)

    def done(self, job: int, ret: Any) -> None:
        """A job is back: its value kept; the trial told once all its jobs are."""
        self.in_flight -= 1
        trial = self.trials.pop(job)
        trial.values[job] = trial_value(ret, len(self.spec.directions))
        if len(trial.values) < len(trial.jobs):
            return
        state, values = self._outcome(trial)
        if state is None:  # a stop signal interrupted it: RUNNING, resumed in place on a re-run
            log.info("trial %d (job %s) interrupted: left to resume", trial.number, trial.jobs)
            return
        if self.batch:
            self.told.append((trial.number, (state, values, trial)))
        else:
            self._tell(trial, state, values)

    # -- the trials -----------------------------------------------------------------------------
    def _start_trial(self, w: Any) -> None:
        number, params = self.sweep._ask(self.study, self.spec, w)
        base = trial_overrides(params, self.spec.dists, self.spec.fixed)
        seeds = self.sweep.seeds_for(w, params, self.spec)
        self.study._storage.set_trial_user_attr(self._id(number), JOBS_ATTR, list(w.jobs))
        self.study._storage.set_trial_user_attr(self._id(number), SEEDS_ATTR, seeds)
        self.study._storage.set_trial_user_attr(self._id(number), OVERRIDES_ATTR, list(base))
        trial = Trial(number, list(w.jobs), {})
        for job, seed in zip(w.jobs, seeds if len(w.jobs) > 1 else [None], strict=True):
            trial.overrides[job] = self.sweep.unit_overrides(base, seed)
            self.trials[job] = trial
            self.pending.append((job, trial.overrides[job]))

    def _id(self, number: int) -> int:
        return self.study._storage.get_trial_id_from_study_id_trial_number(
            self.study._study_id, number
        )

    def _outcome(self, trial: Trial) -> tuple[Any, list[float] | None]:
        """(state, values) to tell; (None, None): a job was interrupted, the trial stays RUNNING."""
        from optuna.trial import TrialState

        states = [job_state(self.sweep.sweep_dir / str(j)) for j in trial.jobs]
        if "interrupted" in states:
            return None, None
        if "pruned" in states:
            return TrialState.PRUNED, None
        got = [trial.values[j] for j in trial.jobs]
        if any(v is None for v in got):
            return TrialState.FAIL, None
        return TrialState.COMPLETE, aggregate(got, self.sweep.trial_objective)  # type: ignore[arg-type]

    def _tell(self, trial: Trial, state: Any, values: list[float] | None) -> None:
        from optuna.trial import TrialState

        jobs = ",".join(map(str, trial.jobs))
        if state == TrialState.COMPLETE:
            tell(self.study, trial.number, values)
            log.info("trial %d (job %s): %s", trial.number, jobs, values)
        else:
            tell(self.study, trial.number, state=state)
            log.info("trial %d (job %s) %s", trial.number, jobs, state.name.lower())
        self.ended += 1
        self.failed += state == TrialState.FAIL
        if not self.batch and self.ended >= self.sweep.n_jobs:
            self._check_failures(self.failed, self.ended, "so far")

    def _tell_batch(self) -> None:
        if not self.told:
            return
        told, self.told = self.told, []
        failed_before = self.failed
        for _, (state, values, trial) in sorted(told, key=lambda x: x[0]):
            self._tell(trial, state, values)
        self._check_failures(self.failed - failed_before, len(told), "of the last batch")

    def _check_failures(self, failed: int, of: int, which: str) -> None:
        rate = self.sweep.max_failure_rate
        if not self.stopped and failed / of > rate:
            log.error(
                "stopping the sweep: %d of %d trials %s failed (hydra.sweeper.max_failure_rate=%s)",
                failed,
                of,
                which,
                rate,
            )
            self.stopped = True
            self.groups = []


def run_loop(launcher: Any, n_jobs: int, take: Callable[[], Any], done: Callable) -> None:
    """The jobs through ``launcher.launch_stream`` (rlexp's local and SLURM launchers), else
    through its ``launch``, one job at a time."""
    stream = getattr(launcher, "launch_stream", None)
    if callable(stream):
        stream(n_jobs, take, done)
        return
    while (item := take()) is not None:
        if item == WAIT:  # nothing runs here while take is asked: a barrier cannot hold
            raise RuntimeError("the trial loop waited with no job running")
        job, overrides = item
        done(job, launcher.launch([overrides], initial_job_idx=job)[0])


def check_trial_seeds(n: Any, how: Any, dists: Any) -> None:
    """``trial_seeds`` a whole number >= 1, ``trial_objective`` mean or iqm, ``seed`` not searched
    when a trial is several seeds."""
    from rlexp.launch.optuna_study import StudyConfigError

    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise StudyConfigError(f"hydra.sweeper.trial_seeds={n!r}: a whole number >= 1")
    if how not in TRIAL_OBJECTIVES:
        raise StudyConfigError(
            f"hydra.sweeper.trial_objective={how!r}: choose from {list(TRIAL_OBJECTIVES)}"
        )
    if n > 1 and SEED_KEY in dists:
        raise StudyConfigError(
            f"hydra.sweeper.trial_seeds={n} gives each trial its own {n} seeds: take {SEED_KEY} "
            "out of the search space (hydra.sweeper.params or the command line)"
        )
