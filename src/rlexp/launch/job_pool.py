"""``hydra/launcher=local`` (and the plugin's ``joblib``): each job of a sweep in a process of its
own, ``n_jobs`` at a time, so that one job that dies never takes the others with it.

joblib's loky pool, which ran the jobs before, treats a worker that dies (SIGKILL from the OOM
killer, a segfault in an env) as a broken pool: it SIGKILLs every other worker mid-iteration (no
stop checkpoint, ``status.json`` left ``running``) and the sweep ends in its traceback. Here each job
is a fresh ``spawn`` process started for it: a job process that ends without handing back its
result is recorded as dead in its own ``status.json`` (``failed``, how it died, the step, the resume
point, ``exit_code`` 128 + N), the running jobs go on, the next ones start, and the sweep's summary
counts it as failed (exit 1). Running the same command again resumes it from its newest checkpoint
and skips the finished jobs.

Stop signals keep the rules of ``launch/sweep_stop.py``: the job processes start with the stop
signals blocked (the sweep's threads keep them blocked) and take them once their handlers are in
place (``signals.become_sweep_worker``); after a stop no further job starts. A job process gets
SIGTERM when the sweep's process dies (``PR_SET_PDEATHSIG``): it saves at its safe point and stops.
"""

from __future__ import annotations

import logging
import multiprocessing
import multiprocessing.connection
import os
import signal
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from rlexp.launch.sweep_stop import exit_stopped

log = logging.getLogger(__name__)

#: How often the sweep's process looks at its job processes when nothing else wakes it (s).
POLL_S = 0.5


def n_jobs_of(value: Any) -> int:
    """joblib's ``n_jobs``: a positive count, or -1 for one per CPU (-2: all but one, ...)."""
    cpus = os.cpu_count() or 1
    n = int(value) if value is not None else -1
    return max(1, n if n > 0 else cpus + 1 + n)


def _job_main(payload: bytes, conn: Any, parent: int) -> None:
    """A job process: take the stop signals, run the job, send its ``JobReturn`` back."""
    import cloudpickle  # (a requirement of joblib, which hydra/launcher=local needs)

    from rlexp.runtime.signals import become_sweep_worker, die_with_parent

    become_sweep_worker()
    die_with_parent(parent, signal.SIGTERM)  # the sweep's process ended: a stop at a safe point
    fn, args = cloudpickle.loads(payload)
    ret = fn(*args)
    try:
        data = cloudpickle.dumps(ret)
    except Exception:  # a return value that does not pickle: the sweep's summary reads the dir
        ret.return_value = None
        data = cloudpickle.dumps(ret)
    conn.send_bytes(data)
    conn.close()


class Job:
    """One job's process, the pipe its result comes through, and where its run dir is."""

    def __init__(self, idx: int, overrides: Sequence[str], run_dir: Path | None) -> None:
        self.idx = idx
        self.overrides = list(overrides)
        self.run_dir = run_dir
        self.process: Any = None
        self.conn: Any = None
        self.result: Any = None

    @property
    def label(self) -> str:
        return str(self.run_dir) if self.run_dir is not None else f"#{self.idx}"


def died_reason(code: int | None, pid: int | None, step: int, resume_point: str) -> str:
    """Why a job process that handed back nothing ended, as one line for its ``status.json``."""
    if code is not None and code < 0:
        name = signal.Signals(-code).name
        how = f"was killed by {name}" + (" (as the OOM killer does)" if -code == 9 else "")
    else:
        how = f"exited with code {code} without a result"
    return (
        f"the job's process (PID {pid}) {how} after step {step}; {resume_point}; the other jobs "
        "went on; run the same command again to resume it"
    )


def exit_code_of(code: int | None) -> int:
    """The shell's code for a process that ended with ``code`` (-N: 128 + N)."""
    if code is None:
        return 1
    return 128 - code if code < 0 else code


def record_died(job: Job) -> None:
    """Write ``failed`` into a dead job's ``status.json`` (never over a final state it wrote)."""
    from rlexp.checkpoints.files import latest_good_checkpoint
    from rlexp.run.rundir import read_status, write_status

    code = job.process.exitcode
    if job.run_dir is None:
        log.error("job #%d died (exit %s) before it had a run dir", job.idx, code)
        return
    status = read_status(job.run_dir)
    if status.get("state") not in (None, "running"):
        return  # it ended its run (finished, failed, interrupted) and died after
    ckpt = None
    try:
        ckpt = latest_good_checkpoint(job.run_dir / "checkpoints", move_aside=False)
    except Exception:  # an unreadable dir: no resume point named
        ckpt = None
    point = f"the resume point is {ckpt['path']}" if ckpt else "no checkpoint was written"
    step = status.get("global_step") if isinstance(status.get("global_step"), int) else 0
    step = max(step, int(ckpt["global_step"]) if ckpt else 0)
    reason = died_reason(code, job.process.pid, step, point)
    log.error("job %s died: %s", job.label, reason)
    try:
        job.run_dir.mkdir(parents=True, exist_ok=True)
        write_status(job.run_dir, "failed", step, reason=reason, exit_code=exit_code_of(code))
    except OSError as exc:
        log.error("could not record the death of job %s: %s", job.label, exc)


#: What ``take`` returns when no job may start now, but one may once a running job has ended.
WAIT = "wait"


class JobPool:
    """Runs jobs through ``start(job)`` (which spawns its process), ``n_jobs`` at a time, taking the
    next one from ``take()`` as soon as a slot is free (None: no more jobs; :data:`WAIT`: none now,
    ask again when a job ended); ``ended(job)`` once each job is reaped; ``stopping()`` says when no
    further job may start."""

    def __init__(self, n_jobs: int, stopping: Callable[[], int | None]) -> None:
        self.n_jobs = n_jobs
        self.stopping = stopping
        self.running: list[Job] = []

    def pids(self) -> list[int]:
        return [j.process.pid for j in self.running if j.process is not None and j.process.pid]

    def run(
        self,
        take: Callable[[], Any],
        start: Callable[[Job], None],
        ended: Callable[[Job], None] = lambda job: None,
    ) -> None:
        more = True
        while more or self.running:
            signum = self.stopping()
            while more and len(self.running) < self.n_jobs and signum is None:
                job = take()
                if job is None or job == WAIT:
                    more = job is not None
                    break
                start(job)
                self.running.append(job)
            if signum is not None and more:
                more = False  # no further job starts (launch_jobs names the ones left)
            if not self.running:
                if more:  # WAIT with nothing running would wait for ever
                    raise RuntimeError("the job pool was told to wait with no job running")
                continue
            # a job's pipe only until its result came: a closed pipe is always ready (a busy loop)
            handles = [j.process.sentinel for j in self.running]
            handles += [j.conn for j in self.running if j.result is None]
            multiprocessing.connection.wait(handles, timeout=POLL_S)
            for job in list(self.running):
                if self._collect(job):
                    ended(job)

    def _collect(self, job: Job) -> bool:
        """Take the job's result if it sent one; once its process ended, reap it (True)."""
        if job.result is None:
            try:
                if job.conn.poll():
                    job.result = job.conn.recv_bytes()
            except (EOFError, OSError):
                pass
        if job.process.is_alive():
            return False
        job.process.join()
        if job.result is None:
            try:  # sent just before it ended
                if job.conn.poll():
                    job.result = job.conn.recv_bytes()
            except (EOFError, OSError):
                pass
        job.conn.close()
        self.running.remove(job)
        if job.result is None:
            record_died(job)
        return True


def launch_jobs(
    launcher: Any, job_overrides: Sequence[Sequence[str]], initial_job_idx: int
) -> list:
    """The joblib launcher's ``launch`` on :class:`JobPool`: every job's ``JobReturn`` (a dead
    job's is a completed one with no value, as a failed job's: its status.json says why)."""
    from hydra.core.utils import filter_overrides

    n_jobs = n_jobs_of(launcher.joblib.get("n_jobs"))
    log.info(
        "rlexp's job pool (n_jobs=%d, one process per job) is launching %d jobs",
        n_jobs,
        len(job_overrides),
    )
    pool = _Pool(launcher, n_jobs)
    jobs = []
    for i, overrides in enumerate(job_overrides):
        idx = initial_job_idx + i
        log.info("\t#%d : %s", idx, " ".join(filter_overrides(overrides)))
        jobs.append(Job(idx, overrides, _run_dir(launcher, overrides, idx)))
    waiting = list(jobs)
    stop = pool.run(lambda: waiting.pop(0) if waiting else None, lambda job: None)
    for job in jobs if stop.signum is not None else ():
        if job.process is None:
            log.warning("%s: the sweep is stopping; job %s not started", stop.name, job.label)
    returns = [pool.job_return(job) for job in jobs]
    if stop.signum is not None:
        exit_stopped(str(pool.sweep_dir), stop)
    return returns


def stream_jobs(
    launcher: Any,
    n_jobs: int,
    take: Callable[[], Any],
    done: Callable[[int, Any], None],
) -> None:
    """Jobs taken one at a time as a slot frees (an asynchronous Optuna sweep): ``take()`` gives
    (job number, overrides), None (no more) or :data:`WAIT`; ``done(job number, JobReturn)`` as
    each ends, in the sweep's main thread. A stop signal ends the sweep as :func:`launch_jobs`
    does, once the running jobs are back."""
    from hydra.core.utils import filter_overrides

    pool = _Pool(launcher, n_jobs)
    log.info("rlexp's job pool (n_jobs=%d, one process per job): asynchronous trials", n_jobs)

    def next_job() -> Any:
        item = take()
        if item is None or item == WAIT:
            return item
        idx, overrides = item
        log.info("\t#%d : %s", idx, " ".join(filter_overrides(overrides)))
        return Job(idx, overrides, _run_dir(launcher, overrides, idx))

    stop = pool.run(next_job, lambda job: done(job.idx, pool.job_return(job)))
    if stop.signum is not None:
        exit_stopped(str(pool.sweep_dir), stop)


class _Pool:
    """The launcher's jobs in spawned processes: how one starts, and its ``JobReturn``."""

    def __init__(self, launcher: Any, n_jobs: int) -> None:
        from hydra.core.singleton import Singleton
        from hydra.core.utils import setup_globals

        setup_globals()
        self.launcher, self.n_jobs = launcher, n_jobs
        self.sweep_dir = Path(str(launcher.config.hydra.sweep.dir))
        self.sweep_dir.mkdir(parents=True, exist_ok=True)
        log.info("Launching jobs, sweep output dir : %s", self.sweep_dir)
        self.singleton_state = Singleton.get_state()
        self.ctx = multiprocessing.get_context("spawn")
        self.parent = os.getpid()

    def start(self, job: Job) -> None:
        import cloudpickle
        from hydra_plugins.hydra_joblib_launcher._core import execute_job

        lc = self.launcher
        args = (job.idx, job.overrides, lc.hydra_context, lc.config, lc.task_function,
                self.singleton_state)  # fmt: skip
        payload = cloudpickle.dumps((execute_job, args))
        reader, writer = self.ctx.Pipe(duplex=False)
        job.process = self.ctx.Process(
            target=_job_main, args=(payload, writer, self.parent), daemon=False
        )
        job.process.start()
        writer.close()
        job.conn = reader

    def run(self, take: Callable[[], Any], ended: Callable[[Job], None]) -> Any:
        """:meth:`JobPool.run` under :class:`ParentStop`; returns the stop (``signum`` or None)."""
        from rlexp.launch.sweep_stop import ParentStop

        stop_holder: list[ParentStop] = []
        pool = JobPool(self.n_jobs, lambda: stop_holder[0].signum if stop_holder else None)
        with ParentStop(pool.pids) as stop:
            stop_holder.append(stop)
            pool.run(take, self.start, ended)
        return stop

    def job_return(self, job: Job) -> Any:
        """The job's ``JobReturn``; a dead or never started job's: completed with no value."""
        import cloudpickle
        from hydra.core.utils import JobReturn, JobStatus

        if job.result is not None:
            return cloudpickle.loads(job.result)
        ret = JobReturn(overrides=job.overrides, working_dir=str(job.run_dir or self.sweep_dir))
        ret.return_value, ret.status = None, JobStatus.COMPLETED  # died, or never started
        return ret


def _run_dir(launcher: Any, overrides: Sequence[str], idx: int) -> Path | None:
    """The run dir Hydra will give job ``idx`` (``hydra.sweep.dir`` / ``subdir``), None if it
    cannot be worked out here."""
    from omegaconf import OmegaConf, open_dict

    try:
        cfg = launcher.hydra_context.config_loader.load_sweep_config(
            launcher.config, list(overrides)
        )
        with open_dict(cfg):
            cfg.hydra.job.num = idx
            cfg.hydra.job.id = f"{cfg.hydra.job.name}_{idx}"
        sweep = OmegaConf.select(cfg, "hydra.sweep.dir")
        sub = OmegaConf.select(cfg, "hydra.sweep.subdir")
        return Path(os.path.abspath(os.path.join(str(sweep), str(sub))))
    except Exception:
        return None
