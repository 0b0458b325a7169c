"""The run's last console line: what it did, its final evaluation, and what to do next."""

from __future__ import annotations

import shlex
from pathlib import Path
from typing import Any

from rlexp.common.table import format_number


def done_message(trainer: Any, run_dir: Path) -> str:
    """``done: 1,000,000 env steps; final eval eval/episode_return=3263.1 (best 3301.9);
    checkpoint ...`` and, on the next line, the commands a user runs next (evaluate it,
    watch its curves, list the runs)."""
    parts = [f"done: {trainer.global_step:,} env steps"]
    metric = trainer.cfg.best_metric
    final = trainer.last_eval.get(metric) if trainer.last_eval else None
    if final is not None:
        text = f"final eval {metric}={format_number(final)}"
        best = trainer.best_metric
        if best is not None and best != -float("inf") and best != final:
            text += f" (best {format_number(best)})"
        parts.append(text)
    if trainer.last_checkpoint:
        parts.append(f"checkpoint {trainer.last_checkpoint}")
    here = shlex.quote(str(run_dir))
    steps = [f"rlexp eval {here}", "rlexp runs"]
    if (Path(run_dir) / "tensorboard").is_dir():  # logger.tensorboard wrote its event files
        steps.insert(1, f"tensorboard --logdir {shlex.quote(str(Path(run_dir) / 'tensorboard'))}")
    return "; ".join(parts) + "\nnext: " + "  |  ".join(steps)
