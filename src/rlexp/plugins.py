"""Installed packages extend rlexp through the ``rlexp.plugins`` entry-point group.

A package declares one entry point in its ``pyproject.toml``::

    [project.entry-points."rlexp.plugins"]
    my_lab = "my_lab.rlexp_plugin:register"

``load_plugins()`` runs once per process at start-up (``rlexp train`` / ``python train.py``,
``rlexp eval``, and every training job, so sweep workers and SLURM jobs have them too): it imports
each entry point and, when the entry point names a function, calls it without arguments. A plugin
registers what it adds in rlexp's registries: native tasks (``rlexp.envs.native.TASKS``), reward,
observation, event and action terms (``REWARDS``, ``OBSERVATIONS``, ``EVENTS``, ``ACTIONS``), event
functions (``rlexp.events.register_event``, ``allow_event_module``), batched torch env factories
(``rlexp.envs.batched.register_env_factory``, ``allow_env_module``). An installed package is trusted
code; a config file still names only what is registered, and cannot import arbitrary modules.
"""

from __future__ import annotations

import logging
from importlib import metadata

from rlexp.config.validate import ConfigError

log = logging.getLogger(__name__)

#: The entry-point group rlexp loads.
GROUP = "rlexp.plugins"

#: name -> "distribution version" of each plugin loaded in this process (for provenance).
LOADED: dict[str, str] = {}
_done = False


class PluginError(ConfigError):
    """A plugin that failed to load; the message names the plugin, its entry point and package."""


def _distribution(ep: metadata.EntryPoint) -> str:
    dist = getattr(ep, "dist", None)
    return f"{dist.metadata['Name']} {dist.version}" if dist is not None else "unknown package"


def _one_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return f"{type(exc).__name__}: {text.splitlines()[0]}" if text else type(exc).__name__


def load_plugins() -> dict[str, str]:
    """Import and run every ``rlexp.plugins`` entry point, once per process; ``PluginError``
    naming the first one that fails (a half-loaded set of plugins would fail later, less clearly)."""
    global _done
    if _done:
        return LOADED
    _done = True  # a failure is reported once; the process is expected to stop
    found = sorted(metadata.entry_points(group=GROUP), key=lambda e: e.name)
    if found:
        from rlexp.envs.native.render import GL_FIX, gl_problem

        problem = gl_problem(rendering=False)  # before a plugin imports MuJoCo, which would abort
        if problem:
            raise ConfigError(f"{problem}; {GL_FIX}")
    for ep in found:
        where = f"rlexp plugin {ep.name!r} ({ep.value}, from {_distribution(ep)})"
        try:
            obj = ep.load()
            if callable(obj):
                obj()
        except Exception as exc:
            raise PluginError(
                f"{where} failed to load: {_one_line(exc)}; fix the package or uninstall it"
            ) from exc
        LOADED[ep.name] = _distribution(ep)
        log.debug("loaded %s", where)
    return LOADED
