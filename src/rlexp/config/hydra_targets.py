"""What Hydra itself would call from a config, checked before it does (docs/envs.md, "Security:
what a name may import"): the ``_target_`` of each ``hydra.callbacks`` entry (instantiated at
start-up) and the ``class`` / ``()`` factories and ``ext://`` objects of ``hydra.job_logging`` /
``hydra.hydra_logging`` (``logging.config.dictConfig`` builds them). A config could otherwise name
``shutil.copyfile`` as a callback or ``tarfile.TarFile`` as a log handler, and Hydra would call it
with the config's arguments before the run starts.
"""

from __future__ import annotations

import logging
import re
from typing import Any

from rlexp.common.registry import reach, under

#: Where a ``hydra.callbacks.<name>._target_`` may point: Hydra's own and plugins' callbacks, rlexp's.
CALLBACK_MODULES = ("hydra.", "hydra_plugins.", "rlexp.")
#: Modules whose classes a logging config may name: the standard library's logging, Hydra's
#: colorlog plugin, Hydra, rlexp.
LOGGING_MODULES = ("logging", "logging.handlers")
LOGGING_PREFIXES = ("colorlog.", "hydra.", "hydra_plugins.", "rlexp.")
#: What such a class must be.
LOGGING_BASES = (logging.Handler, logging.Formatter, logging.Filter)
_IDENT = re.compile(r"[A-Za-z][A-Za-z0-9_]*\Z")


def check_hydra_targets(hydra: Any) -> None:
    """A ValueError of one line naming the key when ``hydra`` (the composed ``hydra`` node, as a
    mapping) names something Hydra would call that is not a callback or logging class."""
    if hydra is None:
        return
    for name, node in (hydra.get("callbacks") or {}).items():
        _check_callback(f"hydra.callbacks.{name}", node)
    for part in ("job_logging", "hydra_logging"):
        _check_logging(f"hydra.{part}", hydra.get(part))


def _check_callback(key: str, node: Any) -> None:
    from hydra.experimental.callback import Callback

    target = str(node.get("_target_", "")) if hasattr(node, "get") else ""
    where = f"{key}._target_={target!r}"
    module, _, attr = target.rpartition(".")
    try:
        found = reach(module, attr, where, CALLBACK_MODULES)
    except ValueError as exc:
        raise ValueError(
            f"{exc} (a config may not import arbitrary code: a callback is a Hydra Callback class "
            f"under {list(CALLBACK_MODULES)}; install your own in hydra_plugins)"
        ) from None
    if not (isinstance(found, type) and issubclass(found, Callback)):
        raise ValueError(f"{where}: not a hydra.experimental.callback.Callback class")


def _check_logging(key: str, node: Any) -> None:
    if hasattr(node, "items"):
        for k, v in node.items():
            if str(k) in ("class", "()"):
                _check_logging_class(f"{key}.{k}", v)
            else:
                _check_logging(f"{key}.{k}", v)
    elif isinstance(node, list | tuple) or type(node).__name__ == "ListConfig":
        for i, v in enumerate(node):
            _check_logging(f"{key}[{i}]", v)
    elif isinstance(node, str) and node.startswith("ext://"):
        if not re.fullmatch(r"ext://sys\.(stdout|stderr)", node):
            raise ValueError(
                f"{key}={node!r}: a logging config may name only ext://sys.stdout or "
                "ext://sys.stderr (ext:// would import any module)"
            )


def _check_logging_class(key: str, value: Any) -> None:
    import importlib

    target = str(value)
    module, _, attr = target.rpartition(".")
    parts = [*module.split("."), attr]
    allowed = module in LOGGING_MODULES or under(module, LOGGING_PREFIXES)
    if not allowed or not all(_IDENT.match(p) for p in parts):
        raise ValueError(
            f"{key}={target!r}: a logging config names a handler, formatter or filter class of "
            f"{[*LOGGING_MODULES, *LOGGING_PREFIXES]} (a config may not import arbitrary code)"
        )
    try:
        found = vars(importlib.import_module(module)).get(attr)
    except ImportError as exc:
        raise ValueError(
            f"{key}={target!r}: module {module!r} could not be imported ({exc})"
        ) from None
    if not (isinstance(found, type) and issubclass(found, LOGGING_BASES)):
        raise ValueError(f"{key}={target!r}: not a logging Handler, Formatter or Filter class")
