"""What a run dir's own files prove, before ``trainer.resume=auto`` skips or continues a run there.

A run or sweep job continues only what its config and checkpoints prove; ``status.json`` alone
proves nothing (docs/checkpoints.md, "What a run dir must prove"):

- **skip** (``already finished at step N: skipping``, the saved result returned to a sweeper) only
  when the dir's ``config.yaml`` is this run's config (keys a continuation may change aside,
  ``RESUME_MAY_CHANGE``): a job dir whose ``config.yaml`` is missing or of another config would
  hand its old result to a new configuration, and an Optuna study would record it;
- **continue** only from a checkpoint whose own config is this run's;
- **start over** only where nothing trained: a dir that holds metrics or a status of a run that
  trained (step > 0) but no checkpoint that loads (``checkpoints/`` deleted, every file corrupt)
  is refused: starting from step 0 there would append a second run to its ``metrics.jsonl``.

Each refusal is one line (``ConfigError``: exit 2, or a failed sweep job) naming the dir, what it
holds or what differs, and what to do: move that dir aside, or use a new dir. Nothing is written.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

from rlexp.config.validate import ConfigError
from rlexp.run import rundir
from rlexp.run.rundir import RESUME_MAY_CHANGE, config_differences, read_status

log = logging.getLogger(__name__)

#: What ends every refusal: the two ways out.
FIX = "move that dir aside, or use a new hydra.run.dir / hydra.sweep.dir"
#: ``metrics.jsonl`` is read from its end, at most this many bytes, for the step of its last row.
TAIL_BYTES = 64 * 1024


def saved_config(run_dir: Path) -> dict[str, Any] | None:
    """The run dir's ``config.yaml`` as a plain dict (None when there is none); ``ConfigError``
    when it cannot be read as a config mapping (``rlexp.run.rundir.saved_config``)."""
    return rundir.saved_config(run_dir, FIX)


def precheck_run_dir(run_dir: Path, config: Any) -> None:
    """For a single run with ``trainer.resume=auto``, before Hydra writes its log into the dir
    (``rlexp.launch.precheck``): what :func:`finished_result` and :func:`check_continuation` would
    refuse, without loading a checkpoint (a dir whose checkpoints all fail to load is refused
    when the run loads them)."""
    from rlexp.checkpoints.files import step_checkpoints
    from rlexp.config.validate import to_dict, total_frames
    from rlexp.runtime.distributed import info

    config_dict = to_dict(config)
    total = total_frames(config, info().world_size)
    if finished_result(run_dir, config_dict, total, quiet=True) is not None:
        return  # skipped, proven
    if not step_checkpoints(Path(run_dir) / "checkpoints"):
        check_continuation(run_dir, config_dict, None)


def finished_result(
    run_dir: Path, config_dict: dict[str, Any], total: int, quiet: bool = False
) -> dict | None:
    """The saved final eval when ``run_dir`` already finished this config's budget (the job is
    skipped), None when there is something to train. ``ConfigError`` when the dir says finished
    but its ``config.yaml`` is missing or of another config: its result is not this run's."""
    status = read_status(run_dir)
    state, step = status.get("state"), status.get("global_step")
    done = state in ("stopped_early", "pruned") or (
        state == "finished" and isinstance(step, int) and step >= total
    )
    if not done:
        return None
    what = f"run dir {run_dir} says {str(state).replace('_', ' ')} at step {step}"
    saved = saved_config(run_dir)
    if saved is None:
        raise ConfigError(
            f"{what} but holds no config.yaml to show which config that was: its result cannot "
            f"be taken for this one; {FIX}"
        )
    diffs = config_differences(saved, config_dict, ignore=RESUME_MAY_CHANGE)
    if diffs:
        raise ConfigError(
            f"{what} for a different experiment (differs in {', '.join(diffs)}): its result is "
            f"not this config's; {FIX}"
        )
    if not quiet:
        log.info("%s: skipping", what.replace(" says ", " already "))
    final = status.get("final_eval")
    return dict(final) if isinstance(final, dict) else {}


def finished_before_building(config: Any, run_dir: Path) -> dict | None:
    """A job whose dir already finished this config (``trainer.resume=auto``; not distributed,
    whose ranks decide together in ``rlexp.app.train``): its saved result, proven as
    :func:`finished_result` proves it, before the job's config check builds an env (and imports
    torch): a re-run sweep skips its finished jobs in a fraction of a second each. None: build and
    train."""
    import os

    from rlexp.config.validate import to_dict, total_frames

    if config.trainer.resume != "auto" or os.environ.get("RLEXP_DISTRIBUTED") == "1":
        return None
    if not (Path(run_dir) / "status.json").is_file():
        return None
    return finished_result(Path(run_dir), to_dict(config), total_frames(config, 1))


def check_continuation(
    run_dir: Path, config_dict: dict[str, Any], ckpt: dict[str, Any] | None
) -> None:
    """``ConfigError`` unless ``trainer.resume=auto`` may go on in ``run_dir``: from ``ckpt`` (the
    newest checkpoint that loads) when its config is this run's, or from step 0 when nothing in
    the dir trained."""
    if ckpt is not None:
        saved = ckpt.get("config")
        diffs = (
            config_differences(saved, config_dict, ignore=RESUME_MAY_CHANGE)
            if isinstance(saved, dict)
            else ["config (the checkpoint has none)"]
        )
        if diffs:
            raise ConfigError(
                f"checkpoint {ckpt.get('path')} in run dir {run_dir} is of a different experiment "
                f"(differs in {', '.join(diffs)}); {FIX}"
            )
        return
    held = trained_without_checkpoint(Path(run_dir))
    if held:
        raise ConfigError(
            f"run dir {run_dir} holds {held} but no checkpoint that loads: starting again from "
            f"step 0 there would mix two runs in one metrics.jsonl; {FIX}"
        )


def trained_without_checkpoint(run_dir: Path) -> str:
    """What in ``run_dir`` says a run trained there ("" when nothing does): rows in
    ``metrics.jsonl`` past step 0, or a ``status.json`` at a step > 0 that is not ``failed`` (a
    run that failed in its first rollout, the NaN guard on the first batch, counted its steps but
    logged and learned nothing: the corrected config may start there)."""
    status = read_status(run_dir)
    step = status.get("global_step")
    metrics = run_dir / "metrics.jsonl"
    try:
        size = metrics.stat().st_size if metrics.is_file() else 0
    except OSError:
        size = 0
    last = last_logged_step(metrics) if size else None
    if size and (last is None or last > 0):  # rows at step 0 only: nothing trained yet
        at = f" (step {last})" if last is not None else ""
        return f"metrics of a run{at} in metrics.jsonl"
    state = status.get("state")
    if isinstance(step, int) and not isinstance(step, bool) and step > 0 and state != "failed":
        return f"a status.json of a run ({state} at step {step})"
    return ""


def last_logged_step(path: Path) -> int | None:
    """The ``step`` of the last whole row of a ``metrics.jsonl`` (read from its end, bounded)."""
    try:
        with open(path, "rb") as f:
            f.seek(0, 2)
            size = f.tell()
            f.seek(max(0, size - TAIL_BYTES))
            tail = f.read(TAIL_BYTES)
    except OSError:
        return None
    for line in reversed(tail.splitlines()):
        try:
            row = json.loads(line)
        except ValueError:
            continue  # a torn last line, or the cut-off first one
        step = row.get("step") if isinstance(row, dict) else None
        if isinstance(step, int) and not isinstance(step, bool):
            return step
    return None
