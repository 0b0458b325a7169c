"""``hydra/sweeper=optuna`` (also ``rlexp_optuna``): rlexp's Optuna sweeper, ask-and-tell on
Optuna >= 4, whose study lives in the sweep dir, so that re-running the same
``python train.py -m ...`` command continues the sweep.

Each batch of ``n_jobs`` trials is asked (``study.ask(distributions)``), launched through Hydra's
launcher (basic, ``hydra/launcher=local``, ``slurm``), and told its job's value or ``FAIL``
(``study.tell``). Hydra's own sweepers cannot resume (facebookresearch/hydra#3328): they ask
``n_trials`` new trials on every run and number the job dirs from 0, over the earlier trials' dirs.
Here:

- the study is kept in ``hydra.sweeper.storage``, by default ``<sweep dir>/optuna.journal``
  (Optuna's JournalStorage, safe on a cluster's shared file system; ``rlexp.launch.optuna_study``);
  only this process writes it: the trials' jobs never open it;
- ``n_trials`` is the study's total: each trial owns a job dir named by its job number
  (``hydra.job.num``; the trial number unless a failed trial was retried), recorded on the trial
  (user attr ``rlexp_job``). A re-run keeps the finished trials and their dirs untouched, re-runs
  a trial left ``RUNNING`` by a killed sweep in place (the same trial, the same dir: the job
  resumes from its newest checkpoint; a job that had finished is not run again, the trial is told
  the result in its dir), retries a ``FAIL`` trial with the same parameters (Optuna's way:
  ``study.enqueue_trial(params)``; a new trial of the study, in the failed one's dir, as a grid
  sweep re-runs a failed job), and asks new trials only for the job dirs still missing;
- a trial whose job failed (rlexp's task function returns None) is told ``FAIL`` and the sweep goes
  on; a sweep in which no trial completed ends without ``optimization_results.yaml`` and without a
  traceback: rlexp's summary line (``rlexp.launch.sweep``) says what happened;
- a resumed study reseeds the sampler with ``seed + trials so far``, so it does not propose again
  the parameters its first run started with;
- one sweep at a time per sweep dir (a lock file beside the study): a second one would re-run the
  first one's trials in flight.
"""

from __future__ import annotations

import json
import logging
import math
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hydra.core.utils import JobReturn, JobStatus
from omegaconf import DictConfig, OmegaConf

from rlexp.files.fsutil import HolderBusy, HolderLock
from rlexp.launch import optuna_space, optuna_study
from rlexp.launch.optuna_space import SearchSpaceError
from rlexp.launch.optuna_study import JOB_ATTR, RETRY_ATTR, StudyConfigError, job_of

log = logging.getLogger(__name__)

#: Held by the sweep that runs the study (flock), with its pid and host for the one that is refused.
LOCK_FILE = "optuna.lock"
#: What rlexp's task function returns for a trial (``rlexp.app._task``): its final eval return.
OBJECTIVE = "eval/episode_return"
#: Exit code when the sweep cannot start (the dir is in use, the storage cannot be opened).
EXIT_REFUSED = 2


class SweepRefused(Exception):
    """The sweep cannot start: one line for the user, then exit :data:`EXIT_REFUSED`."""


@dataclass
class Work:
    """One trial to launch: a killed trial re-run in place, a failed one retried, or a new one."""

    kind: str  # "resume" | "retry" | "new"
    job: int
    trial: Any = None  # resume: the RUNNING FrozenTrial
    retry_of: Any = None  # retry: the failed FrozenTrial


@dataclass
class SweepSpec:
    """The sweeper's config, checked: what a sweep needs before it opens the study."""

    directions: list[str]
    sampler: dict[str, Any] | None
    pruner: dict[str, Any] | None
    dists: dict[str, Any]
    fixed: dict[str, str]
    custom: Callable[[DictConfig, Any], None] | None = None
    grid: dict[str, list[Any]] | None = field(default=None)


class SweepLock:
    """An exclusive ``flock`` on ``<sweep dir>/optuna.lock`` for the life of the sweep (a
    ``rlexp.files.fsutil.HolderLock``)."""

    def __init__(self, sweep_dir: Path) -> None:
        self.path = sweep_dir / LOCK_FILE
        self._lock = HolderLock(self.path)

    def acquire(self) -> None:
        try:
            self._lock.acquire()
        except HolderBusy as busy:
            raise SweepRefused(
                f"sweep dir {self.path.parent} is in use by another Optuna sweep ({busy.holder}): "
                "wait for it to end (a killed sweep holds nothing)"
            ) from None

    def release(self) -> None:
        self._lock.release()


def plan_work(trials: Sequence[Any], n_trials: int) -> tuple[list[Work], dict[int, Any]]:
    """What a (re-)run of the study does: per job dir its latest trial decides (RUNNING: killed,
    re-run in place; FAIL: retried; COMPLETE/PRUNED: kept), then new trials up to ``n_trials``
    job dirs. Returns (the work in job order, the latest trial of every job dir)."""
    from optuna.trial import TrialState

    heads: dict[int, Any] = {}
    for t in sorted(trials, key=lambda t: t.number):
        job = job_of(t)
        if job is not None:
            heads[job] = t
    work = []
    for job, t in sorted(heads.items()):
        if t.state == TrialState.RUNNING:
            work.append(Work("resume", job, trial=t))
        elif t.state == TrialState.FAIL:
            work.append(Work("retry", job, retry_of=t))
    start = max(heads) + 1 if heads else 0
    work += [Work("new", start + i) for i in range(max(0, n_trials - len(heads)))]
    return work, heads


def batches(work: list[Work], size: int) -> list[list[Work]]:
    """Runs of at most ``size`` items with consecutive job numbers: a launcher numbers one call's
    jobs from its first (``initial_job_idx``), and the job number is the job dir."""
    out: list[list[Work]] = []
    for item in work:
        last = out[-1] if out else None
        if last and len(last) < size and item.job == last[-1].job + 1:
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
    if not isinstance(status, dict) or status.get("state") not in ("finished", "stopped_early"):
        return None
    missing = sorted(set(overrides) - set(_job_overrides(job_dir)))
    if missing:
        log.warning("job dir %s did not run with %s: its result is not taken", job_dir, missing)
        return None
    final = status.get("final_eval")
    value = final.get(OBJECTIVE) if isinstance(final, dict) else None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        return None
    return float(value)


def _job_overrides(job_dir: Path) -> list[str]:
    """The job dir's ``.hydra/overrides.yaml`` ([] when missing or not a list of strings)."""
    try:
        listed = OmegaConf.to_container(OmegaConf.load(job_dir / ".hydra" / "overrides.yaml"))
    except Exception:
        return []
    return [str(o) for o in listed] if isinstance(listed, list) else []


def _plain(value: Any) -> Any:
    return OmegaConf.to_container(value, resolve=True) if OmegaConf.is_config(value) else value


def check_spec(sweeper: Any, arguments: Sequence[str]) -> SweepSpec:
    """``hydra.sweeper`` (a mapping of its keys) and the sweep's command-line ``arguments``,
    checked: a ValueError (``StudyConfigError``, ``SearchSpaceError``) naming the key otherwise.
    Imports nothing it would have to run."""
    get = sweeper.get
    rate = get("max_failure_rate", 1.0)
    if not isinstance(rate, (int, float)) or not 0.0 <= rate <= 1.0:
        raise StudyConfigError(f"hydra.sweeper.max_failure_rate={rate!r}: a share in [0, 1]")
    sampler = optuna_study.leaf_config(
        "hydra.sweeper.sampler", _plain(get("sampler")), optuna_study.SAMPLERS
    )
    pruner = optuna_study.leaf_config(
        "hydra.sweeper.pruner", _plain(get("pruner")), optuna_study.PRUNERS
    )
    optuna_study.check_pruner(pruner)
    params = _plain(get("params")) or {}
    lines = [f"{k}={v}" for k, v in params.items()] + list(arguments)
    dists, fixed = optuna_space.search_space(lines)
    old = _plain(get("search_space")) or {}
    dists = {
        **{str(k): optuna_space.from_dict(str(k), v) for k, v in old.items() if k not in fixed},
        **dists,
    }
    spec = SweepSpec(optuna_study.directions(get("direction")), sampler, pruner, dists, fixed)
    if sampler is not None and sampler["_target_"] == optuna_study.SAMPLERS["grid"]:
        spec.grid = {k: optuna_space.grid_choices(k, d) for k, d in dists.items()}
    custom = get("custom_search_space")
    if custom:
        from rlexp.common.registry import reach

        module, _, name = str(custom).rpartition(".")
        where = f"hydra.sweeper.custom_search_space={custom!r}"
        try:  # the user's own module (not the standard library's), a function defined there
            spec.custom = reach(module, name, where, None)
        except ValueError as exc:
            raise StudyConfigError(str(exc)) from None
    return spec


def _tell(study: Any, number: int, values: Any = None, state: Any = None) -> None:
    """``study.tell``; the grid and brute-force samplers call ``study.stop()`` once every point is
    asked, which Optuna refuses outside ``optimize`` (the trial is recorded all the same)."""
    try:
        study.tell(number, values, state=state)
    except RuntimeError as exc:
        if "Study.stop" not in str(exc):
            raise


class OptunaSweep:
    """The resumable ask-and-tell loop described in the module docstring (the Hydra plugin class
    ``hydra_plugins.rlexp_sweeper.RlexpOptunaSweeper`` hands its config here)."""

    def __init__(self, **sweeper: Any) -> None:
        self.cfg = sweeper
        self.n_trials = int(sweeper.get("n_trials", 20))
        self.n_jobs = max(1, int(sweeper.get("n_jobs", 1)))
        self.max_failure_rate = float(sweeper.get("max_failure_rate", 1.0))
        self.storage = sweeper.get("storage")
        self.study_name = sweeper.get("study_name")
        self.config: DictConfig | None = None
        self.launcher: Any = None
        self.sweep_dir = Path(".")
        self.study: Any = None  # the optuna Study once the sweep opened it

    def setup(self, *, hydra_context: Any, task_function: Any, config: DictConfig) -> None:
        from hydra.core.plugins import Plugins

        launcher = Plugins.instance().instantiate_launcher(
            config=config, hydra_context=hydra_context, task_function=task_function
        )
        self.bind(config, launcher)

    def bind(self, config: DictConfig, launcher: Any) -> None:
        """The sweep's config and the launcher its batches go through (``setup``, or a test)."""
        self.config, self.launcher = config, launcher
        self.sweep_dir = Path(str(config.hydra.sweep.dir))

    def sweep(self, arguments: list[str]) -> None:
        """Continue (or start) the study in the sweep dir up to ``n_trials`` job dirs."""
        lock = SweepLock(self.sweep_dir)
        try:
            lock.acquire()
            spec = check_spec(self.cfg, arguments)
            self.study = self._open_study(spec)
            self._run(self.study, spec)
        except (SweepRefused, StudyConfigError, SearchSpaceError) as exc:
            log.error("%s", exc)
            sys.exit(EXIT_REFUSED)
        finally:
            lock.release()

    def storage_spec(self) -> Any:
        """``hydra.sweeper.storage``; the default journal becomes the sweep dir's ``optuna.db``
        where an rlexp before the journal left its study there (and no journal exists yet)."""
        path = optuna_study.journal_path(self.storage) if isinstance(self.storage, str) else None
        legacy = self.sweep_dir / "optuna.db"
        if path is not None and path.name == "optuna.journal" and not path.exists():
            if path.parent.resolve() == self.sweep_dir.resolve() and legacy.is_file():
                log.info("continuing the SQLite study of an earlier rlexp: %s", legacy)
                return f"sqlite:///{legacy}"
        return self.storage

    def _open_study(self, spec: SweepSpec) -> Any:
        import optuna

        optuna.logging.set_verbosity(optuna.logging.WARNING)
        if self.storage is None:
            log.warning(
                "hydra.sweeper.storage is null: the study is in memory and this sweep cannot be "
                "continued by running it again"
            )
        self.storage = self.storage_spec()
        storage = optuna_study.make_storage(self.storage)
        pruner = optuna_study.build(spec.pruner)
        study = optuna_study.open_study(
            storage, self.storage, self.study_name, spec.directions, None, pruner
        )
        if spec.grid is not None:
            self.n_trials = min(self.n_trials, math.prod(len(v) for v in spec.grid.values()))
            log.info("GridSampler: n_trials is %d, the size of the grid", self.n_trials)
        return study

    def _sampler(self, spec: SweepSpec, n_before: int) -> Any:
        """The configured sampler; a seeded one gets ``seed + n_before`` on a resumed study: the
        same seed would propose the first run's parameters again (TPE's first trials are its
        random sampler's)."""
        if spec.sampler is None:
            return None
        kwargs: dict[str, Any] = {}
        if spec.grid is not None:
            kwargs["search_space"] = spec.grid
        seed = spec.sampler.get("seed")
        if n_before and seed is not None:
            kwargs["seed"] = int(seed) + n_before
        sampler = optuna_study.build(spec.sampler, **kwargs)
        if "seed" in kwargs and n_before:
            log.info(
                "resumed study: sampler %s reseeded with %d", type(sampler).__name__, kwargs["seed"]
            )
        return sampler

    def _run(self, study: Any, spec: SweepSpec) -> None:
        from optuna.trial import TrialState

        trials = study.get_trials(deepcopy=False)
        for t in trials:  # killed between ask() and recording its job: it never ran
            if t.state == TrialState.RUNNING and job_of(t) is None:
                _tell(study, t.number, state=TrialState.FAIL)
        if len(spec.directions) == 1:
            self._tell_finished_jobs(study, spec)
        sampler = self._sampler(spec, len(trials))
        if sampler is not None:
            study.sampler = sampler
        work, heads = plan_work(study.get_trials(deepcopy=False), self.n_trials)
        kept = sum(t.state in (TrialState.COMPLETE, TrialState.PRUNED) for t in heads.values())
        counts = {k: sum(w.kind == k for w in work) for k in ("resume", "retry", "new")}
        log.info(
            "study %r in %s: %d trial(s) kept, %d killed to re-run, %d failed to retry, %d new "
            "(n_trials=%d)",
            study.study_name,
            self.storage,
            kept,
            counts["resume"],
            counts["retry"],
            counts["new"],
            self.n_trials,
        )
        for batch in batches(work, self.n_jobs):
            asked = [self._ask(study, spec, w) for w in batch]
            overrides = [optuna_space.trial_overrides(p, spec.dists, spec.fixed) for _, p in asked]
            returns = self.launcher.launch(overrides, initial_job_idx=batch[0].job)
            failed = 0
            for w, (number, _), ret in zip(batch, asked, returns, strict=True):
                values = trial_value(ret, len(spec.directions))
                if values is None:
                    failed += 1
                    _tell(study, number, state=TrialState.FAIL)
                    log.info("trial %d (job %d) failed", number, w.job)
                else:
                    _tell(study, number, values)
            if failed / len(batch) > self.max_failure_rate:
                log.error(
                    "stopping the sweep: %d of %d trials of the last batch failed "
                    "(hydra.sweeper.max_failure_rate=%s)",
                    failed,
                    len(batch),
                    self.max_failure_rate,
                )
                break
        self._save_results(study, spec.directions)

    def _ask(self, study: Any, spec: SweepSpec, w: Work) -> tuple[int, dict[str, Any]]:
        """(trial number, parameters) of ``w``: the killed trial itself, or a trial asked now (a
        retry enqueued first with the failed trial's parameters), its job dir recorded on it."""
        if w.kind == "resume":
            return w.trial.number, dict(w.trial.params)
        if w.kind == "retry":
            study.enqueue_trial(dict(w.retry_of.params))
        trial = study.ask(spec.dists)
        trial.set_user_attr(JOB_ATTR, w.job)
        if w.kind == "retry":
            trial.set_user_attr(RETRY_ATTR, w.retry_of.number)
        if spec.custom is not None:
            spec.custom(self.config, trial)
        return trial.number, dict(trial.params)

    def _tell_finished_jobs(self, study: Any, spec: SweepSpec) -> None:
        """A trial left RUNNING whose job had finished (the sweep was killed while another job of
        its batch trained: a launcher returns a batch's results together) is told the result its
        job dir holds, the value rlexp's task function returns on a re-run, and is not launched
        again: its dir stays as it is."""
        from optuna.trial import TrialState

        _, heads = plan_work(study.get_trials(deepcopy=False), 0)
        for job, t in sorted(heads.items()):
            if t.state != TrialState.RUNNING:
                continue
            ran_with = optuna_space.trial_overrides(t.params, spec.dists, spec.fixed)
            value = finished_value(self.sweep_dir / str(job), ran_with)
            if value is not None:
                _tell(study, t.number, value)
                log.info(
                    "trial %d: its job dir %d had finished (%s = %s): told, not run again",
                    t.number,
                    job,
                    OBJECTIVE,
                    value,
                )

    def _save_results(self, study: Any, directions: list[str]) -> None:
        """``optimization_results.yaml`` as hydra-optuna-sweeper wrote it, plus the best trial's
        number and job dir; none when no trial completed (the summary line says why)."""
        from optuna.trial import TrialState

        done = [t for t in study.get_trials(deepcopy=False) if t.state == TrialState.COMPLETE]
        if not done:
            log.warning(
                "no trial of study %r completed: no optimization_results.yaml", study.study_name
            )
            return
        if len(directions) < 2:
            best = study.best_trial
            results: dict[str, Any] = {
                "name": "optuna",
                "best_params": best.params,
                "best_value": best.value,
                "best_trial": best.number,
                "best_job": job_of(best),
            }
            log.info(
                "best: trial %d (job %s) %s = %s",
                best.number,
                job_of(best),
                best.params,
                best.value,
            )
        else:
            front = [
                {"params": t.params, "values": t.values, "trial": t.number}
                for t in study.best_trials
            ]
            results = {"name": "optuna", "solutions": front}
            log.info("Pareto front: %d trial(s)", len(front))
        OmegaConf.save(OmegaConf.create(results), self.sweep_dir / "optimization_results.yaml")
