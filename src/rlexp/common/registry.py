"""Looking up a function a config names: a registered name, or a dotted path inside an allowlist of
modules (so a config file cannot import arbitrary code). Events, hooks, the batched envs' factories
and the Optuna sweeper's ``custom_search_space`` all resolve through :func:`reach`; Gymnasium's
``module:EnvId`` modules through :func:`check_module_name` (docs/envs.md, "Security: what a name
may import").

The rule a name must pass, checked before anything past the module itself is touched:

- every part of the module path and the attribute is a public identifier (no ``_x``, no dunder);
- the module is never one of Python's standard library (``os``, ``subprocess``, ``this``), and is
  under an allowed prefix at a ``.`` boundary (``rlexp.envs.`` admits ``rlexp.envs.batched``, never
  ``rlexp.envsx`` or ``rlexp_evil``); a name the user's own command line gives for a module it
  imports (Gymnasium's ``module:EnvId``, ``custom_search_space``) has no allowlist;
- the attribute is one name of the module's own namespace (read from its ``__dict__``: no property,
  no module ``__getattr__`` runs), and the object is a function or class **defined** under an
  allowed prefix (its own ``__module__``): an allowed module's imports (``os``, ``subprocess``,
  ``importlib``, builtins) are never reached through it.
"""

from __future__ import annotations

import difflib
import importlib
import inspect
import re
import sys
from collections.abc import Callable, Mapping, Sequence
from typing import Any

_IDENT = re.compile(r"[A-Za-z][A-Za-z0-9_]*\Z")
#: A string Gymnasium (``gym.make``) reads as ``module:EnvId``, importing ``module`` first.
_MODULE_ID = re.compile(r"([A-Za-z_]\w*(?:\.\w+)*):([A-Za-z][\w.-]*(?:/[\w.-]+)?)\Z")


def choices_hint(value: str, choices: Sequence[str]) -> str:
    """``; choose from [...]`` and the closest choice, for an error message."""
    close = difflib.get_close_matches(value, list(choices), n=1)
    return f"; choose from {sorted(choices)}" + (f"; did you mean {close[0]!r}?" if close else "")


def under(module: str, prefixes: Sequence[str]) -> bool:
    """``module`` is inside one of ``prefixes`` at a ``.`` boundary (a prefix ``torchrl.envs`` or
    ``torchrl.envs.`` admits ``torchrl.envs`` and ``torchrl.envs.libs``, not ``torchrl.envsx``)."""
    return any((module + ".").startswith(p if p.endswith(".") else p + ".") for p in prefixes)


def is_stdlib(module: str) -> bool:
    """``module`` belongs to Python's standard library (``os.path``, ``subprocess``, ``this``)."""
    return module.split(".")[0] in sys.stdlib_module_names


def module_of(value: Any) -> str | None:
    """The module Gymnasium would import for ``value`` (``pkg.mod:Env-v0`` -> ``pkg.mod``)."""
    found = _MODULE_ID.match(value) if isinstance(value, str) else None
    return found.group(1) if found else None


def strings_in(node: Any, key: str = "") -> list[tuple[str, str]]:
    """Every string under ``node`` (nested mappings and lists) with its dotted key."""
    if isinstance(node, str):
        return [(key, node)]
    if isinstance(node, Mapping) or hasattr(node, "items"):
        items = list(node.items())
    elif isinstance(node, Sequence) and not isinstance(node, bytes):  # list, tuple, ListConfig
        items = list(enumerate(node))
    else:
        return []
    found: list[tuple[str, str]] = []
    for k, v in items:
        found += strings_in(v, f"{key}.{k}" if key else str(k))
    return found


def check_module_name(module: str, where: str, allowed: Sequence[str] | None) -> None:
    """A ValueError of one line, before anything is imported, unless ``module`` is a dotted path of
    public identifiers, not of the standard library, under ``allowed`` (None: any such module)."""
    parts = module.split(".")
    bad = next((p for p in parts if not _IDENT.match(p)), None)
    if bad is not None:
        raise ValueError(
            f"{where}: module {module!r} has the part {bad!r}; a name may only use public "
            "identifiers (no '_private' or '__dunder__' parts, no empty parts)"
        )
    if is_stdlib(module):  # os, subprocess, importlib, builtins, this, antigravity...
        raise ValueError(
            f"{where}: {module!r} is a module of Python's standard library, which registers no "
            "env and defines no rlexp callable; name your own package's module"
        )
    if allowed is not None and not under(module, allowed):
        raise ValueError(f"{where}: module {module!r} is not allowed (allowed: {list(allowed)})")


def reach(module: str, attr: str, where: str, allowed: Sequence[str] | None) -> Callable[..., Any]:
    """The function or class ``attr`` defined in ``module`` (or a module of ``allowed``); a
    ValueError of one line naming ``where`` otherwise. Nothing outside ``allowed`` is imported and
    nothing is called before the object passes (module docstring)."""
    check_module_name(module, where, allowed)
    if not _IDENT.match(attr):
        what = "walks attributes" if "." in attr else "is not a public name"
        raise ValueError(
            f"{where}: {attr!r} {what}; name one public function or class defined in the module "
            "itself (module:callable), never an attribute of it such as a module it imports"
        )
    try:
        mod = importlib.import_module(module)
    except Exception as exc:  # ModuleNotFoundError, or the module's own failure
        text = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
        raise ValueError(
            f"{where}: module {module!r} could not be imported ({type(exc).__name__}: {text}); "
            "install the package (pip install -e PATH) or fix PYTHONPATH"
        ) from None
    if getattr(mod, "__name__", None) != module:  # an alias put into sys.modules
        raise ValueError(f"{where}: {module!r} is an alias of module {mod.__name__!r}, refused")
    obj = vars(mod).get(attr)
    if obj is None:
        public = [n for n in vars(mod) if not n.startswith("_")]
        close = difflib.get_close_matches(attr, public, n=1)
        hint = f"; did you mean {close[0]!r}?" if close else ""
        raise ValueError(f"{where}: module {module!r} has no attribute {attr!r}{hint}")
    if not (inspect.isfunction(obj) or inspect.isclass(obj)):
        kind = "a module" if inspect.ismodule(obj) else f"a {type(obj).__name__}"
        raise ValueError(
            f"{where}: {module}.{attr} is {kind}, not a callable rlexp calls: name a function "
            "or class defined in the module itself"
        )
    home = str(getattr(obj, "__module__", None) or "")
    inside = under(home, allowed) if allowed is not None else under(home, [module])
    if not inside:
        raise ValueError(
            f"{where}: {module}.{attr} is defined in module {home!r}, outside "
            f"{list(allowed) if allowed is not None else [module]} (a name reaches only what an "
            "allowed module defines, never what it imports)"
        )
    return obj


def resolve(
    name: str,
    where: str,
    registry: Mapping[str, Callable[..., Any]],
    allowed: Sequence[str],
    what: str,
    how_to_register: str,
) -> Callable[..., Any]:
    """``registry[name]``, or the object at dotted path ``name`` inside a module of ``allowed``
    (:func:`reach`); a ValueError naming ``<where>.func`` otherwise (``what``: "event function",
    "hook")."""
    if name in registry:
        return registry[name]
    if "." in name:
        module, _, attr = name.rpartition(".")
        key = f"{where}.func={name!r}"
        if not under(module, allowed):
            raise ValueError(
                f"{key}: dotted paths must be inside {list(allowed)} "
                f"(a config may not import arbitrary code); {how_to_register}"
            )
        return reach(module, attr, key, allowed)
    raise ValueError(
        f"{where}.func={name!r} is not a known {what}" + choices_hint(name, list(registry))
    )
