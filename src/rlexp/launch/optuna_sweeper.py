"""``hydra/sweeper=rlexp_optuna``: hydra-optuna-sweeper whose study lives in the sweep dir, so that
re-running the same ``python train.py -m ...`` command continues the sweep.

Hydra's own sweepers cannot resume (facebookresearch/hydra#3328): they ask ``n_trials`` new trials
on every run and number the job dirs from 0, over the earlier trials' dirs. Here:

- the study is kept in ``hydra.sweeper.storage``, by default ``<sweep dir>/optuna.db`` (SQLite,
  Optuna's RDB storage; optuna 2.x, which hydra-optuna-sweeper pins, has no JournalStorage). Only
  this process writes it: the trials' jobs never open it, so a sweep dir on NFS is fine;
- ``n_trials`` is the study's total: each trial owns a job dir named by its job number
  (``hydra.job.num``; the trial number unless a failed trial was retried), recorded on the trial
  (system attr :data:`JOB_ATTR`). A re-run keeps the finished trials and their dirs untouched,
  re-runs a trial left ``RUNNING`` by a killed sweep in place (the same trial, the same dir: the
  job resumes from its newest checkpoint; a job that had finished is not run again, the trial is
  told the result in its dir), retries a ``FAIL`` trial with the same parameters
  (Optuna's way: ``study.enqueue_trial(params)``; a new trial of the study, in the failed one's dir,
  as a grid sweep re-runs a failed job), and asks new trials only for the job dirs still missing;
- a trial whose job failed (rlexp's task function returns None) is told ``FAIL`` and the sweep goes
  on; a sweep in which no trial completed ends without ``optimization_results.yaml`` and without
  Optuna's traceback: rlexp's summary line (``rlexp.launch.sweep``) says what happened;
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
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hydra.core.utils import JobReturn, JobStatus
from hydra.utils import instantiate
from hydra_plugins.hydra_optuna_sweeper._impl import OptunaSweeperImpl, create_params_from_overrides
from omegaconf import DictConfig, OmegaConf

from rlexp.fsutil import HolderBusy, HolderLock

log = logging.getLogger(__name__)

#: The study's file in the sweep dir (conf/hydra/sweeper/rlexp_optuna.yaml's default storage).
STUDY_FILE = "optuna.db"
#: Held by the sweep that runs the study (flock), with its pid and host for the one that is refused.
LOCK_FILE = "optuna.lock"
#: Trial system attr: the job number (job dir name) the trial runs in.
JOB_ATTR = "rlexp_job"
#: Trial system attr of a retry: the number of the failed trial it repeats.
RETRY_ATTR = "rlexp_retry_of"
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
    trial: Any = None  # resume: the RUNNING optuna Trial
    retry_of: Any = None  # retry: the failed FrozenTrial


def check_sqlalchemy() -> None:
    """optuna 2.x's RDB storage cannot open SQLite with SQLAlchemy 2 (its alembic stamp is never
    committed: an AssertionError, then 'database is locked'); say so in one line."""
    import optuna
    import sqlalchemy

    if int(optuna.__version__.split(".")[0]) < 3 and int(sqlalchemy.__version__.split(".")[0]) >= 2:
        raise SweepRefused(
            f"optuna {optuna.__version__} (pinned by hydra-optuna-sweeper) cannot keep a study in "
            f"SQLite with SQLAlchemy {sqlalchemy.__version__}: pip install 'sqlalchemy<2' "
            "'alembic<1.17' (rlexp's optuna extra pins them), or set hydra.sweeper.storage=null "
            "(in memory: the sweep cannot be continued)"
        )


class SweepLock:
    """An exclusive ``flock`` on ``<sweep dir>/optuna.lock`` for the life of the sweep (a
    ``rlexp.fsutil.HolderLock``)."""

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


def job_of(trial: Any) -> int | None:
    """The job number a trial ran in (None: a trial rlexp did not launch)."""
    job = trial.system_attrs.get(JOB_ATTR)
    return job if isinstance(job, int) else None


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
            work.append(Work("resume", job))
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
    job skips only if its ``config.yaml`` proves the same config (``rlexp.run_proof``)."""
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


class ResumableOptunaSweeperImpl(OptunaSweeperImpl):
    """hydra-optuna-sweeper's implementation (search space, sampler, overrides) with the resumable
    sweep loop described in the module docstring."""

    def setup(self, *, hydra_context: Any, task_function: Any, config: DictConfig) -> None:
        super().setup(hydra_context=hydra_context, task_function=task_function, config=config)
        self.sampler_config = OmegaConf.select(config, "hydra.sweeper.sampler")

    def sweep(self, arguments: list[str]) -> None:
        """Continue (or start) the study in the sweep dir up to ``n_trials`` job dirs."""
        lock = SweepLock(Path(str(self.sweep_dir)))
        try:
            lock.acquire()
            study = self._open_study()
            self._run(study, arguments)
        except SweepRefused as exc:
            log.error("%s", exc)
            sys.exit(EXIT_REFUSED)
        finally:
            lock.release()

    def _configure_trials(
        self, trials: list[Any], search_space_distributions: dict, fixed_params: dict
    ) -> Sequence[Sequence[str]]:
        """The plugin's overrides, in the search space's order: a trial re-run from the storage
        lists its params by name, and its job's overrides must read as its first attempt's."""
        overrides = super()._configure_trials(trials, search_space_distributions, fixed_params)
        order = {name: i for i, name in enumerate([*search_space_distributions, *fixed_params])}
        rank = lambda o: order.get(o.split("=", 1)[0], len(order))  # noqa: E731
        return [tuple(sorted(o, key=rank)) for o in overrides]

    def _open_study(self) -> Any:
        import optuna

        if self.storage is None:
            log.warning(
                "hydra.sweeper.storage is null: the study is in memory and this sweep cannot be "
                "continued by running it again"
            )
        elif str(self.storage).startswith("sqlite:"):
            check_sqlalchemy()
            Path(str(self.sweep_dir)).mkdir(parents=True, exist_ok=True)
        directions = self._get_directions()
        try:
            study = optuna.create_study(
                study_name=self.study_name,
                storage=self.storage,
                sampler=self.sampler if not callable(self.sampler) else None,
                directions=directions,
                load_if_exists=True,
            )
        except Exception as exc:  # a URL it cannot open, a file that is not a study
            raise SweepRefused(f"cannot open the Optuna study in {self.storage}: {exc}") from None
        have = [d.name.lower() for d in study.directions]
        if have != [d.lower() for d in directions]:
            raise SweepRefused(
                f"study {study.study_name!r} in {self.storage} was created to {have}, this sweep "
                f"asks {directions} (hydra.sweeper.direction): use a new hydra.sweep.dir or "
                "hydra.sweeper.study_name"
            )
        return study

    def _search_space(self, arguments: list[str]) -> tuple[dict, dict]:
        """(distributions, fixed params) from hydra.sweeper.params and the command line, as the
        plugin's ``sweep`` builds them; a GridSampler is built and caps ``n_trials``."""
        import functools

        import optuna

        self._process_searchspace_config()
        params_conf = self._parse_sweeper_params_config() + list(arguments)
        dists, fixed = create_params_from_overrides(params_conf)
        if self.search_space_distributions:
            dists = {**self.search_space_distributions, **dists}
        if (
            isinstance(self.sampler, functools.partial)
            and self.sampler.func == optuna.samplers.GridSampler
        ):
            grid = {name: self._to_grid_sampler_choices(d) for name, d in dists.items()}
            self.sampler = self.sampler(grid)
            self.n_trials = min(self.n_trials, math.prod(len(v) for v in grid.values()))
            log.info("GridSampler: n_trials is %d, the size of the grid", self.n_trials)
        for name in fixed:
            dists.pop(name, None)
        return dists, fixed

    def _reseed(self, study: Any, n_before: int) -> None:
        """A resumed study with a seeded sampler gets ``seed + n_before``: the same seed would
        propose the first run's parameters again (TPE's first trials are its random sampler's)."""
        cfg = self.sampler_config
        if n_before == 0 or cfg is None or cfg.get("_partial_") or cfg.get("seed") is None:
            return
        seed = int(cfg.seed) + n_before
        study.sampler = instantiate(cfg, seed=seed)
        log.info("resumed study: sampler %s reseeded with %d", type(study.sampler).__name__, seed)

    def _run(self, study: Any, arguments: list[str]) -> None:
        from optuna.trial import Trial, TrialState

        dists, fixed = self._search_space(arguments)
        if self.sampler is not None and not callable(self.sampler):
            study.sampler = self.sampler
        trials = study.get_trials(deepcopy=False)
        directions = self._get_directions()
        for t in trials:  # killed between ask() and recording its job: it never ran
            if t.state == TrialState.RUNNING and job_of(t) is None:
                study.tell(t.number, state=TrialState.FAIL)
        if len(directions) == 1:
            self._tell_finished_jobs(study, fixed)
        self._reseed(study, len(trials))
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
        for batch in batches(work, max(1, self.n_jobs)):
            trials_now = []
            for w in batch:
                if w.kind == "resume":
                    trial = Trial(study, heads[w.job]._trial_id)
                else:
                    if w.kind == "retry":
                        study.enqueue_trial(dict(w.retry_of.params))
                    trial = study.ask()
                    trial.set_system_attr(JOB_ATTR, w.job)
                    if w.kind == "retry":
                        trial.set_system_attr(RETRY_ATTR, w.retry_of.number)
                trials_now.append(trial)
            overrides = self._configure_trials(trials_now, dists, fixed)
            returns = self.launcher.launch(overrides, initial_job_idx=batch[0].job)
            failed = 0
            for w, trial, ret in zip(batch, trials_now, returns, strict=True):
                values = trial_value(ret, len(directions))
                if values is None:
                    failed += 1
                    study.tell(trial, state=TrialState.FAIL)
                    log.info("trial %d (job %d) failed", trial.number, w.job)
                else:
                    study.tell(trial, values)
            if failed / len(batch) > self.max_failure_rate:
                log.error(
                    "stopping the sweep: %d of %d trials of the last batch failed "
                    "(hydra.sweeper.max_failure_rate=%s)",
                    failed,
                    len(batch),
                    self.max_failure_rate,
                )
                break
        self._save_results(study, directions)

    def _tell_finished_jobs(self, study: Any, fixed: dict[str, Any]) -> None:
        """A trial left RUNNING whose job had finished (the sweep was killed while another job of
        its batch trained: a launcher returns a batch's results together) is told the result its
        job dir holds, the value rlexp's task function returns on a re-run, and is not launched
        again: its dir stays as it is."""
        from optuna.trial import TrialState

        _, heads = plan_work(study.get_trials(deepcopy=False), 0)
        for job, t in sorted(heads.items()):
            if t.state != TrialState.RUNNING:
                continue
            ran_with = [f"{k}={v}" for k, v in {**t.params, **fixed}.items()]  # as launched
            value = finished_value(Path(str(self.sweep_dir)) / str(job), ran_with)
            if value is not None:
                study.tell(t.number, value)
                log.info(
                    "trial %d: its job dir %d had finished (%s = %s): told, not run again",
                    t.number,
                    job,
                    OBJECTIVE,
                    value,
                )

    def _save_results(self, study: Any, directions: list[str]) -> None:
        """``optimization_results.yaml`` as the plugin writes it, plus the best trial's number and
        job dir; none when no trial completed (the summary line says why)."""
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
        OmegaConf.save(
            OmegaConf.create(results), Path(str(self.sweep_dir)) / "optimization_results.yaml"
        )


def read_trials(sweep_dir: Path) -> list[dict[str, Any]] | str:
    """The trials of the study in ``<sweep_dir>/optuna.db`` (number, job, state, values, params,
    retry_of), or why they cannot be read. Read-only in effect: an existing study is only loaded."""
    path = sweep_dir / STUDY_FILE
    if not path.is_file():
        return f"no {STUDY_FILE} in the sweep dir"
    try:
        import optuna

        check_sqlalchemy()
        optuna.logging.set_verbosity(optuna.logging.WARNING)
        storage = f"sqlite:///{path}"
        out = []
        for summary in optuna.get_all_study_summaries(storage):
            study = optuna.load_study(study_name=summary.study_name, storage=storage)
            for t in study.get_trials(deepcopy=False):
                out.append(
                    {
                        "study": summary.study_name,
                        "number": t.number,
                        "job": job_of(t),
                        "state": t.state.name,
                        "values": t.values,
                        "params": dict(t.params),
                        "retry_of": t.system_attrs.get(RETRY_ATTR),
                    }
                )
        return out
    except (ImportError, SweepRefused) as exc:
        return str(exc)
    except Exception as exc:  # a damaged or foreign file: the report goes on without it
        return f"{STUDY_FILE} is not readable ({type(exc).__name__}: {str(exc).splitlines()[0]})"
