"""SLURM preemption: checkpoint at a safe point on SLURM's warning signal, then requeue via submitit.

The flow (docs/sweeps.md, "Preemption and requeue"):

1. submitit starts the job and installs its own handler for the preemption signal (``USR2``, or
   ``$SUBMITIT_PREEMPT_SIGNAL``), which would checkpoint the *callable* and requeue at once, killing
   the training loop wherever it is.
2. ``app.train`` builds the ``Trainer`` and calls :func:`install_preemption_handler`, which replaces
   that handler (remembering it) with one that only calls ``trainer.request_stop(...)``.
3. At the end of the current iteration the trainer saves a checkpoint and raises ``StopRequested``;
   ``app.train`` writes ``status.json`` state ``stopped`` and re-raises; Hydra's ``run_job`` turns it
   into a failed ``JobReturn``.
4. The launcher (:class:`RequeueOnPreemption`, ``hydra/launcher=slurm``) sees that failed return, and since a stop was
   requested by the signal, runs submitit's remembered handler: it re-dumps the job pickle, counts a
   timeout against ``max_num_timeout`` if the time limit was near, calls ``scontrol requeue`` and
   exits.
5. The requeued attempt loads the same pickle, so Hydra rebuilds the same job config (the sweep dir's
   ``${now:...}`` values come from the pickled config's resolver cache) and the same run dir;
   ``trainer.resume=auto`` continues from the newest checkpoint, the W&B run id is read back from
   ``wandb_run_id.txt``, and the run ends at ``trainer.total_frames``.
"""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import threading
from dataclasses import dataclass
from typing import Any

from hydra.core.utils import JobReturn, JobStatus

log = logging.getLogger(__name__)


@dataclass
class _Preemption:
    """What the signal handler saw; read by the launcher once the task function has returned."""

    signum: int | None = None
    previous: Any = None  # the handler we replaced (submitit's checkpoint_and_try_requeue)
    requested: bool = False


_state = _Preemption()


def in_slurm() -> bool:
    """True inside a SLURM allocation (batch job or ``srun`` step)."""
    return bool(os.environ.get("SLURM_JOB_ID"))


def preemption_signal() -> signal.Signals:
    """The signal submitit listens for (``USR2`` unless ``SUBMITIT_PREEMPT_SIGNAL`` says otherwise)."""
    name = os.environ.get("SUBMITIT_PREEMPT_SIGNAL", "USR2").upper()
    sig = getattr(signal, name if name.startswith("SIG") else f"SIG{name}", None)
    if not isinstance(sig, signal.Signals):
        raise ValueError(f"SUBMITIT_PREEMPT_SIGNAL={name!r} is not a signal name; use e.g. USR2")
    return sig


def install_preemption_handler(trainer: Any) -> bool:
    """Under SLURM, make the preemption signal ask ``trainer`` to checkpoint and stop at a safe point.

    Returns True when a handler was installed. Outside SLURM (no ``SLURM_JOB_ID``) or off the main
    thread (where Python can't install signal handlers) it does nothing.
    """
    if not in_slurm():
        return False
    if threading.current_thread() is not threading.main_thread():
        log.warning(
            "SLURM job off the main thread: no preemption handler (submitit requeues at once; the next attempt resumes)"
        )
        return False
    sig = preemption_signal()
    _state.signum, _state.requested = int(sig), False
    current = signal.getsignal(sig)
    if not getattr(current, "_rlexp_preemption", False):  # a later run in the same process keeps
        _state.previous = current  # the original (submitit's) handler, not the last run's
    job = os.environ.get("SLURM_JOB_ID")

    def _on_signal(signum: int, frame: Any) -> None:
        # Signal context: only set flags. The loop checkpoints at the end of the current iteration.
        _state.requested = True
        trainer.request_stop(f"SLURM signal {signal.Signals(signum).name} (job {job})")

    _on_signal._rlexp_preemption = True  # type: ignore[attr-defined]
    signal.signal(sig, _on_signal)
    log.info(
        "SLURM job %s (restart %s): %s checkpoints and stops at the next safe point, then requeues",
        job,
        os.environ.get("SLURM_RESTART_COUNT", "0"),
        sig.name,
    )
    return True


def stop_requested_by_signal() -> bool:
    """True once the preemption signal arrived in this process."""
    return _state.requested


def requeue() -> None:
    """Requeue this job after the trainer checkpointed; does not return when the job was requeued.

    Under submitit, runs submitit's own handler (re-dump the job, apply ``max_num_timeout``,
    ``scontrol requeue``, exit). Without submitit (a plain ``sbatch`` script), runs
    ``scontrol requeue $SLURM_JOB_ID`` and exits.
    """
    previous, signum = _state.previous, _state.signum or int(preemption_signal())
    owner = getattr(previous, "__self__", None)
    if callable(previous) and type(owner).__module__.startswith("submitit"):
        log.info("requeueing through submitit")
        previous(signum, None)  # raises SystemExit after requeueing, or UncompletedJobError
        return
    job = os.environ["SLURM_JOB_ID"]  # an array task's own job id: requeues just that task
    log.info("requeueing SLURM job %s", job)
    subprocess.run(["scontrol", "requeue", job], check=True, timeout=60)
    sys.exit(-1)


class RequeueOnPreemption:
    """Launcher mixin: a job that stopped because of the preemption signal requeues once it returned.

    Combined with hydra-submitit-launcher's ``SlurmLauncher`` in
    ``hydra_plugins.rlexp_launcher.RlexpSlurmLauncher`` (Hydra only loads launchers from the
    ``hydra_plugins`` package); selected by ``hydra/launcher=slurm``.
    """

    def __call__(self, *args: Any, **kwargs: Any) -> JobReturn:
        ret = super().__call__(*args, **kwargs)  # type: ignore[misc]
        from rlexp.training.trainer import StopRequested

        if (
            stop_requested_by_signal()
            and ret.status == JobStatus.FAILED
            and isinstance(ret._return_value, StopRequested)
        ):
            requeue()
        return ret
