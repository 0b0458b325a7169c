"""``hydra/launcher=slurm``: hydra-submitit-launcher's SLURM launcher + rlexp's preemption requeue,
and a sweep that outlives a job whose process died."""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from hydra.core.singleton import Singleton
from hydra.core.utils import JobReturn, JobStatus, filter_overrides
from omegaconf import OmegaConf, open_dict

try:
    from hydra_plugins.hydra_submitit_launcher.config import BaseQueueConf
    from hydra_plugins.hydra_submitit_launcher.submitit_launcher import SlurmLauncher
except ImportError:  # no rlexp[slurm]: Hydra imports every plugin module at start and warns about
    # one that fails; hydra/launcher=slurm then fails to compose, naming the extra (rlexp.extras)
    BaseQueueConf, SlurmLauncher = None, object  # type: ignore[assignment,misc]

from rlexp.launch.slurm import RequeueOnPreemption

log = logging.getLogger(__name__)

#: How often an asynchronous sweep looks at its SLURM jobs (s).
POLL_S = 1.0


class RlexpSlurmLauncher(RequeueOnPreemption, SlurmLauncher):
    """Submits each sweep job as a SLURM array task; a job stopped by SLURM's signal requeues.

    A job that fails returns normally (``rlexp.app._task`` records why in its ``status.json``). A job
    whose process died without a result (out of memory, ``scancel``, the time limit after the last
    requeue, a lost node) would make submitit's ``results()`` raise and end the launcher before it
    collected the others: here it is logged in one line, recorded ``failed`` in its run dir, and
    returns None (what Optuna records as a failed trial), so the sweep goes on to its summary.
    """

    def launch(
        self, job_overrides: Sequence[Sequence[str]], initial_job_idx: int
    ) -> list[JobReturn]:
        """As ``BaseSubmititLauncher.launch`` (hydra-submitit-launcher 1.2), except the results."""
        if self.config is None or not job_overrides:
            raise RuntimeError("RlexpSlurmLauncher.launch needs setup() first and at least one job")
        executor = self._executor()
        job_params = [self._job_args(initial_job_idx + i, ov) for i, ov in enumerate(job_overrides)]
        jobs = executor.map_array(self, *zip(*job_params, strict=True))
        return self.collect(jobs, job_overrides, initial_job_idx)

    def launch_stream(
        self, n_jobs: int, take: Callable[[], Any], done: Callable[[int, JobReturn], None]
    ) -> None:
        """An asynchronous Optuna sweep's jobs (``rlexp.launch.optuna_async``): one SLURM job
        submitted per ``take()`` (job number, overrides) as soon as fewer than ``n_jobs`` are
        queued or running; ``done(job number, JobReturn)`` as each ends (polled every
        :data:`POLL_S` s). ``take()`` may say None (no more) or ``"wait"`` (none until one ends)."""
        if self.config is None:
            raise RuntimeError("RlexpSlurmLauncher.launch_stream needs setup() first")
        executor = self._executor()
        running: dict[int, tuple[Any, list[str]]] = {}
        more = True
        while more or running:
            while more and len(running) < n_jobs:
                item = take()
                if item is None or item == "wait":
                    more = item is not None
                    break
                idx, overrides = item
                running[idx] = (executor.submit(self, *self._job_args(idx, overrides)), overrides)
            ended = [idx for idx, (job, _) in running.items() if job.done()]
            if not ended:
                time.sleep(POLL_S)
            for idx in ended:
                job, overrides = running.pop(idx)
                done(idx, self.collect([job], [overrides], idx)[0])

    def _executor(self) -> Any:
        """submitit's executor with this launcher's parameters (as hydra-submitit-launcher)."""
        import submitit

        params = self.params
        init_params = {"folder": params["submitit_folder"]}
        specific_init_keys = {"max_num_timeout"}
        init_params.update(
            **{f"{self._EXECUTOR}_{x}": y for x, y in params.items() if x in specific_init_keys}
        )
        init_keys = specific_init_keys | {"submitit_folder"}
        executor = submitit.AutoExecutor(cluster=self._EXECUTOR, **init_params)
        baseparams = set(OmegaConf.structured(BaseQueueConf).keys())
        executor.update_parameters(
            **{
                x if x in baseparams else f"{self._EXECUTOR}_{x}": y
                for x, y in params.items()
                if x not in init_keys
            }
        )
        log.info("Submitit '%s' sweep output dir : %s", self._EXECUTOR, self.config.hydra.sweep.dir)
        sweep_dir = Path(str(self.config.hydra.sweep.dir))
        sweep_dir.mkdir(parents=True, exist_ok=True)
        if "mode" in self.config.hydra.sweep:
            os.chmod(sweep_dir, mode=int(str(self.config.hydra.sweep.mode), 8))
        return executor

    def _job_args(self, idx: int, overrides: Sequence[str]) -> tuple[Any, ...]:
        """What ``BaseSubmititLauncher.__call__`` takes for job ``idx`` (logged as Hydra does)."""
        log.info("\t#%d : %s", idx, " ".join(filter_overrides(overrides)))
        return (list(overrides), "hydra.sweep.dir", idx, f"job_id_for_{idx}", Singleton.get_state())

    def collect(
        self, jobs: Sequence[Any], job_overrides: Sequence[Sequence[str]], initial_job_idx: int
    ) -> list[JobReturn]:
        """Each submitit job's ``JobReturn``; a job that ended without one is logged and recorded
        (``record_lost_job``) and stands as a completed job that returned None."""
        returns = []
        for idx, (job, overrides) in enumerate(
            zip(jobs, job_overrides, strict=True), initial_job_idx
        ):
            try:
                returns.append(job.results()[0])
                continue
            except Exception as exc:  # submitit's UncompletedJobError / FailedJobError, and kin
                reason = f"SLURM job {job.job_id} ended without a result: {_gist(exc)}"
            where = getattr(getattr(job, "paths", None), "stderr", None)
            log.error("job #%d: %s; its output: %s", idx, reason, where)
            self.record_lost_job(idx, overrides, reason)
            ret = JobReturn(overrides=list(overrides), status=JobStatus.COMPLETED)
            ret.return_value = None
            returns.append(ret)
        return returns

    def record_lost_job(self, idx: int, overrides: Sequence[str], reason: str) -> None:
        """``status.json`` ``failed`` with ``reason`` in the job's run dir, where the job began one
        and left it ``running`` (or no status): a status the job wrote itself is kept."""
        from rlexp.run.rundir import read_status, write_status

        if self.hydra_context is None or self.config is None:
            return
        try:
            cfg = self.hydra_context.config_loader.load_sweep_config(self.config, list(overrides))
            with open_dict(cfg.hydra.job):
                cfg.hydra.job.num = idx
            run_dir = Path(str(cfg.hydra.sweep.dir)) / str(cfg.hydra.sweep.subdir)
        except Exception as exc:  # a subdir that needs what only the job knows (hydra.job.id)
            log.warning("job #%d: its run dir is not known here (%s)", idx, exc)
            return
        status = read_status(run_dir)
        if not run_dir.is_dir() or status.get("state") not in (None, "running"):
            return
        step = status.get("global_step")
        try:
            write_status(run_dir, "failed", step if isinstance(step, int) else 0, reason=reason)
        except OSError as exc:
            log.error("could not record the failure in %s: %s", run_dir, exc)


def _gist(exc: BaseException) -> str:
    """The first lines of submitit's message (it appends the job's whole error stream)."""
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip().strip("-")]
    text = " ".join(lines[:2]) or type(exc).__name__
    return text if len(text) <= 300 else text[:297] + "..."
