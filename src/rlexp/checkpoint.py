"""Checkpoint files: atomic writes, ``weights_only`` loads, and RNG state capture.

A checkpoint is a plain dict of tensors and Python primitives, so ``torch.load(weights_only=True)``
reads it: ``format``, ``global_step``, ``policy`` (state dict, normaliser statistics included),
``algorithm`` (optimiser state, iteration), ``windows`` (recent episode returns/lengths), ``rng``
and ``config`` (the resolved experiment config as a plain dict).
"""

from __future__ import annotations

import logging
import os
import random
import re
from pathlib import Path
from typing import Any

import numpy as np
import torch

log = logging.getLogger(__name__)

FORMAT = "rlexp-checkpoint-v1"
_STEP_RE = re.compile(r"_step_(\d+)\.pt$")


def rng_state() -> dict[str, Any]:
    """The python, numpy and torch RNG states, as weights_only-loadable values."""
    np_state = np.random.get_state()
    return {
        "python": random.getstate(),
        "numpy": {
            "key": torch.from_numpy(np_state[1].astype(np.int64)),
            "pos": int(np_state[2]),
            "has_gauss": int(np_state[3]),
            "cached_gaussian": float(np_state[4]),
        },
        "torch": torch.get_rng_state(),
        "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else [],
    }


def set_rng_state(state: dict[str, Any]) -> None:
    """Restore what ``rng_state`` captured."""
    random.setstate(state["python"])
    np_s = state["numpy"]
    np.random.set_state(
        (
            "MT19937",
            np_s["key"].numpy().astype(np.uint32),
            np_s["pos"],
            np_s["has_gauss"],
            np_s["cached_gaussian"],
        )
    )
    torch.set_rng_state(state["torch"])
    if (
        state.get("cuda")
        and torch.cuda.is_available()
        and len(state["cuda"]) == torch.cuda.device_count()
    ):
        torch.cuda.set_rng_state_all(state["cuda"])


def to_storable(obj: Any) -> Any:
    """numpy arrays and scalars -> tensors / Python numbers, recursively, so that
    ``torch.load(weights_only=True)`` can read the result."""
    if isinstance(obj, np.ndarray):
        return torch.from_numpy(obj.copy())
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, dict):
        return {k: to_storable(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [to_storable(v) for v in obj]
    if isinstance(obj, tuple):
        return tuple(to_storable(v) for v in obj)
    return obj


def save_checkpoint(path: Path, state: dict[str, Any]) -> Path:
    """Write ``state`` to ``path`` atomically (temp file in the same dir, fsync, rename)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    with open(tmp, "wb") as f:
        torch.save(to_storable({"format": FORMAT, **state}), f)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    return path


def load_checkpoint(path: str | Path) -> dict[str, Any]:
    """Load a checkpoint file (``weights_only=True``), or the newest one in a run/checkpoint dir."""
    p = Path(path)
    try:
        if p.is_dir():
            p = latest_checkpoint(p)
        if not p.is_file():
            raise FileNotFoundError(f"checkpoint {str(p)!r} does not exist")
    except OSError as exc:  # a symlink loop, a path too long, no permission
        if isinstance(exc, FileNotFoundError) and exc.args and "does not exist" in str(exc):
            raise
        raise FileNotFoundError(
            f"checkpoint {str(p)!r} cannot be read: {exc.strerror or exc}"
        ) from None
    try:
        ckpt = torch.load(p, map_location="cpu", weights_only=True)
    except Exception as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise ValueError(
            f"checkpoint {str(p)!r} is unreadable (truncated, corrupt or not a weights-only "
            f"checkpoint): {first}"
        ) from None
    if not isinstance(ckpt, dict) or ckpt.get("format") != FORMAT:
        raise ValueError(f"{str(p)!r} is not an rlexp checkpoint (format {FORMAT!r})")
    step = ckpt.get("global_step")
    if not isinstance(step, int) or isinstance(step, bool) or step < 0:
        raise ValueError(f"checkpoint {str(p)!r} has global_step={step!r}; expected an int >= 0")
    for key in ("policy", "algorithm", "config"):
        if not isinstance(ckpt.get(key), dict):
            raise ValueError(
                f"checkpoint {str(p)!r} has no {key!r} section: not a complete rlexp checkpoint"
            )
    ckpt["path"] = str(p)
    return ckpt


def check_checkpoint_fits(ckpt: dict[str, Any], config: Any, policy: torch.nn.Module) -> None:
    """``ValueError`` naming the part that differs when ``ckpt`` cannot continue ``config``: another
    env (name, backend, native task) or policy shapes that do not match (``policy`` is loaded)."""
    saved_env = ckpt["config"].get("env") or {}
    env = config.env
    mine = {"env.name": env.name, "env.backend": env.backend}
    theirs = {"env.name": saved_env.get("name"), "env.backend": saved_env.get("backend")}
    if env.native is not None:
        mine["env.native.task"] = env.native.task
        theirs["env.native.task"] = (saved_env.get("native") or {}).get("task")
    for key, value in mine.items():
        if theirs[key] != value:
            raise ValueError(
                f"the checkpoint is of {key}={theirs[key]!r}, this run has {key}={value!r}"
            )
    try:
        policy.load_state_dict(ckpt["policy"])
    except (RuntimeError, KeyError, TypeError) as exc:
        lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
        detail = next(
            (ln for ln in lines if ln.startswith(("size mismatch", "Missing", "Unexpected"))),
            lines[-1] if lines else "",
        )
        raise ValueError(
            f"the checkpoint's policy does not fit this config's policy ({detail})"
        ) from None


def checkpoint_path(ckpt_dir: Path, exp_name: str, global_step: int) -> Path:
    return ckpt_dir / f"{exp_name}_step_{global_step:09d}.pt"


def step_checkpoints(directory: Path) -> list[Path]:
    """``*_step_N.pt`` files in ``directory`` (or its ``checkpoints/``), oldest step first."""
    candidates = list(directory.glob("*.pt")) + list((directory / "checkpoints").glob("*.pt"))
    stepped = sorted(
        (int(m.group(1)), str(c)) for c in candidates if (m := _STEP_RE.search(c.name))
    )
    return [Path(c) for _, c in stepped]


def latest_checkpoint(directory: Path) -> Path:
    """The checkpoint with the highest step in ``directory`` or its ``checkpoints/`` subdir."""
    stepped = step_checkpoints(directory)
    if not stepped:
        raise FileNotFoundError(f"no rlexp checkpoint (*_step_N.pt) in {str(directory)!r}")
    return stepped[-1]


def latest_good_checkpoint(directory: Path) -> dict[str, Any] | None:
    """The newest checkpoint in ``directory`` that loads; corrupt ones are reported and skipped."""
    for path in reversed(step_checkpoints(directory)):
        try:
            return load_checkpoint(path)
        except ValueError as exc:
            log.warning("%s; falling back to the previous checkpoint", exc)
    return None


def prune_checkpoints(directory: Path, keep_last: int) -> None:
    """Delete all but the newest ``keep_last`` step checkpoints (``keep_last <= 0``: keep all)."""
    for tmp in directory.glob(".*.tmp-*"):  # left by a write that a kill interrupted
        if not tmp.name.endswith(f"-{os.getpid()}"):
            tmp.unlink(missing_ok=True)
    if keep_last <= 0:
        return
    for path in step_checkpoints(directory)[:-keep_last]:
        path.unlink(missing_ok=True)
