"""Metric sinks behind one small interface: TensorBoard, W&B, JSONL and the console.

``MetricLogger.log(metrics, step)`` fans a flat ``{"group/name": float}`` dict out to every enabled
backend; ``close()`` flushes them all. Metric names follow ``train/episode_return``, ``loss/policy``,
``eval/success_rate``, ``perf/sps``. The TensorBoard backend also writes the run's hyperparameters in
the HParams plugin's format, so ``tensorboard --logdir <sweep dir>`` compares a sweep's jobs.
"""

from __future__ import annotations

import json
import logging
import math
import os
import time
from pathlib import Path
from typing import Protocol

from rlexp.config.rules import first_line
from rlexp.config.schema import LoggerConfig

log = logging.getLogger(__name__)


class Backend(Protocol):
    def log(self, metrics: dict[str, float], step: int) -> None: ...

    def close(self) -> None: ...


#: What the HParams dashboard shows for each job besides its hyperparameters. The dashboard reads a
#: metric as the last scalar of that tag in the job's run, so these are the final values, and
#: ``best/eval_episode_return`` is the best eval return so far (logged whenever it improves).
BEST_EVAL_RETURN = "best/eval_episode_return"
HPARAMS_METRICS = (
    "eval/episode_return",
    "eval/success_rate",
    "train/episode_return",
    "train/episode_length",
    BEST_EVAL_RETURN,
)
#: Config sections that are tables of named terms (hooks, events, task terms): listed by name in
#: the HParams table; a key a job overrides inside one still gets its own column.
TERM_TABLES = frozenset(
    {
        "hooks",
        "events.train",
        "events.eval",
        "env.native.events",
        "env.native.observations",
        "env.native.rewards",
        "env.native.actions",
    }
)
#: How the run writes metrics is no hyperparameter.
NOT_HPARAMS = frozenset({"logger"})
MAX_HPARAM_TEXT = 200  # characters of a list or string value the table shows


def hparams_of(config: dict, overrides: list[str] | None = None) -> dict[str, float | bool | str]:
    """The run's config as the HParams table's columns: dotted keys, scalar values (a list as its
    text, a table of named terms as its names, ``None`` left out), plus each overridden key and the
    job's overrides as one ``overrides`` string."""
    out: dict[str, float | bool | str] = {}

    def walk(node: dict, prefix: str) -> None:
        for key, value in node.items():
            name = f"{prefix}{key}"
            if name in NOT_HPARAMS:
                continue
            if name in TERM_TABLES and isinstance(value, dict):
                out[name] = _brief(", ".join(str(k) for k in value))
            elif isinstance(value, dict):
                walk(value, name + ".")
            elif value is not None:
                out[name] = _scalar(value)

    walk(config, "")
    for override in overrides or []:
        key = override.split("=", 1)[0].lstrip("+~")
        value = _lookup(config, key)
        if value is not None and not isinstance(value, dict):
            out.setdefault(key, _scalar(value))  # e.g. env.native.rewards.success_bonus.weight
    if overrides:
        out["overrides"] = _brief(" ".join(overrides))
    return out


def _scalar(value: object) -> float | bool | str:
    if isinstance(value, (bool, int, float)):
        return value
    if isinstance(value, (list, tuple)):
        return _brief(json.dumps(value, default=str))
    return _brief(str(value))


def _brief(text: str) -> str:
    return text if len(text) <= MAX_HPARAM_TEXT else text[: MAX_HPARAM_TEXT - 3] + "..."


def _lookup(config: dict, dotted: str) -> object:
    node: object = config
    for part in dotted.split("."):
        if not isinstance(node, dict) or part not in node:
            return None
        node = node[part]
    return node


def _job_overrides(run_dir: Path) -> list[str]:
    """The Hydra overrides of this job (``.hydra/overrides.yaml``; none for ``--config-json``)."""
    path = run_dir / ".hydra" / "overrides.yaml"
    if not path.is_file():
        return []
    from omegaconf import OmegaConf

    try:
        overrides = OmegaConf.to_container(OmegaConf.load(path))
    except Exception as exc:  # a hand-edited file: the columns from the config still come
        log.warning("TensorBoard HParams: cannot read %s (%s)", path, exc)
        return []
    return [str(o) for o in overrides] if isinstance(overrides, list) else []


def _hparams_summary(tag: str, data: object):
    """One summary of the HParams plugin, made as TensorBoard's ``hparams.summary.session_end_pb``
    makes it: that module imports TensorFlow at the top (``summary_v2``, used for the rest, has no
    session end), so only the session end is built here, from the plugin's own metadata helper."""
    from tensorboard.compat.proto.summary_pb2 import Summary
    from tensorboard.plugins.hparams import metadata

    return Summary(
        value=[
            Summary.Value(
                tag=tag,
                metadata=metadata.create_summary_metadata(data),
                tensor=metadata.NULL_TENSOR,
            )
        ]
    )


def _last_logged(files: list[Path], tag: str) -> float | None:
    """The last value of scalar ``tag`` in the newest of ``files`` that has it (each process
    carries the best over into its own file, so the newest one holding the tag knows it). Read
    with TensorBoard's own loader, which stops at a record torn by a crash."""
    from tensorboard.backend.event_processing.event_file_loader import LegacyEventFileLoader

    needle = tag.encode()
    for path in reversed(files):
        try:
            with open(path, "rb") as f:
                if needle not in f.read():  # most files never logged it: skip the parse
                    continue
            last = None
            for event in LegacyEventFileLoader(str(path)).Load():  # as written: simple_value
                for value in event.summary.value:
                    if value.tag == tag:
                        last = value.simple_value
        except OSError:
            continue
        if last is not None:
            return last
    return None


class TensorBoardBackend:
    """TensorBoard event files under ``<run_dir>/tensorboard``, with the run's hyperparameters in
    the HParams plugin's format there too (one run per job in the HParams dashboard, not the
    sub-run torch's ``add_hparams`` makes)."""

    def __init__(self, run_dir: Path, config: dict | None = None) -> None:
        from torch.utils.tensorboard import SummaryWriter

        self.run_dir = run_dir
        log_dir = run_dir / "tensorboard"
        earlier = sorted(log_dir.glob("events.out.tfevents.*")) if log_dir.is_dir() else []
        self.writer = SummaryWriter(log_dir=str(log_dir))
        self.hparams = config is not None
        self.best = _last_logged(earlier, BEST_EVAL_RETURN) if self.hparams and earlier else None
        self._carry_best = self.best is not None  # a resumed run goes on from the earlier best
        if self.hparams:
            try:
                self._write_session_start(hparams_of(config, _job_overrides(run_dir)))
            except Exception as exc:  # the table is a convenience; training goes on without it
                log.warning("TensorBoard HParams: not written (%s)", exc)
                self.hparams = False

    def _write_session_start(self, hparams: dict[str, float | bool | str]) -> None:
        """The experiment (columns: hyperparameters and metrics) and this job's values, at the start,
        so a running job is in the dashboard and a killed one stays there (TensorBoard's own
        ``hparams.summary_v2`` protos)."""
        from tensorboard.plugins.hparams import summary_v2 as hp

        # No domain: the dashboard takes one job's experiment for the whole sweep, and a discrete
        # domain of this job's value alone would filter the other jobs out.
        experiment = hp.hparams_config_pb(
            hparams=[hp.HParam(key) for key in hparams],
            metrics=[hp.Metric(tag) for tag in HPARAMS_METRICS],
        )
        # trial_id "": each job is a session of its own (not grouped by a hash of its values)
        start = hp.hparams_pb(hparams, trial_id="", start_time_secs=time.time())
        for summary in (experiment, start):
            self.writer.file_writer.add_summary(summary)

    def log(self, metrics: dict[str, float], step: int) -> None:
        for key, value in metrics.items():
            self.writer.add_scalar(key, value, global_step=step)
        if not self.hparams:
            return
        value = metrics.get("eval/episode_return")
        improved = (
            value is not None and math.isfinite(value) and (self.best is None or value > self.best)
        )
        if improved:
            self.best = value
        if improved or self._carry_best:
            self.writer.add_scalar(BEST_EVAL_RETURN, self.best, global_step=step)
            self._carry_best = False

    def close(self) -> None:
        try:
            if self.hparams:
                self._write_session_end()
        finally:
            self.writer.flush()
            self.writer.close()

    def _write_session_end(self) -> None:
        """How the job ended, from ``status.json`` (written before the logger closes). Only for an
        end that stays: TensorBoard keeps the first session end of a run, and an interrupted or
        preempted run is resumed."""
        from tensorboard.plugins.hparams import api_pb2, metadata, plugin_data_pb2

        from rlexp.run.rundir import read_status

        status = {
            "finished": api_pb2.STATUS_SUCCESS,
            "stopped_early": api_pb2.STATUS_SUCCESS,
            "pruned": api_pb2.STATUS_SUCCESS,
        }.get(str(read_status(self.run_dir).get("state")))
        if status is None:
            return
        end = plugin_data_pb2.SessionEndInfo(status=status, end_time_secs=time.time())
        self.writer.file_writer.add_summary(
            _hparams_summary(
                metadata.SESSION_END_INFO_TAG,
                plugin_data_pb2.HParamsPluginData(session_end_info=end),
            )
        )


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


def wandb_credentials() -> str:
    """Where W&B would find credentials for the server it talks to ("" when nowhere), asked of
    wandb itself: its base URL (``WANDB_BASE_URL``, its settings files; a self-hosted server too),
    ``WANDB_API_KEY`` / ``WANDB_IDENTITY_TOKEN_FILE``, the ``.netrc`` entry for that host
    (``NETRC`` too), and the key in its settings."""
    for var in ("WANDB_API_KEY", "WANDB_IDENTITY_TOKEN_FILE"):
        if os.environ.get(var):
            return var
    from wandb.sdk import wandb_setup
    from wandb.sdk.lib import wbauth

    settings = wandb_setup.singleton().settings
    try:
        if wbauth.read_netrc_auth(host=settings.base_url):
            return f".netrc ({settings.base_url})"
    except Exception as exc:  # a malformed key: wandb.init would refuse it too; say so, go online
        return f".netrc ({settings.base_url}; wandb says: {first_line(exc)})"
    if settings.api_key:
        return "wandb settings"
    return ""


def _wandb_mode(requested: str) -> str:
    """``auto`` runs online only when wandb finds credentials for its server; otherwise offline,
    with a warning naming the server."""
    if requested != "auto":
        return requested
    if os.environ.get("WANDB_MODE"):
        return os.environ["WANDB_MODE"]
    if not wandb_credentials():
        from wandb.sdk import wandb_setup

        host = wandb_setup.singleton().settings.base_url
        log.warning(
            "W&B: no API key for %s (WANDB_API_KEY, .netrc, wandb login); logging offline under "
            "the run dir (sync later with `wandb sync`)",
            host,
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
        backends.append(TensorBoardBackend(run_dir, config))
    if cfg.wandb.enabled:
        backends.append(WandbBackend(run_dir, cfg, run_name, config, wandb_run_id(run_dir), group))
    return MetricLogger(backends)
