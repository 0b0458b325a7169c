"""Entry point: Hydra composes ``conf/``, ``train(config, run_dir)`` builds the objects and runs.

``main()`` is what ``python train.py`` and ``rlexp train`` call. The command line is checked first
(``rlexp.launch.precheck``): a bad override or a config that cannot be built prints one line and
exits 2 before Hydra creates a run dir. A run then locks its dir, builds everything, and only then
writes ``config.yaml``, provenance and logs. How each way of ending shows up (status, exit code):
docs/faults.md.
"""

from __future__ import annotations

import logging
import os
import sys
from functools import partial
from pathlib import Path
from typing import Any

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from rlexp.common import speedups as _speedups
from rlexp.config.paths import CONF_DIR, with_user_config_dir  # CONF_DIR: package's or checkout's
from rlexp.config.rules import first_line
from rlexp.config.schema import RootConfig, register_configs
from rlexp.config.validate import ConfigError, to_dict, to_root_config, total_frames
from rlexp.launch import job_log
from rlexp.plugins import load_plugins
from rlexp.run import end as run_end
from rlexp.run.next_steps import done_message
from rlexp.run.proof import check_continuation, finished_before_building, finished_result
from rlexp.run.rundir import (
    EXIT_CONFIG,
    EXIT_FAILED,
    EXIT_NONFINITE,
    EXIT_SIGNAL_BASE,
    HYDRA_JOB,
    RESUME_MAY_CHANGE,
    Heartbeat,
    RunDirLock,
    check_run_dir,
    clean_temp_files,
    config_differences,
    read_status,
    write_hydra_files,
    write_run_files,
    write_status,
)
from rlexp.runtime import entry, outside_run
from rlexp.runtime.job_dir import job_dir
from rlexp.runtime.signals import sweep_worker
from rlexp.runtime.user_code import user_code_exits
from rlexp.training.build import seed_everything

log = logging.getLogger(__name__)


class RunEnded(Exception):
    """The run stopped before finishing; ``exit_code`` is what ``python train.py`` exits with
    (``rlexp.run.rundir``: 1 failed, 3 non-finite values, 128 + N interrupted by signal N)."""

    def __init__(self, message: str, exit_code: int) -> None:
        super().__init__(message)
        self.exit_code = exit_code


def train(
    config: RootConfig, run_dir: Path, sweep_group: str | None = None, jobs: int = 1
) -> dict[str, float]:
    """Lock the run dir, build envs, policy, PPO, loggers and Trainer from ``config``, train, and
    return the last eval. Nothing is written into the run dir before the config has built.
    ``jobs``: the sweep's jobs running side by side on this machine (``trainer.eval_async=auto``)."""
    import torch

    from rlexp.runtime import distributed
    from rlexp.runtime.signals import stop_on_signals

    dist = distributed.info()
    distributed.set_timeout(config.trainer.stall_timeout_s)  # the longest wait for another rank
    _speedups.apply()
    _speedups.release_frozen()  # an earlier run in this process (a sweep's jobs, tests)
    torch.set_num_threads(config.trainer.torch_threads)
    lock = RunDirLock(run_dir)
    with _speedups.startup_gc(), stop_on_signals() as stops:
        try:
            if dist.is_main:
                lock.acquire()  # before anything is read or written: one run per dir
            _agree(failed=False)
            return _train_locked(config, run_dir, sweep_group, stops, jobs)
        except ConfigError:
            _agree(failed=True)
            raise
        finally:
            lock.release()
            distributed.shutdown()


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


def _train_locked(
    config: RootConfig, run_dir: Path, sweep_group: str | None, stops: Any, jobs: int
) -> dict[str, float]:
    import torch

    from rlexp.checkpoints.files import check_checkpoint_fits, latest_good_checkpoint
    from rlexp.launch.checks import check_resume_checkpoint
    from rlexp.launch.slurm import install_preemption_handler
    from rlexp.run.metrics import MetricLogger, make_logger
    from rlexp.run.provenance import versions
    from rlexp.runtime import distributed

    t = config.trainer
    dist = distributed.info()
    from rlexp.training.build import resolve_device

    # auto is decided by build() once the env exists (the env's GPU, or the CPU for a CPU env and
    # a small MLP: rlexp.runtime.devices.auto_device); a device named outright is resolved here
    device = t.device if t.device == "auto" else resolve_device(t.device, t.strict_device)
    if dist.enabled and device.startswith("cuda"):
        device = f"cuda:{dist.local_rank}"  # each rank on its own GPU
    seed_everything(config.seed + dist.rank)
    total = total_frames(config, dist.world_size)

    # -- the run dir: what it holds decides what this run does (nothing is written here yet) -------
    if t.resume == "auto":  # a re-run of a job that finished this config: its result, no training
        done = finished_result(
            run_dir, to_dict(config), total
        )  # rlexp.run.proof: proven or refused
        if done is not None:
            return done
    if dist.is_main:
        clean_temp_files(run_dir)
    t.device = device  # the saved config records the device actually used
    config_dict = to_dict(config)
    ckpt = None
    check_run_dir(run_dir, config_dict, t.resume)  # a continuation, or another run's dir?
    if t.resume == "auto":
        ckpt = latest_good_checkpoint(run_dir / "checkpoints", move_aside=dist.is_main)
        check_continuation(run_dir, config_dict, ckpt)  # its own checkpoint, or nothing trained
    job_log.release()  # the dir is this run's: its train.log is written from here (launch/job_log)

    # -- build: a failure here is a config error (one line, exit 2, no config.yaml) ---------------
    from rlexp.training.build import build

    try:
        with user_code_exits("the run's build"):
            objects = build(config, run_dir, device, total)
        if ckpt is not None:
            check_checkpoint_fits(ckpt, config, objects.policy)
        elif t.resume not in ("auto", "never", ""):
            ckpt = check_resume_checkpoint(config, objects.policy)
            diffs = config_differences(ckpt["config"], config_dict, ignore=RESUME_MAY_CHANGE)
            if diffs:
                log.warning("resuming %s with a different config (%s)", t.resume, ", ".join(diffs))
    except Exception as exc:
        if stops.requested:  # a Ctrl-C that broke the build (a worker it reached): a stop, 128+N
            raise RunEnded(f"interrupted ({stops.reason()}) while the run was built: nothing "
                           "trained", EXIT_SIGNAL_BASE + (stops.signum or 2)) from None  # fmt: skip
        if isinstance(exc, ConfigError):
            raise
        raise ConfigError(f"the run cannot be built from this config: {first_line(exc)}") from None
    if objects.device != device:  # auto, decided from the env: the saved config records it
        device = t.device = objects.device
        config_dict = to_dict(config)

    # -- from here on the run dir is written -------------------------------------------------------
    if dist.is_main:
        write_run_files(config, config_dict, run_dir, device)
    log.info(
        "run dir: %s (device %s, seed %d, torch threads %d)",
        run_dir,
        device,
        config.seed,
        torch.get_num_threads(),  # what the update runs with, read back from torch
    )
    if dist.is_main:
        logger = make_logger(config.logger, run_dir, t.exp_name, config_dict, group=sweep_group)
    else:
        logger = MetricLogger([])
    trainer = objects.trainer(logger, config_dict, versions(), _eval_async(config, total, jobs))
    if ckpt is not None:
        _load(trainer, ckpt, run_dir)
    stops.attach(trainer)  # SIGINT / SIGTERM / SIGHUP: checkpoint at the end of the iteration
    install_preemption_handler(trainer)  # under SLURM: the preemption signal checkpoints, requeues
    return _run(trainer, run_dir, total, stops, ckpt)


def _load(trainer: Any, ckpt: dict, run_dir: Path) -> None:
    """Continue from ``ckpt``; the env's ``set_state`` raising is one line, exit 2, and
    ``status.json`` says ``failed`` with it (it must not keep saying the run finished)."""
    from rlexp.training.loop import EnvRestoreError

    try:
        trainer.load_state_dict(ckpt)
    except EnvRestoreError as exc:
        trainer.close()
        write_status(run_dir, "failed", int(ckpt["global_step"]), reason=str(exc), exit_code=2)
        raise ConfigError(str(exc)) from None


def _run(
    trainer: Any, run_dir: Path, total: int, stops: Any, ckpt: dict | None
) -> dict[str, float]:
    """Train; every way out leaves ``status.json`` saying how the run ended and why."""
    from rlexp.algorithms.ppo import NonFiniteError
    from rlexp.launch.slurm import stop_requested_by_signal
    from rlexp.run import stalls
    from rlexp.run.writable import check_checkpoints_writable
    from rlexp.training.trainer import StopRequested

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
        if stops.requested and trainer.global_step == 0:
            raise StopRequested(stops.reason())  # a signal during the build: nothing to save yet
        check_checkpoints_writable(trainer.ckpt_dir, trainer.cfg.exp_name)  # not at the 1st save
        _speedups.training_gc()  # the GC walks only what training creates from here on
        with user_code_exits("the training loop"):  # sys.exit() in an env: failed (user_code.py)
            trainer.train(total)
            if trainer.eval_env is not None and not trainer.last_eval:
                trainer.eval_once()
        if trainer.stopped_early is not None:  # a hook ended it: a result, not a failure (exit 0)
            status(
                "stopped_early",
                trainer.global_step,
                trainer.last_eval,
                reason=trainer.stopped_early,
            )
        else:
            status("finished", trainer.global_step, trainer.last_eval)
    except StopRequested as exc:
        step = trainer.global_step
        if stop_requested_by_signal():  # SLURM preemption: the launcher requeues the job
            log.warning(
                "stopped at step %d (%s): checkpoint %s", step, exc, trainer.last_checkpoint
            )
            status("stopped", step, trainer.last_eval, reason=str(exc))
            raise
        log.warning("interrupted at step %d (%s): %s", step, exc, last_good())
        status("interrupted", step, trainer.last_eval, reason=str(exc))
        raise RunEnded(f"interrupted ({exc})", EXIT_SIGNAL_BASE + (stops.signum or 2)) from None
    except (
        KeyboardInterrupt
    ):  # a second Ctrl-C: no checkpoint mid-iteration (it would not be exact)
        step = trainer.global_step
        reason = f"interrupted twice at step {step}: stopped without a checkpoint; {last_good()}"
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
        reason = f"{type(exc).__name__}: {first_line(exc)} (traceback in {trace}); {last_good()}"
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


def _eval_async(config: RootConfig, total: int, jobs: int) -> bool:
    """``trainer.eval_async`` as a bool (``auto`` decided here, once, and logged with why)."""
    from rlexp.config.rules import available_cpus
    from rlexp.runtime import distributed
    from rlexp.training.eval_worker import decide_eval_async

    dist = distributed.info()
    if not dist.is_main:  # rank 0 alone evaluates
        return False
    on, why = decide_eval_async(config, total, available_cpus(), jobs, dist.world_size)
    choice = str(config.trainer.eval_async).lower()
    log.info("[eval] trainer.eval_async=%s -> %s: %s", choice, "on" if on else "off", why)
    return on


#: Set by ``main`` once the command line passed ``precheck`` (a single run): the job need not build
#: the config a second time.
_PRECHECKED: dict[str, Any] = {}


def _task(cfg: DictConfig) -> float | None:
    """Hydra's task function: typed config in, final eval return out (for sweepers).

    A single run exits with the code of how it ended (docs/faults.md). In a sweep, a job that fails
    records the reason in its own dir and returns None (Optuna records a failed trial; NaN would
    crash its sweeper), so the launcher goes on with the other jobs; the sweep's end
    (``rlexp.launch.sweep``) reports the failed ones and sets the exit code.
    """
    hc = HydraConfig.get()
    HYDRA_JOB.update(cfg=cfg, hydra=hc)
    multirun = hc.mode is not None and hc.mode.name == "MULTIRUN"
    run_dir = Path(job_dir())  # not hc.runtime.output_dir: a dir named "${...}" breaks it
    sweep_group = Path(hc.sweep.dir).name if multirun else None
    outside_run.job_started(f"job {run_dir}")  # a Ctrl-C after the previous job: the sweep stops
    worker = sweep_worker()  # a joblib worker of a local sweep (rlexp.launch.sweep_stop)
    if worker is not None and worker.signum is not None:
        log.warning("%s: the sweep is stopping; job %s not started", worker.name, run_dir)
        return None
    try:
        load_plugins()  # a sweep worker or a SLURM job is a fresh process
        config = to_root_config(cfg)
        if (done := finished_before_building(config, run_dir)) is not None:
            return done.get("eval/episode_return")  # a re-run sweep's finished job, before torch
        if not _PRECHECKED.get("config"):
            from rlexp.launch.checks import check_buildable

            check_buildable(config)
        if os.environ.get("RLEXP_DISTRIBUTED") == "1":
            _join_distributed()
        jobs = 1  # the joblib launcher runs n_jobs of a sweep's jobs at once on this machine
        if multirun:
            from rlexp.config.rules import available_cpus
            from rlexp.training.eval_worker import launcher_jobs

            jobs = launcher_jobs(hc.launcher.get("n_jobs"), available_cpus())
        metrics: dict[str, Any] = train(config, run_dir, sweep_group, jobs)
    except ConfigError as exc:
        outside_run.reraise_if_interrupted(exc)
        return _failed(run_dir, f"config error: {exc}", EXIT_CONFIG, multirun, exc)
    except RunEnded as exc:
        if exc.exit_code >= EXIT_SIGNAL_BASE:  # a signal: stop the whole sweep too
            log.error("%s", exc)
            if worker is not None:
                return None  # the sweep's process exits 128+N once every job is back
            _exit(exc.exit_code)
        return _failed(run_dir, str(exc), exc.exit_code, multirun, exc)
    except KeyboardInterrupt:  # Ctrl-C twice while the run was being built: nothing to save
        log.error("interrupted before training started")
        if worker is not None:
            return None
        sys.exit(EXIT_SIGNAL_BASE + 2)
    except OSError as exc:  # the run dir before training (training's own end: RunEnded, exit 1)
        return _failed(run_dir, entry.run_dir_error(run_dir, exc), EXIT_CONFIG, multirun, exc)
    except Exception as exc:
        from rlexp.training.trainer import StopRequested

        if not multirun or isinstance(exc, StopRequested):
            raise  # StopRequested: SLURM preemption, the launcher requeues the job (launch/slurm.py)
        log.exception("job failed")  # the traceback goes to the job's log; the sweep goes on
        return _failed(run_dir, f"{type(exc).__name__}: {first_line(exc)}", EXIT_FAILED, True, exc)
    return metrics.get("eval/episode_return")


def _join_distributed() -> None:
    from rlexp.runtime import distributed

    if not distributed.info().enabled:
        try:
            distributed.init_in_job()
        except RuntimeError as exc:
            raise ConfigError(str(exc)) from None


def _exit(code: int) -> None:
    """``sys.exit(code)``; a distributed rank leaves with ``os._exit`` once its logs are flushed:
    its gloo threads can abort the interpreter's teardown ("terminate called without an active
    exception", exit -6 instead of the code), seen on a loaded 2-core machine after a failure and
    after a finished run alike."""
    from rlexp.runtime import distributed

    if not distributed.info().enabled:
        sys.exit(code)
    logging.shutdown()  # flush and close every handler (console, the job's log file)
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


def _failed(run_dir: Path, message: str, code: int, multirun: bool, exc: Exception) -> None:
    """One line; a single run exits with ``code``, a sweep job records it and returns None."""
    from rlexp.run.rundir import RunDirBusy

    job_log.drop()  # stopped before the run owned the dir: its train.log stays as it was
    log.error("%s", message)
    if not multirun:
        _exit(code)
    state = read_status(run_dir).get("state")
    if not isinstance(exc, RunDirBusy) and state in (None, "failed"):  # never another run's status
        try:
            write_hydra_files(run_dir)  # the job's overrides, for rlexp report
            write_status(run_dir, "failed", 0, reason=message, exit_code=code)
        except OSError as err:
            log.error("could not record the failure in %s: %s", run_dir, err)
    return None


def main() -> None:
    """``python train.py [--distributed] [overrides]``: check the command line, then compose
    ``conf/`` with Hydra and train."""
    from rlexp.extras import hint
    from rlexp.launch.precheck import precheck
    from rlexp.runtime import distributed

    register_configs()
    os.environ.setdefault("MUJOCO_GL", "egl")
    wanted, rest = distributed.split_flag(sys.argv[1:])
    multirun = any(a in ("-m", "--multirun") for a in rest)
    outside_run.install(multirun)  # Ctrl-C before training: one line; after its end: no change
    if wanted and multirun:
        # A sweep: the launcher's jobs start the ranks (SLURM tasks_per_node); each job joins its group.
        os.environ["RLEXP_DISTRIBUTED"] = "1"
    elif wanted:
        try:
            rest = distributed.init(rest)
        except RuntimeError as exc:
            print(f"error: {exc}", file=sys.stderr)
            sys.exit(EXIT_CONFIG)
    try:
        load_plugins()
        rest = with_user_config_dir(rest)  # a conf/ in the working directory
        _PRECHECKED["config"] = precheck(rest, CONF_DIR)
    except ConfigError as exc:
        outside_run.reraise_if_interrupted(exc)  # a Ctrl-C inside a library: exit 130
        print(f"config error: {hint(str(exc))}", file=sys.stderr)
        sys.exit(EXIT_CONFIG)
    sys.argv = [sys.argv[0], *rest]
    if multirun:
        _speedups.sweep_gc()
    os.environ.setdefault("HYDRA_FULL_ERROR", "1")  # its errors reach rlexp.runtime.entry's guard
    hydra.main(config_path=str(CONF_DIR), config_name="config", version_base="1.3")(_task)()
    if not multirun:
        _prompt_exit()


def _prompt_exit() -> None:
    """A single run that finished has written everything (checkpoint, status, closed loggers): run
    the atexit handlers (W&B, TensorBoard and logging flush theirs there), then leave without the
    interpreter's teardown of torch, TorchRL and MuJoCo modules: ~1 s of destructors the user waits
    for and that write nothing, and where a torchrun rank's gloo threads can abort (see _exit)."""
    import atexit

    atexit._run_exitfuncs()
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)
