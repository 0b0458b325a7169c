"""Where a run's own env module came from (``env.name=module:EnvId``, Gymnasium's syntax), so that
``rlexp eval RUN`` and ``rlexp export RUN`` work from a shell without the training shell's
``PYTHONPATH``.

The training run records the folder its module was imported from (``provenance.json``,
``env_source``). Evaluating or exporting a checkpoint of that run dir, a module that is not
importable here is looked for in that folder only: the folder goes at the END of ``sys.path`` (an
installed package of the same name always wins), and only when it holds the module. Exported files
never extend ``sys.path``: their metadata may come from anywhere. Otherwise: one line naming the
module, where the run found it, and how to make it importable.
"""

from __future__ import annotations

import importlib
import importlib.util
import logging
import sys
from pathlib import Path
from typing import Any

from rlexp.config.validate import ConfigError

log = logging.getLogger(__name__)


class EnvModuleError(ConfigError):
    """The module of ``env.name=module:EnvId`` is not importable here (exit 2)."""


def env_module(env_name: Any) -> str | None:
    """The ``module`` of ``module:EnvId``; None for a plain id."""
    if not isinstance(env_name, str) or ":" not in env_name:
        return None
    return env_name.split(":", 1)[0] or None


def env_name_in(config: Any) -> Any:
    """``env.name`` of a stored config dict (None where it has none)."""
    env = config.get("env") if isinstance(config, dict) else None
    return env.get("name") if isinstance(env, dict) else None


def _importable(top: str) -> bool:
    try:
        return importlib.util.find_spec(top) is not None  # (finds, does not run, the module)
    except (ImportError, ValueError):
        return False


def locate(env_name: Any) -> dict[str, str] | None:
    """``{"module", "path"}``: the ``sys.path`` folder that ``module:EnvId``'s top-level package
    comes from (as a training run records it); None for a plain id or an unfindable module."""
    module = env_module(env_name)
    if module is None:
        return None
    top = module.split(".")[0]
    try:
        spec = importlib.util.find_spec(top)
    except (ImportError, ValueError):
        return None
    if spec is None:
        return None
    if spec.origin and spec.origin not in ("built-in", "frozen", "namespace"):
        origin = Path(spec.origin).resolve()
        root = origin.parent.parent if origin.name.startswith("__init__.") else origin.parent
    elif spec.submodule_search_locations:  # a namespace package: its first folder
        root = Path(list(spec.submodule_search_locations)[0]).resolve().parent
    else:
        return None
    return {"module": module, "path": str(root)}


def _holds(folder: Path, top: str) -> bool:
    return (folder / f"{top}.py").is_file() or (folder / top).is_dir()


def recorded_source(run_dir: Path) -> dict[str, Any] | None:
    """The ``env_source`` a run dir's ``provenance.json`` holds (None: none, or unreadable)."""
    from rlexp.files.safe_read import load_json

    try:
        info = load_json(run_dir / "provenance.json", limit=1 << 20)
    except (OSError, ValueError):
        return None
    source = info.get("env_source") if isinstance(info, dict) else None
    ok = isinstance(source, dict) and all(
        isinstance(source.get(k), str) for k in ("module", "path")
    )
    return source if ok else None


def run_dir_of(checkpoint: str | Path) -> Path:
    """The run dir of a checkpoint file (``RUN/checkpoints/x.pt``; elsewhere: its folder)."""
    parent = Path(checkpoint).resolve().parent
    return parent.parent if parent.name == "checkpoints" else parent


def ensure_env_importable(env_name: Any, run_dir: Path | None) -> None:
    """Make ``env.name=module:EnvId``'s module importable (``rlexp eval`` / ``export``), or
    ``EnvModuleError`` in one line. ``run_dir``: the user's own run (its recorded folder may be
    added to the end of ``sys.path``); None (an exported file): nothing is added. A module that is
    found but fails as it is imported is check_gym_id's one line, when the env is built."""
    module = env_module(env_name)
    if module is None:
        return
    top = module.split(".")[0]
    if _importable(top):
        return
    source = recorded_source(run_dir) if run_dir is not None else None
    found = None
    if source is not None and source["module"].split(".")[0] == top:
        found = Path(source["path"])
        if found.is_absolute() and found.is_dir() and _holds(found, top):
            sys.path.append(str(found))
            importlib.invalidate_caches()
            log.info("[env] module %r imported from %s (where the run found it)", module, found)
            return
    gone = f"the run imported it from {found}, which no longer holds it; " if found else ""
    raise EnvModuleError(
        f"env.name={env_name!r} needs module {module!r}, which is not importable here "
        f"({gone}run with PYTHONPATH=<the folder that holds {top}> or pip install the package "
        "that holds it)"
    )
