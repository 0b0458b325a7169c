"""A run dir: one run at a time (a lock), ``status.json``, ``heartbeat.json``, and the checks before
a run writes in it.

A run takes an exclusive ``fcntl.flock`` on ``<run_dir>/.rlexp.lock`` for its whole life. The kernel
drops the lock when the process dies (SIGKILL, a node crash on the same host, a SLURM requeue), so a
lock file left behind never blocks a resume; a second live run on the same dir is refused with the
holder's PID, host and start time. The lock file stays (removing it would race with a new holder).

A running run also keeps ``heartbeat.json`` fresh (``Heartbeat``: host, PID and its start time, the
time, the step, the best and last eval), so that ``rlexp runs`` can tell a run that is still going
from one that a SIGKILL, an OOM kill or a lost node left saying ``running`` (docs/runs.md).
"""

from __future__ import annotations

import json
import logging
import math
import os
import socket
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from rlexp.config.validate import ConfigError
from rlexp.files.fsutil import HolderBusy, HolderLock, atomic_write_text

log = logging.getLogger(__name__)

LOCK_NAME = ".rlexp.lock"
#: Exit codes of ``python train.py`` (docs/faults.md).
EXIT_FAILED = 1  # training started and failed (status.json: failed, with the reason)
EXIT_CONFIG = 2  # bad config or command line, or a busy run dir: nothing was trained
EXIT_NONFINITE = 3  # the NaN guard stopped the run (status.json: failed)
#: Interrupted by a signal after saving a checkpoint: 128 + the signal number (130 SIGINT, 143
#: SIGTERM, 129 SIGHUP), as a shell expects from a process that a signal ended.
EXIT_SIGNAL_BASE = 128


class RunDirBusy(ConfigError):
    """Another live process holds the run dir's lock."""


class RunDirLock:
    """Exclusive lock on a run dir for the life of one run (``with RunDirLock(dir): ...``): a
    ``rlexp.files.fsutil.HolderLock`` on ``<run_dir>/.rlexp.lock``."""

    def __init__(self, run_dir: Path) -> None:
        self.run_dir = Path(run_dir)
        self.path = self.run_dir / LOCK_NAME
        self._lock = HolderLock(self.path)

    def acquire(self) -> RunDirLock:
        """Take the lock or raise ``RunDirBusy`` naming the holder; creates the dir if needed."""
        try:
            self._lock.acquire()
        except HolderBusy as busy:
            raise RunDirBusy(
                f"run dir {self.run_dir} is in use by another run ({busy.holder}); wait for it to "
                "end, or use another hydra.run.dir"
            ) from None
        return self

    def check(self) -> None:
        """Raise ``RunDirBusy`` if a live run holds the lock now (takes and drops it at once)."""
        if not self.path.is_file():
            return
        self.acquire()
        self.release()

    def release(self) -> None:
        """Drop the lock (idempotent)."""
        self._lock.release()

    @property
    def held(self) -> bool:
        return self._lock.held

    def __enter__(self) -> RunDirLock:
        return self.acquire()

    def __exit__(self, *exc: object) -> None:
        self.release()


def read_status(run_dir: Path) -> dict[str, Any]:
    """``status.json`` of a run dir ({} when there is none or it is not a JSON object); read
    bounded (``rlexp.files.safe_read``: a FIFO or a huge file never blocks or fills memory)."""
    from rlexp.files.safe_read import load_json

    try:
        status = load_json(Path(run_dir) / "status.json")
    except (OSError, ValueError):
        return {}
    return status if isinstance(status, dict) else {}


def final_value(status: Any, metric: str, states: tuple[str, ...]) -> float | None:
    """A ``status.json``'s final evaluation of ``metric`` when the run ended in one of ``states``
    (None: another state, no such value, or not a finite number)."""
    if not isinstance(status, dict) or status.get("state") not in states:
        return None
    final = status.get("final_eval")
    value = final.get(metric) if isinstance(final, dict) else None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        return None
    return float(value)


def write_status(
    run_dir: Path, state: str, global_step: int, final_eval: dict | None = None, **extra: Any
) -> None:
    """``status.json``: running | finished | stopped_early | pruned | interrupted | stopped | failed, the step and the last eval
    (what sweeps and ``rlexp report`` read to tell finished jobs from unfinished ones). Rank 0 only."""
    from rlexp.runtime.distributed import info

    if not info().is_main:
        return
    status = {
        "state": state,
        "global_step": global_step,
        "final_eval": final_eval or {},
        "time": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "pid": os.getpid(),
        "host": socket.gethostname(),
        **extra,
    }
    # synced: sweeps and resumes decide from it, after a crash of the node too
    atomic_write_text(Path(run_dir) / "status.json", json.dumps(status, indent=2) + "\n")


def clean_temp_files(run_dir: Path) -> list[Path]:
    """Remove temporary files a killed write left (checkpoints, status); call with the lock held."""
    run_dir = Path(run_dir)
    removed = []
    for pattern in (".*.tmp-*", "checkpoints/.*.tmp-*", ".status.json.tmp*"):
        for path in run_dir.glob(pattern):
            try:
                path.unlink()
                removed.append(path)
            except FileNotFoundError:
                pass
    if removed:
        log.info("removed %d temporary file(s) left by an interrupted write", len(removed))
    return removed


#: Keys a continuation may change: the budget (train longer), how to resume, the device, the console.
RESUME_MAY_CHANGE = (
    "trainer.total_frames",
    "trainer.iterations",
    "trainer.resume",
    "trainer.device",
    "trainer.progress",
    "trainer.strict_device",
    "algorithm.compile",  # how the loss runs, not what it computes
    "trainer.precision",  # the networks' arithmetic (fp32 <-> bf16 resume; older dirs lack it)
    "logger.console",  # the summary lines on the console
    "env.num_eval_envs",  # evaluation copies (the Gymnasium default went from 1 to 10)
    "trainer.eval_async",  # where eval rounds run, not what they compute (and older dirs lack it)
    "trainer.stall_timeout_s",  # how a stuck run is told and ended, not what it trains
    "trainer.stop_grace_s",
    "env.vectorization",  # removed (it never did anything); older run dirs still hold it
)


def config_differences(
    a: dict[str, Any], b: dict[str, Any], ignore: tuple[str, ...] = (), prefix: str = ""
) -> list[str]:
    """Dotted keys whose values differ between two plain config dicts."""
    out = []
    for key in sorted(set(a) | set(b)):
        path = f"{prefix}{key}"
        if path in ignore:
            continue
        va, vb = a.get(key), b.get(key)
        if isinstance(va, dict) and isinstance(vb, dict):
            out += config_differences(va, vb, ignore, path + ".")
        elif va != vb:
            out.append(path)
    return out


def check_run_dir(run_dir: Path, config_dict: dict[str, Any], resume: str) -> None:
    """What ``trainer.resume`` may do with what the dir holds: ``auto`` continues the same
    experiment only; ``never`` refuses a dir that holds a run (starting over there would mix the
    old run's checkpoints and metrics with the new one's)."""
    if resume == "auto":
        check_same_experiment(run_dir, config_dict)
    elif resume in ("never", ""):
        held = holds_a_run(Path(run_dir))
        if held:
            raise ConfigError(
                f"trainer.resume=never but run dir {run_dir} holds a run ({held}); starting over "
                "there would mix two runs: use a new hydra.run.dir, or move that dir aside"
            )


def holds_a_run(run_dir: Path) -> str:
    """What in ``run_dir`` belongs to a run that trained ("" when nothing does)."""
    from rlexp.checkpoints.files import step_checkpoints

    ckpts = step_checkpoints(run_dir / "checkpoints")
    if ckpts:
        return f"{len(ckpts)} checkpoint(s), newest {ckpts[-1].name}"
    metrics = run_dir / "metrics.jsonl"
    if metrics.is_file() and metrics.stat().st_size > 0:
        return "metrics.jsonl"
    return ""


def saved_config(run_dir: Path, fix: str = "move the run dir aside") -> dict[str, Any] | None:
    """The run dir's ``config.yaml`` as a plain dict (None when there is none); ``ConfigError``
    naming it and ``fix`` when it cannot be read as a config mapping."""
    from omegaconf import OmegaConf

    path = Path(run_dir) / "config.yaml"
    if not path.is_file():
        return None
    try:
        saved = OmegaConf.to_container(OmegaConf.load(path), resolve=True)
    except Exception as exc:  # a damaged config.yaml: say so rather than guess
        raise ConfigError(f"{path} is unreadable ({exc}); {fix}") from None
    if not isinstance(saved, dict):
        raise ConfigError(f"{path} is not a config mapping; {fix}")
    return saved


def check_same_experiment(run_dir: Path, config_dict: dict[str, Any]) -> None:
    """A dir that holds a checkpoint holds an experiment: continuing there with another config would
    mix two runs. A dir with a ``config.yaml`` but no checkpoint (a run that failed before training)
    holds nothing yet and takes the corrected config."""
    from rlexp.checkpoints.files import step_checkpoints

    if not step_checkpoints(Path(run_dir) / "checkpoints"):
        return
    saved = saved_config(run_dir)
    if saved is None:
        return
    diffs = config_differences(saved, config_dict, ignore=RESUME_MAY_CHANGE)
    if diffs:
        raise ConfigError(
            f"run dir {run_dir} holds a different experiment (differs in {', '.join(diffs)}); "
            "use a new hydra.run.dir / hydra.sweep.dir, or move that dir aside"
        )


def write_run_files(config: Any, config_dict: dict, run_dir: Path, device: str) -> None:
    """``config.yaml``, the same config as JSON (train_config.json + gym_config.json), provenance."""
    from omegaconf import OmegaConf

    from rlexp.config.json_format import write_json_experiment
    from rlexp.config.validate import escape_interpolations
    from rlexp.run.provenance import write_provenance

    write_hydra_files(run_dir)
    # Escaped: a string that looks like ${...} (from a JSON file) reads back as those characters.
    escaped = OmegaConf.create(escape_interpolations(config_dict))
    (run_dir / "config.yaml").write_text(OmegaConf.to_yaml(escaped))
    write_json_experiment(config, run_dir)
    write_provenance(run_dir, device, config.env.name)


#: The job's Hydra config, set by ``rlexp.app._task``: ``.hydra/`` is written by rlexp once the checks have
#: passed (``hydra.output_subdir: null`` in conf/config.yaml), so that a refused run never rewrites
#: the files of the run that owns the dir.
HYDRA_JOB: dict[str, Any] = {}


def write_hydra_files(run_dir: Path) -> None:
    """``.hydra/config.yaml``, ``hydra.yaml`` and ``overrides.yaml``, as Hydra itself writes them."""
    from omegaconf import OmegaConf

    cfg, hydra_cfg = HYDRA_JOB.get("cfg"), HYDRA_JOB.get("hydra")
    if cfg is None or hydra_cfg is None:
        return  # not under Hydra (train() called from Python)
    out = run_dir / ".hydra"
    out.mkdir(parents=True, exist_ok=True)
    OmegaConf.save(cfg, out / "config.yaml")
    OmegaConf.save(OmegaConf.create({"hydra": hydra_cfg}), out / "hydra.yaml")
    OmegaConf.save(hydra_cfg.overrides.task, out / "overrides.yaml")


# -- heartbeat -------------------------------------------------------------------------------------
HEARTBEAT_NAME = "heartbeat.json"
#: Seconds between two heartbeats of a running run (the file records it for its readers).
HEARTBEAT_INTERVAL_S = 10.0
#: A heartbeat older than STALE_INTERVALS x its interval + STALE_MARGIN_S means its run is gone:
#: a few missed beats, plus room for a loaded machine and a slow shared filesystem.
STALE_INTERVALS = 3
STALE_MARGIN_S = 30.0
#: Seconds between two looks of the heartbeat's thread at the step (a stall is seen this soon).
STEP_POLL_S = 1.0


def stale_after(interval_s: float) -> float:
    """Age in seconds past which a heartbeat written every ``interval_s`` is stale."""
    return STALE_INTERVALS * interval_s + STALE_MARGIN_S


def process_stat(pid: int) -> tuple[str, int] | None:
    """(state letter, start time in clock ticks since boot) of process ``pid`` from
    ``/proc/<pid>/stat`` (fields 3 and 22); None when it cannot be read (no such process, no
    ``/proc``, or ``/proc`` hides other users' processes)."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = text[text.rfind(")") + 2 :].split()  # the name in (...) may hold spaces
    return (fields[0], int(fields[19])) if len(fields) >= 20 else None


def process_start_ticks(pid: int) -> int | None:
    """When live process ``pid`` started (clock ticks since boot); None if unknown or a zombie."""
    stat = process_stat(pid)
    return stat[1] if stat is not None and stat[0] not in ("Z", "X") else None


def boot_id() -> str | None:
    """This boot of this host (a PID and its start ticks mean nothing after a reboot)."""
    try:
        return Path("/proc/sys/kernel/random/boot_id").read_text().strip()
    except OSError:
        return None


def read_heartbeat(run_dir: Path) -> dict[str, Any]:
    """``heartbeat.json`` of a run dir ({} when there is none or it is not a JSON object); read
    bounded (``rlexp.files.safe_read``)."""
    from rlexp.files.safe_read import load_json

    try:
        beat = load_json(Path(run_dir) / HEARTBEAT_NAME)
    except (OSError, ValueError):
        return {}
    return beat if isinstance(beat, dict) else {}


def _json_safe(value: Any) -> Any:
    """``value`` with every NaN/Inf float as None (strict JSON, as in ``metrics.jsonl``)."""
    if isinstance(value, dict):
        return {str(k): _json_safe(v) for k, v in value.items()}
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


class Heartbeat:
    """Writes ``heartbeat.json`` now and every ``interval_s`` from a daemon thread until ``stop``.

    ``progress()`` gives what else the beat records (``global_step``, ``total``, ``best_metric``,
    ``best``, ``last_eval``); it is called from the thread, so it must only read. The thread proves
    the process lives, not that it trains: it also samples ``global_step`` every STEP_POLL_S and
    records when it last moved (``step_time``) and the run's ``stall_timeout_s``, so that readers
    tell a loop stuck in an env step or a wait from a working one (``rlexp.analysis.liveness``); the bound
    crossed is logged and beaten at once. The file stays when the run ends (``status.json`` says how
    it ended); a write that fails is logged once and retried at the next beat."""

    def __init__(
        self,
        run_dir: Path,
        progress: Callable[[], dict[str, Any]],
        interval_s: float = HEARTBEAT_INTERVAL_S,
        stall_timeout_s: float | None = None,
    ) -> None:
        self.path = Path(run_dir) / HEARTBEAT_NAME
        self.progress = progress
        self.interval_s = interval_s
        self.stall_timeout_s = stall_timeout_s
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._warned = False
        self._step: Any = None
        self._step_time: float | None = None
        self._stalled = False
        pid = os.getpid()
        self._who = {
            "host": socket.gethostname(),
            "pid": pid,
            "pid_start_ticks": process_start_ticks(pid),
            "boot_id": boot_id(),
            "interval_s": interval_s,
            "stall_timeout_s": stall_timeout_s,
        }

    def _sample(self) -> tuple[dict[str, Any], bool]:
        """(the progress now, whether the step just crossed the stall bound)."""
        try:
            extra = dict(self.progress())
        except Exception as exc:  # never let the progress read break the beat itself
            extra = {"progress_error": f"{type(exc).__name__}: {exc}"}
        return extra, self._watch(extra.get("global_step"), time.time())

    def _watch(self, step: Any, now: float) -> bool:
        if step != self._step or self._step_time is None:
            if self._stalled:
                log.info("[stall] step %s: training moves again", step)
            self._step, self._step_time, self._stalled = step, now, False
            return False
        limit = self.stall_timeout_s
        if limit is None or self._stalled or now - self._step_time <= limit:
            return False
        self._stalled = True
        log.warning(
            "[stall] step %s has not moved for %.0f s (trainer.stall_timeout_s=%g): the loop waits "
            "on something (an env step, an eval round, another rank); SIGTERM stops it",
            step, now - self._step_time, limit,
        )  # fmt: skip
        return True

    def beat(self, extra: dict[str, Any] | None = None) -> None:
        """Write the heartbeat once, atomically (``extra``: progress just sampled)."""
        if extra is None:
            extra, _ = self._sample()
        data = _json_safe({**self._who, "time": round(time.time(), 3),
                           "step_time": round(self._step_time or time.time(), 3), **extra})  # fmt: skip
        try:  # not synced: rewritten every few seconds, it only says the process lives
            text = json.dumps(data, allow_nan=False, default=str) + "\n"
            atomic_write_text(self.path, text, fsync=False)
        except (OSError, ValueError) as exc:
            if not self._warned:
                log.warning("could not write %s: %s", self.path, exc)
                self._warned = True

    def _loop(self) -> None:
        due = time.monotonic() + self.interval_s
        while not self._stop.wait(min(self.interval_s, STEP_POLL_S)):
            extra, crossed = self._sample()
            if crossed or time.monotonic() >= due:
                self.beat(extra)
                due = time.monotonic() + self.interval_s

    def start(self) -> Heartbeat:
        """First beat now, then one every ``interval_s``."""
        self.beat()
        self._thread = threading.Thread(target=self._loop, name="rlexp-heartbeat", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop the thread and write a last beat (the final step and eval); idempotent."""
        if self._thread is None:
            return
        self._stop.set()
        self._thread.join()
        self._thread = None
        self.beat()
