"""Metric sinks behind one small interface: TensorBoard, W&B, JSONL and the console.

``MetricLogger.log(metrics, step)`` fans a flat ``{"group/name": float}`` dict out to every enabled
backend; ``close()`` flushes them all. Metric names follow ``train/episode_return``, ``loss/policy``,
``eval/success_rate``, ``perf/sps``.
"""

from __future__ import annotations

import json
import logging
import math
import os
import time
from pathlib import Path
from typing import Protocol

from rlexp.config.schema import LoggerConfig

log = logging.getLogger(__name__)


class Backend(Protocol):
    def log(self, metrics: dict[str, float], step: int) -> None: ...

    def close(self) -> None: ...


class TensorBoardBackend:
    """TensorBoard event files under ``<run_dir>/tensorboard``."""

    def __init__(self, run_dir: Path) -> None:
        from torch.utils.tensorboard import SummaryWriter

        self.writer = SummaryWriter(log_dir=str(run_dir / "tensorboard"))

    def log(self, metrics: dict[str, float], step: int) -> None:
        for key, value in metrics.items():
            self.writer.add_scalar(key, value, global_step=step)

    def close(self) -> None:
        self.writer.flush()
        self.writer.close()


class JsonlBackend:
    """``<run_dir>/metrics.jsonl``: one JSON object per logged step, written whole or not at all."""

    def __init__(self, run_dir: Path) -> None:
        self.path = run_dir / "metrics.jsonl"
        self.fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        self._cut_torn_last_line()

    def _cut_torn_last_line(self) -> None:
        """A crash mid-write in an older version (or a full disk) may have left half a line."""
        size = os.lseek(self.fd, 0, os.SEEK_END)
        if size == 0:
            return
        with open(self.path, "rb") as f:
            f.seek(max(0, size - 1))
            if f.read(1) == b"\n":
                return
            f.seek(0)
            data = f.read()
        os.ftruncate(self.fd, data.rfind(b"\n") + 1)

    def log(self, metrics: dict[str, float], step: int) -> None:
        row = {"step": step, "time": round(time.time(), 3)}
        row.update({k: (v if math.isfinite(v) else None) for k, v in metrics.items()})
        data = (json.dumps(row) + "\n").encode()
        end = os.lseek(self.fd, 0, os.SEEK_END)
        try:
            view = memoryview(data)
            while view:
                view = view[os.write(self.fd, view) :]
        except OSError:
            # A full disk: never leave half a line that breaks readers; cut back to the last row.
            try:
                os.ftruncate(self.fd, end)
            except OSError:
                pass
            raise

    def close(self) -> None:
        os.close(self.fd)


def _wandb_mode(requested: str) -> str:
    """``auto`` runs online only when an API key is configured; otherwise offline, with a warning."""
    if requested != "auto":
        return requested
    if os.environ.get("WANDB_MODE"):
        return os.environ["WANDB_MODE"]
    has_key = (
        bool(os.environ.get("WANDB_API_KEY"))
        or (Path.home() / ".netrc").exists()
        and "api.wandb.ai" in (Path.home() / ".netrc").read_text(errors="ignore")
    )
    if not has_key:
        log.warning(
            "W&B: no API key found; logging offline under the run dir (sync later with `wandb sync`)"
        )
        return "offline"
    return "online"


class WandbBackend:
    """Weights & Biases run; files under ``<run_dir>/wandb``."""

    def __init__(
        self,
        run_dir: Path,
        cfg: LoggerConfig,
        run_name: str,
        config: dict,
        run_id: str,
        group: str | None = None,
    ) -> None:
        import wandb

        self.run = wandb.init(
            project=cfg.wandb.project,
            entity=cfg.wandb.entity,
            name=run_name,
            dir=str(run_dir),
            config=config,
            mode=_wandb_mode(cfg.wandb.mode),
            tags=list(cfg.wandb.tags),
            id=run_id,
            group=group,
            resume="allow",
            reinit="finish_previous",
        )

    def log(self, metrics: dict[str, float], step: int) -> None:
        self.run.log(metrics, step=step)

    def close(self) -> None:
        self.run.finish()


class MetricLogger:
    """Fans metrics out to the enabled backends."""

    def __init__(self, backends: list[Backend]) -> None:
        self.backends = backends
        self.closed = False
        self.failing: dict[str, str] = {}  # backend -> the write error, while writes fail

    def log(self, metrics: dict[str, float], step: int) -> None:
        """Write to every backend. A backend whose write fails (a full disk) is reported once and
        tried again at the next step; training goes on, since checkpoints are what a run must not
        lose (a checkpoint that cannot be written stops the run with status ``failed``)."""
        if not metrics:
            return
        for backend in self.backends:
            name = type(backend).__name__
            try:
                backend.log(metrics, step)
            except OSError as exc:
                if name not in self.failing:
                    log.warning(
                        "%s: writing metrics at step %d failed (%s); training goes on, these "
                        "metrics are lost until writes succeed again",
                        name,
                        step,
                        exc,
                    )
                self.failing[name] = str(exc)
            else:
                if self.failing.pop(name, None) is not None:
                    log.warning("%s: writing metrics works again from step %d", name, step)

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        for backend in self.backends:
            try:
                backend.close()
            except Exception as exc:  # closing must not hide the run's own outcome
                log.warning("closing %s failed: %s", type(backend).__name__, exc)


def wandb_run_id(run_dir: Path) -> str:
    """The run dir's W&B run id: made once, reused on every resume (a requeued job continues its run)."""
    path = run_dir / "wandb_run_id.txt"
    if path.is_file():
        return path.read_text().strip()
    import secrets

    run_id = secrets.token_hex(4)
    path.write_text(run_id + "\n")
    return run_id


def make_logger(
    cfg: LoggerConfig, run_dir: Path, run_name: str, config: dict, group: str | None = None
) -> MetricLogger:
    """Build the configured metric sinks for one run (``group``: the sweep, for W&B)."""
    backends: list[Backend] = []
    if cfg.jsonl:
        backends.append(JsonlBackend(run_dir))
    if cfg.tensorboard.enabled:
        backends.append(TensorBoardBackend(run_dir))
    if cfg.wandb.enabled:
        backends.append(WandbBackend(run_dir, cfg, run_name, config, wandb_run_id(run_dir), group))
    return MetricLogger(backends)
