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
import stat
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from rlexp.checkpoints.fields import FieldError, Use, check_fields, check_tensors_fit
from rlexp.checkpoints.scan import ScanError, scan
from rlexp.files.fsutil import atomic_write, step_file_name

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
    data = to_storable({"format": FORMAT, **state})

    def write(tmp: Path) -> None:
        with open(tmp, "wb") as f:
            torch.save(data, f)

    try:
        atomic_write(path, write)
    except BaseException as exc:  # a full disk, a signal: no half file left, the old one intact
        if isinstance(exc, RuntimeError) and not isinstance(exc, OSError):
            # torch.save reports a failed write (e.g. ENOSPC) as a RuntimeError from its writer
            raise OSError(f"writing {path} failed: {_write_failure(path, exc)}") from None
        raise
    return path


def _load_failure(path: Path, exc: BaseException) -> str:
    """Why a file does not load, in words that do not tell users to turn the safe loader off."""
    text = str(exc)
    if path.stat().st_size == 0:
        return "an empty file"
    if "Weights only load failed" in text:
        return (
            "not an rlexp checkpoint: loading it would run code from the file, which rlexp never "
            "does (weights_only)"
        )
    if "central directory" in text or isinstance(exc, EOFError):
        return "truncated or corrupt: the write that made it did not finish"
    first = text.strip().splitlines()[0] if text.strip() else type(exc).__name__
    return f"corrupt: {first[:200]}"


def _write_failure(path: Path, exc: BaseException) -> str:
    """torch's writer hides the errno (``file write failed``): name a full disk when it is one."""
    import shutil

    try:
        free = shutil.disk_usage(path.parent).free
    except OSError:
        return str(exc).splitlines()[0]
    if free < 1 << 20:
        return f"No space left on device ({free // 1024} kB free)"
    return f"{str(exc).splitlines()[0]} ({free // (1 << 20)} MB free)"


def load_checkpoint(path: str | Path, use: Use = "read") -> dict[str, Any]:
    """Load a checkpoint file (``weights_only=True``), or the newest one in a run/checkpoint dir.

    What the file declares is checked before torch materialises any of it
    (``rlexp.checkpoints.scan``), and every field rlexp uses after (``rlexp.checkpoints.fields``):
    ``use="rebuild"`` (eval, export) also needs the stored config's sections, ``"resume"`` the
    sections only a resume reads too. ``ValueError``: the file is unusable (a resume skips it like
    a corrupt one); ``FileNotFoundError``: there is none."""
    p = Path(path)
    try:
        if p.is_dir():
            p = latest_checkpoint(p)
    except OSError as exc:  # a symlink loop, a path too long, no permission
        if isinstance(exc, FileNotFoundError) and exc.args and "does not exist" in str(exc):
            raise
        raise FileNotFoundError(
            f"checkpoint {str(p)!r} cannot be read: {exc.strerror or exc}"
        ) from None
    return load_checkpoint_file(p, use)


def load_checkpoint_file(p: Path, use: Use = "read") -> dict[str, Any]:
    """``load_checkpoint`` of one file: a directory, a dangling symlink or a FIFO with a
    checkpoint's name is a ``ValueError`` (skipped like a corrupt file), never a hang or a
    traceback."""
    _check_regular(p)
    try:
        f = open(p, "rb")  # noqa: SIM115 (closed below; scanned and loaded through one handle)
    except OSError as exc:
        raise FileNotFoundError(
            f"checkpoint {str(p)!r} cannot be read: {exc.strerror or exc}"
        ) from None
    with f:
        try:
            size = os.fstat(f.fileno()).st_size
            scan(f, size)
        except ScanError as exc:
            raise ValueError(f"checkpoint {str(p)!r} is unreadable ({exc})") from None
        try:
            import warnings

            f.seek(0)
            with warnings.catch_warnings():  # "Detected pickle protocol N": not for users
                warnings.simplefilter("ignore", UserWarning)
                ckpt = torch.load(f, map_location="cpu", weights_only=True)
        except Exception as exc:
            raise ValueError(
                f"checkpoint {str(p)!r} is unreadable ({_load_failure(p, exc)})"
            ) from None
    if not isinstance(ckpt, dict) or ckpt.get("format") != FORMAT:
        raise ValueError(f"{str(p)!r} is not an rlexp checkpoint (format {FORMAT!r})")
    for key in ("policy", "algorithm", "config"):
        if not isinstance(ckpt.get(key), dict):
            raise ValueError(
                f"checkpoint {str(p)!r} has no {key!r} section: not a complete rlexp checkpoint"
            )
    named = _STEP_RE.search(p.name)
    try:
        check_fields(ckpt, int(named.group(1)) if named else None, use)
    except FieldError as exc:
        raise ValueError(f"checkpoint {str(p)!r} is unusable: {exc}") from None
    ckpt["path"] = str(p)
    return ckpt


def _check_regular(p: Path) -> None:
    """FileNotFoundError when nothing is at ``p``; ValueError when what is there is not a regular
    file (or a symlink to one): opening a FIFO would block for ever, a directory is no checkpoint."""
    try:
        mode = p.stat().st_mode
    except FileNotFoundError:
        if not os.path.lexists(p):
            raise FileNotFoundError(f"checkpoint {str(p)!r} does not exist") from None
        raise ValueError(
            f"checkpoint {str(p)!r} is a dangling symlink (to {os.readlink(p)!r}), not a file"
        ) from None
    except OSError as exc:  # a symlink loop, a path too long, no permission
        raise FileNotFoundError(
            f"checkpoint {str(p)!r} cannot be read: {exc.strerror or exc}"
        ) from None
    if not stat.S_ISREG(mode):
        kind = (
            "a directory" if stat.S_ISDIR(mode) else "not a regular file (a FIFO, socket or device)"
        )
        raise ValueError(f"checkpoint {str(p)!r} is {kind}, not a checkpoint file")


def check_checkpoint_fits(ckpt: dict[str, Any], config: Any, policy: torch.nn.Module) -> None:
    """``ValueError`` naming the part that differs when ``ckpt`` cannot continue ``config``: another
    env (name, backend, native task, number of envs), policy shapes (``policy`` is loaded with the
    checkpoint's weights), optimiser state shapes or counters."""
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
    saved_n = (ckpt["config"].get("env") or {}).get("num_envs")
    if saved_n is not None and "train" in (ckpt.get("envs") or {}) and saved_n != env.num_envs:
        raise ValueError(
            f"the checkpoint holds the state of env.num_envs={saved_n} training envs, this run "
            f"has env.num_envs={env.num_envs}"
        )
    check_tensors_fit(ckpt, policy)  # dtype and shape, before load_state_dict casts or copies
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
    _check_optimizer_state(ckpt.get("algorithm") or {}, policy)


def check_policy_before_building(
    ckpt: dict[str, Any], build: Callable[[], torch.nn.Module]
) -> None:
    """Build the policy of the checkpoint's own config on the meta device (no memory) and compare
    its tensors with the checkpoint's: a stored config declaring 65536-wide layers next to small
    weights is refused before eval or export allocates gigabytes for the real policy."""
    try:
        with torch.device("meta"):
            policy = build()
    except Exception:  # a builder that needs real data: the real build checks the same, later
        return
    check_tensors_fit(ckpt, policy)
    missing = [key for key in policy.state_dict() if key not in ckpt["policy"]]
    if missing:
        shown = ", ".join(missing[:3]) + (
            f" and {len(missing) - 3} more" if len(missing) > 3 else ""
        )
        raise ValueError(
            f"the checkpoint's policy does not fit this config's policy (Missing key(s): {shown})"
        )


def checkpoint_path(ckpt_dir: Path, exp_name: str, global_step: int) -> Path:
    return ckpt_dir / step_file_name(exp_name, global_step)


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


#: Where ``latest_good_checkpoint(move_aside=True)`` puts checkpoints that do not load.
CORRUPT_DIR = "corrupt"


def latest_good_checkpoint(directory: Path, move_aside: bool = False) -> dict[str, Any] | None:
    """The newest checkpoint in ``directory`` that loads, for a resume; corrupt ones are reported
    and skipped, and with ``move_aside`` (a run resuming) moved into ``corrupt/``, where pruning
    never counts them and no later resume trips over them again."""
    return _newest_loadable(directory, "resume", move_aside)


def _newest_loadable(directory: Path, use: Use, move_aside: bool = False) -> dict[str, Any] | None:
    for path in reversed(step_checkpoints(directory)):
        try:
            ckpt = load_checkpoint_file(path, use)
            if use == "resume":  # SAC / TD3: a checkpoint whose replay rows are gone is unusable
                from rlexp.algorithms.replay_files import locate_chunks

                locate_chunks(ckpt, path)
            return ckpt
        except (ValueError, OSError) as exc:  # OSError: unreadable, or pruned meanwhile
            dest = _move_aside(path) if move_aside and os.path.lexists(path) else None
            if dest is not None:
                log.warning("%s; moved to %s; falling back to the previous checkpoint", exc, dest)
            else:
                log.warning("skipped %s; falling back to the previous checkpoint", exc)
    return None


def select_checkpoint(path: str | Path, which: str | None = None) -> tuple[dict[str, Any], str]:
    """The one rule by which ``rlexp eval`` and ``rlexp export`` pick a checkpoint, and why (the
    commands print it). ``path`` a file: that file. ``path`` a run dir (or its ``checkpoints/``):
    ``which`` ``last`` (the default: the run's final policy, as rl-zoo's ``enjoy`` loads it) is the
    newest step checkpoint that loads, newer unreadable ones named and skipped; ``best`` is
    ``best.pt`` (the best evaluation, chosen on the eval seed's episodes: an optimistic pick);
    anything else is a checkpoint's path, as given or inside the run's ``checkpoints/``."""
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"{str(p)!r} does not exist (give a run dir or a checkpoint file)")
    if not p.is_dir():
        if which is not None:
            raise ValueError(
                f"--checkpoint {which} picks a checkpoint of a run dir; {str(p)!r} is a file: "
                "leave --checkpoint out"
            )
        return load_checkpoint(p, "rebuild"), "as given"
    which = which or "last"
    if which == "best":
        best = next(
            (b for b in (p / "checkpoints" / "best.pt", p / "best.pt") if b.is_file()), None
        )
        if best is None:
            raise FileNotFoundError(
                f"no best.pt in {str(p)!r} or its checkpoints/ (the run never evaluated): "
                "use --checkpoint last"
            )
        return load_checkpoint_file(best, "rebuild"), "--checkpoint best: the best evaluation"
    if which == "last":
        found = len(step_checkpoints(p))
        if not found:
            raise FileNotFoundError(
                f"no rlexp checkpoint (*_step_N.pt) in {str(p)!r} or its checkpoints/"
            )
        ckpt = _newest_loadable(p, "rebuild")
        if ckpt is None:
            raise ValueError(
                f"none of the {found} checkpoints in {str(p)!r} can be read (each skipped above)"
            )
        return ckpt, "the last checkpoint"
    named = Path(which)
    for candidate in (named, p / named, p / "checkpoints" / named):
        if candidate.is_file():
            return load_checkpoint_file(candidate, "rebuild"), "--checkpoint PATH"
    raise FileNotFoundError(
        f"--checkpoint {which!r}: no such file, nor in {str(p)!r} or its checkpoints/ "
        f"(best, last or a checkpoint's path)"
    )


def _move_aside(path: Path) -> Path | None:
    """``path`` (a file, a directory or a symlink) into ``corrupt/``; None if it cannot be moved."""
    dest_dir = path.parent / CORRUPT_DIR
    dest, n = dest_dir / path.name, 1
    while os.path.lexists(dest):
        dest, n = dest_dir / f"{path.name}.{n}", n + 1
    try:
        dest_dir.mkdir(exist_ok=True)
        os.replace(path, dest)
    except OSError as exc:
        log.warning("cannot move %s aside (%s)", path, exc.strerror or exc)
        return None
    return dest


def prune_checkpoints(directory: Path, keep_last: int, newest: Path | None = None) -> list[Path]:
    """Delete step checkpoints beyond ``keep_last`` (``<= 0``: keep all) and temporary files that a
    killed write left; returns the deleted checkpoints. ``newest`` (the checkpoint just written) is
    always kept and counted first, whatever other files' steps say."""
    for tmp in directory.glob(".*.tmp-*"):  # left by a write that a kill interrupted
        if not tmp.name.endswith(f"-{os.getpid()}"):
            tmp.unlink(missing_ok=True)
    if keep_last <= 0:
        return []
    # only files count: a directory or dangling symlink with a checkpoint's name is no checkpoint
    others = [p for p in reversed(step_checkpoints(directory)) if p != newest and p.is_file()]
    ranked = ([newest] if newest is not None else []) + others
    doomed = ranked[keep_last:]
    for path in doomed:
        path.unlink(missing_ok=True)
    return doomed


def _check_optimizer_state(algorithm: dict[str, Any], policy: torch.nn.Module) -> None:
    """The optimiser state must have one entry of the right shape per trainable parameter (torch's
    own ``load_state_dict`` checks the count, not the shapes, and would carry a wrong-shaped state
    into every later checkpoint)."""
    iteration = algorithm.get("iteration")
    if not isinstance(iteration, int) or isinstance(iteration, bool) or iteration < 0:
        raise ValueError(
            f"the checkpoint has algorithm.iteration={iteration!r}; expected an int >= 0"
        )
    if "optimizers" in algorithm:  # SAC / TD3: one per network, their shapes checked on loading
        opts = algorithm["optimizers"]
        if not isinstance(opts, dict) or not all(
            isinstance(o, dict) and isinstance(o.get("param_groups"), list) for o in opts.values()
        ):
            raise ValueError("the checkpoint has no optimiser state")
        return
    opt = algorithm.get("optimizer")
    if not isinstance(opt, dict) or not isinstance(opt.get("param_groups"), list):
        raise ValueError("the checkpoint has no optimiser state")
    named = [(n, p) for n, p in policy.named_parameters() if p.requires_grad]
    ids = [i for group in opt["param_groups"] for i in group.get("params", [])]
    if len(ids) != len(named):
        raise ValueError(
            f"the checkpoint's optimiser holds {len(ids)} parameters, this policy has {len(named)}"
        )
    state = opt.get("state") or {}
    for i, (name, param) in zip(ids, named, strict=True):
        for key, value in (state.get(i) or {}).items():
            if key == "step" or not isinstance(value, torch.Tensor):
                continue
            if value.shape != param.shape:
                raise ValueError(
                    f"the checkpoint's optimiser state {key} of {name} has shape "
                    f"{tuple(value.shape)}, the parameter has {tuple(param.shape)}"
                )
            if value.dtype != param.dtype:  # torch's load_state_dict would cast it silently
                raise ValueError(
                    f"the checkpoint's optimiser state {key} of {name} is {value.dtype}, the "
                    f"parameter is {param.dtype}"
                )
