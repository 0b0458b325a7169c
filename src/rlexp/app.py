"""Entry point: Hydra composes ``conf/``, ``train(config, run_dir)`` builds the objects and runs.

``main()`` is what ``python train.py`` and ``rlexp train`` call. The command line is checked first
(``rlexp.launch.precheck``): a bad override or a config that cannot be built prints one line and
exits 2 before Hydra creates a run dir. A run then claims its dir (``rlexp.run.lifecycle``: lock, status,
heartbeat, how it ended and its exit code), builds everything, and only then writes ``config.yaml``,
provenance and logs. How each way of ending shows up (status, exit code):
docs/faults.md.
"""

from __future__ import annotations

import logging
import os
import sys
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
from rlexp.run.lifecycle import RunEnded, RunLifecycle, record_job_failure
from rlexp.run.proof import finished_before_building
from rlexp.run.rundir import (
    EXIT_CONFIG,
    EXIT_FAILED,
    EXIT_SIGNAL_BASE,
    HYDRA_JOB,
    RESUME_MAY_CHANGE,
    check_run_dir,
    clean_temp_files,
    config_differences,
    write_run_files,
)
from rlexp.runtime import entry, outside_run
from rlexp.runtime.job_dir import job_dir
from rlexp.runtime.signals import sweep_worker
from rlexp.runtime.user_code import user_code_exits
from rlexp.training.build import seed_everything

log = logging.getLogger(__name__)


def train(
    config: RootConfig, run_dir: Path, sweep_group: str | None = None, jobs: int = 1
) -> dict[str, float]:
    """Claim the run dir, build envs, policy, algorithm, loggers and Trainer from ``config``, run,
    close; return the last eval. Nothing is written into the run dir before the config has built.
    ``jobs``: the sweep's jobs running side by side on this machine (``trainer.eval_async=auto``)."""
    import torch

    from rlexp.launch.slurm import stop_requested_by_signal
    from rlexp.runtime import distributed

    distributed.set_timeout(config.trainer.stall_timeout_s)  # the longest wait for another rank
    _speedups.apply()
    _speedups.release_frozen()  # an earlier run in this process (a sweep's jobs, tests)
    torch.set_num_threads(_torch_threads(config, jobs))
    run = RunLifecycle(run_dir, preempted=stop_requested_by_signal)
    with _speedups.startup_gc(), run.claim():  # stop signals, the lock, the ranks agree
        device, total, done = _prepare(config, run_dir)
        if done is not None:  # resume=auto on a run that finished this config: its result
            return done
        trainer, ckpt = _build(config, run, device, total, sweep_group, jobs)
        return run.run(trainer, total, ckpt)  # status, heartbeat, train, how it ended, close


def _prepare(config: RootConfig, run_dir: Path) -> tuple[str, int, dict[str, float] | None]:
    """The device, the seed and the frame budget; a re-run of a job that finished this config
    (``trainer.resume=auto``) gets its result instead of training again."""
    from rlexp.run.proof import finished_result
    from rlexp.runtime import distributed
    from rlexp.training.build import resolve_device

    t = config.trainer
    dist = distributed.info()
    # auto is decided by build() once the env exists (the env's GPU, or the CPU for a CPU env and
    # a small MLP: rlexp.runtime.devices.auto_device); a device named outright is resolved here
    device = t.device if t.device == "auto" else resolve_device(t.device, t.strict_device)
    if dist.enabled and device.startswith("cuda"):
        device = f"cuda:{dist.local_rank}"  # each rank on its own GPU
    seed_everything(config.seed + dist.rank)
    total = total_frames(config, dist.world_size)
    done = None
    if t.resume == "auto":  # rlexp.run.proof: proven or refused
        done = finished_result(run_dir, to_dict(config), total)
    return device, total, done


def _build(
    config: RootConfig,
    run: RunLifecycle,
    device: str,
    total: int,
    sweep_group: str | None,
    jobs: int,
) -> tuple[Any, dict | None]:
    """The run dir read (what it holds decides what this run does), the objects built, then the
    run dir written: the Trainer, and the checkpoint it continues from."""
    import torch

    from rlexp.checkpoints.files import check_checkpoint_fits, latest_good_checkpoint
    from rlexp.launch.checks import check_resume_checkpoint
    from rlexp.launch.slurm import install_preemption_handler
    from rlexp.run.metrics import MetricLogger, make_logger
    from rlexp.run.proof import check_continuation
    from rlexp.run.provenance import versions
    from rlexp.runtime import distributed

    t = config.trainer
    run_dir = run.run_dir
    dist = distributed.info()
    # -- the run dir: what it holds decides what this run does (nothing is written here yet) -------
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
        if (
            run.stops.requested
        ):  # a Ctrl-C that broke the build (a worker it reached): a stop, 128+N
            raise RunEnded(f"interrupted ({run.stops.reason()}) while the run was built: nothing "
                           "trained", EXIT_SIGNAL_BASE + (run.stops.signum or 2)) from None  # fmt: skip
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
        run.restore(trainer, ckpt)  # the env's set_state raising: failed, exit 2
    run.stops.attach(trainer)  # SIGINT / SIGTERM / SIGHUP: checkpoint at the end of the iteration
    install_preemption_handler(trainer)  # under SLURM: the preemption signal checkpoints, requeues
    return trainer, ckpt


def _torch_threads(config: RootConfig, jobs: int) -> int:
    """``trainer.torch_threads`` as a count (``auto``: this process's CPUs over the sweep's jobs
    side by side and the ranks on this node), logged when ``auto`` chose it."""
    from rlexp.config.rules import available_cpus, torch_threads_for

    value = config.trainer.torch_threads
    ranks = int(os.environ.get("LOCAL_WORLD_SIZE", "1") or 1)  # torchrun's ranks on this node
    threads = torch_threads_for(value, available_cpus(), jobs * max(1, ranks))
    if value == "auto":
        log.info("[threads] trainer.torch_threads=auto -> %d (%d CPUs, %d job(s) x %d rank(s))",
                 threads, available_cpus(), jobs, max(1, ranks))  # fmt: skip
    return threads


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
        return _interrupted_before_training(worker)
    except Exception as exc:
        if entry.interrupted(exc):  # a Ctrl-C inside MuJoCo's C-extension import (ImportError)
            return _interrupted_before_training(worker)
        if isinstance(exc, OSError):  # the run dir before training (its own end: RunEnded, exit 1)
            return _failed(run_dir, entry.run_dir_error(run_dir, exc), EXIT_CONFIG, multirun, exc)
        from rlexp.training.trainer import StopRequested

        if not multirun or isinstance(exc, StopRequested):
            raise  # StopRequested: SLURM preemption, the launcher requeues the job (launch/slurm.py)
        log.exception("job failed")  # the traceback goes to the job's log; the sweep goes on
        return _failed(run_dir, f"{type(exc).__name__}: {first_line(exc)}", EXIT_FAILED, True, exc)
    return metrics.get("eval/episode_return")


def _interrupted_before_training(worker: Any) -> None:
    log.error("interrupted before training started")
    if worker is not None:
        return None
    sys.exit(EXIT_SIGNAL_BASE + 2)


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
    job_log.drop()  # stopped before the run owned the dir: its train.log stays as it was
    log.error("%s", message)
    if not multirun:
        _exit(code)
    record_job_failure(run_dir, message, code, exc)
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
