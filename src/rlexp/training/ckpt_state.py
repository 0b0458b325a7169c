"""The algorithm's part of the trainer's state on its way to the eval worker or to a checkpoint
file, for the learners whose state is more than tensors (SAC, TD3: a replay buffer on disk).

An eval round's snapshot takes ``snapshot_state()`` where the algorithm has one (SAC/TD3: the
replay manifest without writing its new rows: most rounds are never written anywhere); a state
is ``settled`` right before a checkpoint file holds it (best.pt, a step checkpoint that waited for
its round, a round in flight inside a checkpoint: the snapshot's rows are written then); once a
checkpoint is on disk and old ones pruned, ``written`` lets the algorithm delete what no
checkpoint there needs (docs/replay.md, "Checkpoints").
"""

from __future__ import annotations

from pathlib import Path
from typing import Any


def algorithm_state(algorithm: Any, snapshot: bool = False) -> dict[str, Any]:
    """The algorithm's state dict; ``snapshot``: for an eval round (no file written for it)."""
    if snapshot and hasattr(algorithm, "snapshot_state"):
        return algorithm.snapshot_state()
    return algorithm.state_dict()


def settled(algorithm: Any, state: dict[str, Any]) -> dict[str, Any]:
    """``state`` (a trainer state) as a checkpoint file may hold it: every snapshot in it, its own
    and an eval round's in flight, made whole by ``algorithm.settle_state``."""
    settle = getattr(algorithm, "settle_state", None)
    if settle is None:
        return state
    out = dict(state, algorithm=settle(state["algorithm"]))
    flight = out.get("eval_in_flight")
    if flight is not None:
        out["eval_in_flight"] = dict(flight, state=settled(algorithm, flight["state"]))
    return out


def written(algorithm: Any, ckpt_dir: Path, path: Path, state: dict[str, Any]) -> None:
    """``state`` is on disk at ``path`` and old checkpoints are pruned: the algorithm may let go of
    what no checkpoint in ``ckpt_dir`` needs (SAC/TD3: replay chunks)."""
    done = getattr(algorithm, "checkpoint_written", None)
    if done is not None:
        done(ckpt_dir, path, state)
