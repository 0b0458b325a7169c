"""``hydra/sweeper=optuna`` (also ``rlexp_optuna``): rlexp's Optuna sweeper, ask-and-tell on
Optuna >= 4, whose study lives in the sweep dir, so that re-running the same
``python train.py -m ...`` command continues the sweep.

Each of ``n_jobs`` workers takes the next trial (``study.ask(distributions)``) as soon as its
previous job ended, no batch barrier (``hydra.sweeper.async_trials``; ``false``: batches of
``n_jobs`` trials, all awaited), launched through Hydra's launcher (basic, ``hydra/launcher=local``,
``slurm``), and tells its value, ``PRUNED`` or ``FAIL`` (``study.tell``; the loop:
``rlexp.launch.optuna_async``). A trial may be ``hydra.sweeper.trial_seeds=N`` jobs, one per seed,
scored by their mean or IQM. With ``hydra.sweeper.pruner``, each job reports its evaluations to
its trial and stops ``pruned`` when the pruner says so (the ``optuna_prune`` hook,
``rlexp.hooks.optuna_prune``). Hydra's own sweepers cannot resume (facebookresearch/hydra#3328): they ask
``n_trials`` new trials on every run and number the job dirs from 0, over the earlier trials' dirs.
Here:

- the study is kept in ``hydra.sweeper.storage``, by default ``<sweep dir>/optuna.journal``
  (Optuna's JournalStorage, safe on a cluster's shared file system; ``rlexp.launch.optuna_study``);
  only this process asks and tells trials; the trials' jobs open it (from any machine) only to
  report intermediate values when a pruner is configured;
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

import logging
import math
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from rlexp.files.fsutil import HolderBusy, HolderLock
from rlexp.launch import optuna_async, optuna_confirm, optuna_plan, optuna_space, optuna_study
from rlexp.launch.optuna_plan import (  # noqa: F401  (batches, trial_value: the plan's API here too)
    ENDED,
    Work,
    batches,
    check_evaluates,
    finished_value,
    override_value,
    plan_work,
    tell,
    trial_value,
)
from rlexp.launch.optuna_space import SearchSpaceError
from rlexp.launch.optuna_study import (
    JOB_ATTR,
    RETRY_ATTR,
    SWEEP_ATTR,
    StudyConfigError,
    in_sweep,
    job_of,
    jobs_of,
    seeds_of,
)

log = logging.getLogger(__name__)

#: Held by the sweep that runs the study (flock), with its pid and host for the one that is refused.
LOCK_FILE = "optuna.lock"
#: What rlexp's task function returns for a trial (``rlexp.app._task``): its final eval return.
OBJECTIVE = optuna_plan.OBJECTIVE
#: Exit code when the sweep cannot start (the dir is in use, the storage cannot be opened).
EXIT_REFUSED = 2


#: A RUNNING trial without a job this old was left by a sweep killed between ``ask`` and recording
#: the trial's job (a moment); a younger one may be another sweep's of a shared study, just asked.
ORPHAN_AGE_S = 60.0


def _orphaned(trial: Any) -> bool:
    """``trial`` (RUNNING, no job recorded) was asked :data:`ORPHAN_AGE_S` ago or more."""
    import datetime

    start = trial.datetime_start
    return start is None or (datetime.datetime.now() - start).total_seconds() >= ORPHAN_AGE_S


class SweepRefused(Exception):
    """The sweep cannot start: one line for the user, then exit :data:`EXIT_REFUSED`."""


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

    @property
    def prunes(self) -> bool:
        """A pruner that needs the jobs' intermediate values (any but none and ``nop``)."""
        return self.pruner is not None and self.pruner["_target_"] != optuna_study.PRUNERS["nop"]


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


def _plain(value: Any) -> Any:
    return OmegaConf.to_container(value, resolve=True) if OmegaConf.is_config(value) else value


def check_spec(sweeper: Any, arguments: Sequence[str], job_cfg: Any = None) -> SweepSpec:
    """``hydra.sweeper`` (a mapping of its keys) and the sweep's command-line ``arguments``,
    checked: a ValueError (``StudyConfigError``, ``SearchSpaceError``) naming the key otherwise;
    ``job_cfg``: the composed config the jobs start from (a pruner needs evaluations during
    training). Imports nothing it would have to run."""
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
    params = _plain(get("params")) or {}
    lines = [f"{k}={v}" for k, v in params.items()] + list(arguments)
    dists, fixed = optuna_space.search_space(lines)
    old = _plain(get("search_space")) or {}
    dists = {
        **{str(k): optuna_space.from_dict(str(k), v) for k, v in old.items() if k not in fixed},
        **dists,
    }
    spec = SweepSpec(optuna_study.directions(get("direction")), sampler, pruner, dists, fixed)
    optuna_study.check_pruner(pruner, len(spec.directions))
    optuna_async.check_trial_seeds(get("trial_seeds", 1), get("trial_objective", "mean"), dists)
    optuna_confirm.confirm_settings(_plain(get("confirm")), len(spec.directions))
    if spec.prunes and job_cfg is not None:
        check_evaluates(pruner, spec, job_cfg)
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
        self.trial_seeds = sweeper.get("trial_seeds", 1)  # jobs (seeds) per trial
        self.trial_objective = sweeper.get("trial_objective", "mean")  # their mean or IQM
        self.async_trials = bool(sweeper.get("async_trials", True))  # false: batches
        self.confirm = sweeper.get("confirm")  # top_k best trials re-run on fresh seeds
        self.prune_overrides: list[str] = []  # the optuna_prune hook, added to every job
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
            spec = check_spec(self.cfg, arguments, self.config)
            self.study = self._open_study(spec)
            self._run(self.study, spec)
            self.end_of_search(spec)
        except (SweepRefused, StudyConfigError, SearchSpaceError) as exc:
            log.error("%s", exc)
            sys.exit(EXIT_REFUSED)
        finally:
            lock.release()

    def end_of_search(self, spec: SweepSpec) -> None:
        """Called once the search ended (``n_trials`` reached or stopped by
        ``max_failure_rate``), after ``optimization_results.yaml``, inside the sweep lock: the
        confirmation of the best trials on fresh seeds (``rlexp.launch.optuna_confirm``)."""
        settings = optuna_confirm.confirm_settings(_plain(self.confirm), len(spec.directions))
        if settings is not None:
            optuna_confirm.confirm(self, settings, spec.directions[0], self.base_seed(spec), spec)

    def run_jobs(self, jobs: list[tuple[int, list[str]]]) -> dict[int, Any]:
        """``jobs`` (job number, overrides) on the sweep's launcher, ``n_jobs`` at a time, each
        starting as soon as a slot frees: job number -> its ``JobReturn``."""
        waiting, returns = list(jobs), {}
        optuna_async.run_loop(
            self.launcher,
            self.n_jobs,
            lambda: waiting.pop(0) if waiting else None,
            returns.__setitem__,
        )
        return returns

    def next_free_job(self) -> int:
        """A job number above every job dir the study's trials used."""
        trials = self.mine(self.study) if self.study is not None else []
        return max((j for t in trials for j in jobs_of(t)), default=-1) + 1

    def base_seed(self, spec: SweepSpec) -> int:
        """The ``seed`` the jobs compose with: a fixed ``seed=`` override, else the config's."""
        text = spec.fixed.get(optuna_async.SEED_KEY, "").split("=", 1)[-1]
        if text.lstrip("-").isdigit():
            return int(text)
        seed = OmegaConf.select(self.config, "seed", default=0) if self.config else 0
        return int(seed) if isinstance(seed, int) else 0

    def seeds_for(self, w: Work, params: dict[str, Any], spec: SweepSpec) -> list[int]:
        """The seeds of ``w``'s jobs: a re-run's recorded ones, else ``base + k`` for a trial of
        several seeds (every trial the same: common random numbers), else its one seed."""
        recorded = (
            seeds_of(w.trial if w.kind == "resume" else w.retry_of) if w.kind != "new" else []
        )
        if len(recorded) == len(w.jobs):
            return recorded
        if len(w.jobs) > 1:
            return [self.base_seed(spec) + k for k in range(len(w.jobs))]
        searched = params.get(optuna_async.SEED_KEY)
        return [int(searched)] if isinstance(searched, int) else [self.base_seed(spec)]

    def unit_overrides(self, base: Sequence[str], seed: int | None) -> list[str]:
        """One job's overrides: the trial's, its own ``seed=`` (a trial of several seeds), and
        the pruning hook's."""
        out = list(base)
        if seed is not None:
            key = optuna_async.SEED_KEY
            out = [o for o in out if o.split("=", 1)[0].lstrip("+~") != key] + [f"{key}={seed}"]
        return out + self.prune_overrides

    def _prune_overrides(self, spec: SweepSpec, study_name: str) -> list[str]:
        """The ``optuna_prune`` hook as overrides: the storage (an absolute path: a job may run
        elsewhere), the study, the pruner, and the job's number (``${hydra:job.num}``)."""
        if not spec.prunes or self.storage is None:
            return []
        storage = str(self.storage)
        for prefix in (optuna_study.JOURNAL, "sqlite:///"):
            if storage.startswith(prefix) and not storage[len(prefix) :].startswith("/"):
                storage = prefix + str(Path(storage[len(prefix) :]).resolve())
        h = "+hooks.optuna_prune"
        return [
            f"{h}.func=optuna_prune",
            f"{h}.params.storage={override_value(storage)}",
            f"{h}.params.study={override_value(study_name)}",
            f"{h}.params.job=${{hydra:job.num}}",
            f"{h}.params.pruner={override_value(spec.pruner)}",
        ]

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
        if spec.prunes and self.storage is None:
            raise StudyConfigError(
                f"hydra.sweeper.pruner={spec.pruner['_target_']} with hydra.sweeper.storage=null: "  # type: ignore[index]
                "the trials' jobs report to the study from their own processes and cannot reach "
                "one in this process's memory; keep the default journal storage"
            )
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

    def mine(self, study: Any) -> list[Any]:
        """The study's trials that run in this sweep dir (the study may be shared)."""
        key = str(self.sweep_dir.resolve())
        return [t for t in study.get_trials(deepcopy=False) if in_sweep(t, key)]

    def _run(self, study: Any, spec: SweepSpec) -> None:
        from optuna.trial import TrialState

        trials = study.get_trials(deepcopy=False)
        for t in self.mine(study):  # killed between ask() and recording its job: it never ran
            if t.state == TrialState.RUNNING and job_of(t) is None and _orphaned(t):
                tell(study, t.number, state=TrialState.FAIL)
        if len(spec.directions) == 1:
            self._tell_finished_jobs(study, spec)
        sampler = self._sampler(spec, len(trials))
        if sampler is not None:
            study.sampler = sampler
        n_seeds = int(self.trial_seeds)
        work, heads = plan_work(self.mine(study), self.n_trials, n_seeds)
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
        self.prune_overrides = self._prune_overrides(spec, study.study_name)
        loop = optuna_async.TrialLoop(self, study, spec, work, batch=not self.async_trials)
        optuna_async.run_loop(self.launcher, self.n_jobs, loop.take, loop.done)
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
        trial.set_user_attr(SWEEP_ATTR, str(self.sweep_dir.resolve()))
        if w.kind == "retry":
            trial.set_user_attr(RETRY_ATTR, w.retry_of.number)
        if spec.custom is not None:
            spec.custom(self.config, trial)
        return trial.number, dict(trial.params)

    def _tell_finished_jobs(self, study: Any, spec: SweepSpec) -> None:
        """A trial left RUNNING whose jobs had all ended (the sweep was killed while another job
        trained) is told what its job dirs hold (the value rlexp's task function returns on a
        re-run, or PRUNED) and is not launched again: its dirs stay as they are."""
        from optuna.trial import TrialState

        _, heads = plan_work(self.mine(study), 0)
        for t in (t for _, t in sorted(heads.items()) if t.state == TrialState.RUNNING):
            jobs = jobs_of(t)
            ran_with = optuna_space.trial_overrides(t.params, spec.dists, spec.fixed)
            if len(jobs) > 1:  # each job has its own seed= in place of a fixed one
                ran_with = tuple(o for o in ran_with if not o.startswith("seed="))
            states = [optuna_async.job_state(self.sweep_dir / str(j)) for j in jobs]
            if "pruned" in states and all(s in ENDED for s in states):
                tell(study, t.number, state=TrialState.PRUNED)
                log.info("trial %d: its job dir(s) %s had ended pruned: told", t.number, jobs)
                continue
            values = [finished_value(self.sweep_dir / str(j), ran_with) for j in jobs]
            if all(v is not None for v in values):
                value = optuna_async.aggregate([[v] for v in values], self.trial_objective)[0]
                tell(study, t.number, value)
                log.info(
                    "trial %d: its job dir %s had finished (%s = %s): told, not run again",
                    t.number,
                    ",".join(map(str, jobs)),
                    OBJECTIVE,
                    value,
                )

    def _save_results(self, study: Any, directions: list[str]) -> None:
        """``optimization_results.yaml`` as hydra-optuna-sweeper wrote it, plus the best trial's
        number and job dir; none when no trial completed (the summary line says why)."""
        from optuna.trial import TrialState

        done = [t for t in self.mine(study) if t.state == TrialState.COMPLETE]
        if not done:
            log.warning(
                "no trial of study %r completed: no optimization_results.yaml", study.study_name
            )
            return
        if len(directions) < 2:  # this sweep's best (a shared study holds other sweeps' too)
            best = (max if directions[0] == "maximize" else min)(done, key=lambda t: t.value)
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
            numbers = {t.number for t in done}
            front = [
                {"params": t.params, "values": t.values, "trial": t.number}
                for t in study.best_trials
                if t.number in numbers
            ]
            results = {"name": "optuna", "solutions": front}
            log.info("Pareto front: %d trial(s)", len(front))
        OmegaConf.save(OmegaConf.create(results), self.sweep_dir / "optimization_results.yaml")
