"""Is a run whose ``status.json`` says ``running`` still running? Its heartbeat and its PID decide
between running, died, stalled and running? (the rules are in docs/runs.md)."""

from __future__ import annotations

import os
import socket
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any

from rlexp.common.table import format_duration
from rlexp.run.rundir import (
    HEARTBEAT_INTERVAL_S,
    boot_id,
    process_start_ticks,
    process_stat,
    stale_after,
)

_TIME_FORMAT = "%Y-%m-%dT%H:%M:%S%z"  # status.json and provenance.json


def parse_time(text: Any) -> float | None:
    """An rlexp timestamp (``2026-11-23T15:37:22+0000``) as epoch seconds; None if it is not one."""
    try:
        return datetime.strptime(str(text), _TIME_FORMAT).timestamp()
    except ValueError:
        return None


@dataclass(frozen=True)
class Here:
    """This host, as the liveness rules compare it with a run's."""

    host: str
    boot: str | None
    boot_time: float | None  # epoch seconds at boot (/proc/stat btime)
    ticks_per_s: int

    @classmethod
    def now(cls) -> Here:
        btime = None
        try:
            for line in Path("/proc/stat").read_text().splitlines():
                if line.startswith("btime "):
                    btime = float(line.split()[1])
        except OSError:
            pass
        return cls(socket.gethostname(), boot_id(), btime, os.sysconf("SC_CLK_TCK"))


def _pid_gone(pid: int, ticks: int | None) -> str:
    """Why ``pid`` is not the run's process ("" when it may be): gone, a zombie, or started at
    other ``ticks`` (None: the start is not known)."""
    if pid <= 0:
        return f"PID {pid} is not a process"
    try:
        os.kill(pid, 0)  # signal 0: only asks whether the process exists
    except ProcessLookupError:
        return f"PID {pid} is gone"
    except PermissionError:
        pass  # it exists, another user's
    stat = process_stat(pid)  # None: no /proc, or /proc hides it: the PID exists, that is all
    if stat is not None and stat[0] in ("Z", "X"):
        return f"PID {pid} is gone"
    if stat is not None and ticks is not None and stat[1] != ticks:
        return f"PID {pid} is now another process"
    return ""


def _age(seconds: float) -> str:
    return format_duration(max(0.0, seconds))


def _num(value: Any) -> float | None:
    ok = isinstance(value, (int, float)) and not isinstance(value, bool)
    return float(value) if ok else None


def _no_progress(beat: dict[str, Any], now: float) -> str:
    """Why a run whose heartbeat is fresh is stalled: its step has not moved for longer than the
    run's own ``stall_timeout_s`` as its last beat saw it ("" when it moves, or the beat is from
    before ``step_time`` was recorded)."""
    limit, moved, beat_time = (_num(beat.get(k)) for k in ("stall_timeout_s", "step_time", "time"))
    if limit is None or moved is None or beat_time is None or beat_time - moved <= limit:
        return ""
    step = beat.get("global_step")
    return f"step {step} has not moved for {_age(now - moved)} (stalled after {_age(limit)})"


def _by_heartbeat(beat: dict[str, Any], now: float, here: Here) -> tuple[str, str]:
    host, pid = beat.get("host"), beat.get("pid")
    interval = beat.get("interval_s")
    limit = stale_after(interval if isinstance(interval, (int, float)) else HEARTBEAT_INTERVAL_S)
    beat_time = beat.get("time")
    age = now - beat_time if isinstance(beat_time, (int, float)) else float("inf")
    stale = f"no heartbeat for {_age(age)} (stale after {limit:.0f} s)"
    if host == here.host and isinstance(pid, int):
        if beat.get("boot_id") and here.boot and beat["boot_id"] != here.boot:
            return "died", f"host {host} rebooted since its last heartbeat"
        gone = _pid_gone(pid, beat.get("pid_start_ticks"))
        if gone:
            return "died", gone
        if age > limit:  # the process lives but does not beat: hung or stopped (SIGSTOP)
            return "stalled", f"PID {pid} is alive but {stale}"
        stuck = _no_progress(beat, now)  # it beats, but its loop does not move
        return ("stalled", f"PID {pid} is alive but {stuck}") if stuck else ("running", "")
    if age > limit:
        return "died", f"{stale}, on host {host}"
    stuck = _no_progress(beat, now)
    return ("stalled", f"{stuck}, on host {host}") if stuck else ("running", "")


def _by_pid(status: dict[str, Any], here: Here) -> tuple[str, str]:
    """A run from before heartbeat.json: the PID rule, on this host only."""
    pid = status.get("pid")
    if status.get("host") != here.host or not isinstance(pid, int):
        return "running?", f"no heartbeat, and it ran on host {status.get('host')}: cannot tell"
    gone = _pid_gone(pid, None)
    if gone:
        return "died", gone
    ticks, since = process_start_ticks(pid), parse_time(status.get("time"))
    if ticks is not None and here.boot_time is not None and since is not None:
        # A PID reused by a later process started after the run wrote "running".
        if here.boot_time + ticks / here.ticks_per_s > since + 2:
            return "died", f"PID {pid} is now another process"
    return "running", ""


def liveness(
    status: dict[str, Any], beat: dict[str, Any], now: float, here: Here
) -> tuple[str, str]:
    """(status to show, why): a ``running`` status.json checked against heartbeat and PID."""
    state = status.get("state")
    if not isinstance(state, str):
        return "unknown", "no readable status.json (not started, or it ended before training)"
    if state != "running":
        return state, ""
    same_attempt = not (isinstance(status.get("pid"), int) and beat.get("pid") != status["pid"])
    if beat and same_attempt:
        return _by_heartbeat(beat, now, here)
    return _by_pid(status, here)
