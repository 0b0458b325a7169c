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
    """``<run_dir>/metrics.jsonl``: one JSON object per logged step, flushed at once."""

    def __init__(self, run_dir: Path) -> None:
        self.path = run_dir / "metrics.jsonl"
        self.file = open(self.path, "a", encoding="utf-8")  # noqa: SIM115 - closed in close()

    def log(self, metrics: dict[str, float], step: int) -> None:
        row = {"step": step, "time": round(time.time(), 3)}
        row.update({k: (v if math.isfinite(v) else None) for k, v in metrics.items()})
        self.file.write(json.dumps(row) + "\n")
        self.file.flush()

    def close(self) -> None:
        self.file.close()


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

    def log(self, metrics: dict[str, float], step: int) -> None:
        for backend in self.backends:
            backend.log(metrics, step)

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
