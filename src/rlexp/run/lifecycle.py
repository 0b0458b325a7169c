"""One owner for a run's life in its dir: claim it (stop signals, the lock, the ranks agree), then
``status.json`` -> heartbeat -> stall watchdog -> train -> how the run ended -> its exit code, close.

``app.train`` reads as: claim the dir (``RunLifecycle.claim``), build, run (``RunLifecycle.run``).
Every way a run ends leaves ``status.json`` saying how and why, and raises :class:`RunEnded` with
the exit code docs/faults.md documents (1 failed, 3 non-finite values, 128 + N interrupted by signal
N); a finished run returns its last eval. A sweep's job that fails before its run owns a status
records it with :func:`record_job_failure`.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from functools import partial
from pathlib import Path
from typing import Any

from rlexp.common import speedups as _speedups
from rlexp.config.rules import first_line
from rlexp.config.validate import ConfigError
from rlexp.run import end as run_end
from rlexp.run.next_steps import done_message
from rlexp.run.rundir import (
    EXIT_FAILED,
    EXIT_NONFINITE,
    EXIT_SIGNAL_BASE,
    Heartbeat,
    RunDirLock,
    read_status,
    write_hydra_files,
    write_status,
)
from rlexp.runtime import outside_run
from rlexp.runtime.user_code import user_code_exits

log = logging.getLogger(__name__)


class RunEnded(Exception):
    """The run stopped before finishing; ``exit_code`` is what ``python train.py`` exits with
    (``rlexp.run.rundir``: 1 failed, 3 non-finite values, 128 + N interrupted by signal N)."""

    def __init__(self, message: str, exit_code: int) -> None:
        super().__init__(message)
        self.exit_code = exit_code


class RunLifecycle:
    """A run's life in ``run_dir``: lock -> status -> heartbeat -> how it ended -> exit code.

    ``preempted``: whether the stop was the scheduler's preemption signal (SLURM; the launcher
    requeues the job, so the run is ``stopped``, not ``interrupted``)."""

    def __init__(self, run_dir: Path, preempted: Callable[[], bool] = lambda: False) -> None:
        self.run_dir = run_dir
        self.preempted = preempted
        self.lock = RunDirLock(run_dir)
        self.stops: Any = None  # the stop-signal handlers, while the dir is claimed

    @contextmanager
    def claim(self) -> Iterator[RunLifecycle]:
        """Stop signals handled, the dir locked before anything is read or written (one run per
        dir), the ranks agreed that none failed first; the lock released and the process group
        shut down at the end, however it ends."""
        from rlexp.runtime import distributed
        from rlexp.runtime.signals import stop_on_signals

        dist = distributed.info()
        with stop_on_signals() as stops:
            self.stops = stops
            try:
                if dist.is_main:
                    self.lock.acquire()  # before anything is read or written: one run per dir
                _agree(failed=False)
                yield self
            except ConfigError:
                _agree(failed=True)
                raise
            finally:
                self.lock.release()
                distributed.shutdown()

    def restore(self, trainer: Any, ckpt: dict) -> None:
        """Continue from ``ckpt``; the env's ``set_state`` raising is one line, exit 2, and
        ``status.json`` says ``failed`` with it (it must not keep saying the run finished)."""
        from rlexp.algorithms.replay_files import ReplayFileError
        from rlexp.training.loop import EnvRestoreError

        try:
            trainer.load_state_dict(ckpt)
        except (EnvRestoreError, ReplayFileError) as exc:
            trainer.close()
            step, reason = int(ckpt["global_step"]), str(exc)
            if isinstance(exc, ReplayFileError):  # a chunk found but corrupt (docs/replay.md)
                reason += f"; to resume from an older checkpoint, move {ckpt['path']} aside"
            write_status(self.run_dir, "failed", step, reason=reason, exit_code=2)
            raise ConfigError(reason) from None

    def run(self, trainer: Any, total: int, ckpt: dict | None) -> dict[str, float]:
        """Train; every way out leaves ``status.json`` saying how the run ended and why."""
        from rlexp.algorithms.ppo import NonFiniteError
        from rlexp.run import stalls
        from rlexp.run.writable import check_checkpoints_writable
        from rlexp.training.trainer import StopRequested

        run_dir, stops = self.run_dir, self.stops

        def last_good() -> str:
            path = trainer.last_checkpoint or (ckpt and ckpt["path"])
            return f"the last good checkpoint is {path}" if path else "no checkpoint was written"

        status = partial(write_status, run_dir, env_resume=trainer.env_resume)  # docs/envs.md
        status("running", trainer.global_step)
        # heartbeat.json while it trains: how `rlexp runs` tells a killed run from a live one
        t = trainer.cfg
        beat = (Heartbeat(run_dir, partial(stalls.progress, trainer, total),
                          stall_timeout_s=t.stall_timeout_s) if trainer.dist.is_main else None)  # fmt: skip
        # A loop stuck in user code never reaches its safe point: a signal still ends the process.
        watchdog = stalls.StopWatchdog(trainer, run_dir, ckpt and ckpt["path"], t.stop_grace_s)
        stops.watchers.append(watchdog.arm)
        try:
            if beat is not None:
                beat.start()
            if stops.requested and trainer.global_step == 0:  # a signal during the build
                raise StopRequested(stops.reason())  # nothing to save yet
            check_checkpoints_writable(trainer.ckpt_dir, t.exp_name)  # not at the 1st save
            _speedups.training_gc()  # the GC walks only what training creates from here on
            with user_code_exits("the training loop"):  # sys.exit() in an env: failed
                trainer.train(total)
                if trainer.eval_env is not None and not trainer.last_eval:
                    trainer.eval_once()
            if trainer.stopped_early is not None:  # a hook ended it: a result, exit 0
                reason = trainer.stopped_early  # stopped_early, or pruned (an Optuna pruner's)
                how = trainer.hooks.stop_status
                status(how, trainer.global_step, trainer.last_eval, reason=reason)
            else:
                status("finished", trainer.global_step, trainer.last_eval)
        except StopRequested as exc:
            step = trainer.global_step
            if self.preempted():  # SLURM preemption: the launcher requeues the job
                log.warning(
                    "stopped at step %d (%s): checkpoint %s", step, exc, trainer.last_checkpoint
                )
                status("stopped", step, trainer.last_eval, reason=str(exc))
                raise
            log.warning("interrupted at step %d (%s): %s", step, exc, last_good())
            status("interrupted", step, trainer.last_eval, reason=str(exc))
            raise RunEnded(f"interrupted ({exc})", EXIT_SIGNAL_BASE + (stops.signum or 2)) from None
        except KeyboardInterrupt:  # a second Ctrl-C: no checkpoint mid-iteration (not exact)
            step = trainer.global_step
            reason = f"interrupted twice at step {step}: stopped without a checkpoint; "
            reason += last_good()
            log.warning("%s", reason)
            status("interrupted", step, trainer.last_eval, reason=reason)
            raise RunEnded(reason, EXIT_SIGNAL_BASE + 2) from None
        except NonFiniteError as exc:
            reason = f"{exc}; {last_good()}"
            status("failed", trainer.global_step, trainer.last_eval, reason=reason)
            raise RunEnded(f"stopped: {reason}", EXIT_NONFINITE) from None
        except OSError as exc:  # an unwritable checkpoints/, a full disk
            where = f" ({exc.filename})" if exc.filename else ""
            reason = f"{exc.strerror or exc}{where}; {last_good()}"
            run_end.try_write_status(run_dir, trainer, reason)
            raise RunEnded(f"failed at step {trainer.global_step}: {reason}", EXIT_FAILED) from None
        except Exception as exc:  # a bug or a library failure mid-run: keep what can be kept
            saved = run_end.save_at_safe_point(trainer)
            trace = run_end.write_traceback(run_dir)
            reason = f"{type(exc).__name__}: {first_line(exc)} (traceback in {trace}); "
            reason += last_good()
            if saved:
                reason += " (written at the end of the last complete update)"
            run_end.try_write_status(run_dir, trainer, reason)
            raise RunEnded(f"failed at step {trainer.global_step}: {reason}", EXIT_FAILED) from None
        finally:
            watchdog.ended = True  # status.json says how it ended: past the grace, only exit
            outside_run.run_ended()  # a stop signal from here on changes neither exit nor status
            if beat is not None:
                beat.stop()
            trainer.close()
            watchdog.disarm()
        if trainer.dist.is_main:
            log.info("%s", done_message(trainer, run_dir))
        return trainer.last_eval


def record_job_failure(run_dir: Path, message: str, code: int, exc: Exception) -> None:
    """A sweep's job that failed before its run owned a status (a config error, a busy dir): the
    failure in its dir for ``rlexp report``, never over another run's status."""
    from rlexp.run.rundir import RunDirBusy

    state = read_status(run_dir).get("state")
    if not isinstance(exc, RunDirBusy) and state in (None, "failed"):  # never another run's status
        try:
            write_hydra_files(run_dir)  # the job's overrides, for rlexp report
            write_status(run_dir, "failed", 0, reason=message, exit_code=code)
        except OSError as err:
            log.error("could not record the failure in %s: %s", run_dir, err)


_AGREED: dict[int, bool] = {}


def _agree(failed: bool) -> None:
    """Distributed, once: a rank that failed before training tells the others, so that no rank
    waits in a collective for one that has exited."""
    from rlexp.runtime import distributed

    dist = distributed.info()
    if not dist.enabled or _AGREED.get(id(dist)):
        return
    import torch

    _AGREED[id(dist)] = True
    device = (
        f"cuda:{dist.local_rank}" if dist.backend == "nccl" else "cpu"
    )  # nccl: GPU tensors only
    flag = torch.tensor([float(failed)], device=device)
    if distributed.all_reduce_sum(flag).item() > 0 and not failed:
        raise ConfigError("another rank failed before training (see rank 0's log)")
