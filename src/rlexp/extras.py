"""Optional parts of rlexp and the pip extra that installs each (``pip install -e '.[wandb]'`` in a
checkout; the messages name the extra's packages, ``pip install 'wandb>=0.17,<0.32'``).

The core install runs ``rlexp train`` on one machine (TensorBoard and JSONL logs, local sweeps).
A missing extra is one line naming it, before a run writes anything: ``check_config`` for what a
config turns on, ``hint`` for the errors Hydra or an import give when one is missing.
"""

from __future__ import annotations

import importlib.util
import re
import shlex
from typing import TYPE_CHECKING

from rlexp.config.validate import ConfigError

if TYPE_CHECKING:
    from rlexp.config.schema import RootConfig

#: extra -> the modules it provides (what rlexp imports).
EXTRAS: dict[str, tuple[str, ...]] = {
    "wandb": ("wandb",),
    "slurm": ("submitit", "hydra_plugins.hydra_submitit_launcher"),
    "optuna": ("optuna",),
    "video": ("imageio", "imageio_ffmpeg"),
    "report": ("scipy", "matplotlib"),
    "envpool": ("envpool",),
    "box2d": ("Box2D",),  # Gymnasium's Box2D envs: LunarLander, BipedalWalker, CarRacing
}

#: Hydra config groups that only a plugin package of an extra provides (rlexp ships
#: hydra/sweeper/optuna itself: its sweeper names the optuna extra when optuna is missing).
HYDRA_CONFIGS: dict[str, str] = {
    "hydra/launcher/submitit": "slurm",
}


#: Installed packages that break a config rlexp ships: module -> (the config group it clashes in,
#: the fix). hydra-optuna-sweeper registers hydra/sweeper/optuna and hydra/sweeper/sampler/* in
#: Hydra's ConfigStore, and Hydra then checks rlexp's files of those names against its schemas.
CONFLICTS: dict[str, tuple[str, str]] = {
    "hydra_plugins.hydra_optuna_sweeper": (
        "hydra/sweeper",
        "hydra-optuna-sweeper is installed and clashes with rlexp's own hydra/sweeper=optuna "
        "(Hydra checks rlexp's files against the plugin's schemas): pip uninstall -y "
        "hydra-optuna-sweeper (rlexp's optuna extra no longer uses it; docs/sweeps.md, Optuna)",
    ),
}


class MissingExtra(ConfigError):
    """An optional part that is not installed; the message says which extra installs it."""


def _installed(module: str) -> bool:
    try:
        return importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):  # a parent package missing, or a broken one
        return False


def missing(extra: str, modules: tuple[str, ...] | None = None) -> str | None:
    """The first module of ``extra`` (or of ``modules``) that is not installed, else None."""
    for module in modules or EXTRAS[extra]:
        if not _installed(module):
            return module
    return None


def extra_requirements(extra: str) -> list[str]:
    """The requirements ``extra`` adds, as rlexp's installed metadata lists them (pyproject.toml's
    ranges); [] when rlexp's metadata is not there (run from a source tree without an install)."""
    from importlib import metadata

    try:
        requires = metadata.requires("rlexp") or []
    except metadata.PackageNotFoundError:
        return []
    found = []
    for line in requires:
        spec, _, marker = line.partition(";")
        if re.search(rf"""extra\s*==\s*["']{re.escape(extra)}["']""", marker):
            found.append(spec.strip())
    return found


def install_hint(extra: str) -> str:
    """The command that installs ``extra``'s packages. rlexp is not on a package index, so not
    ``pip install 'rlexp[wandb]'`` (it fails for everyone): the extra's own requirements, which
    install wherever rlexp came from (a clone, a wheel, a git URL)."""
    requirements = extra_requirements(extra)
    if requirements and not any(r.startswith("rlexp") for r in requirements):
        return "pip install " + " ".join(shlex.quote(r) for r in requirements)
    return f"pip install -e '.[{extra}]' in rlexp's checkout"


def require(extra: str, what: str, modules: tuple[str, ...] | None = None) -> None:
    """``MissingExtra`` when ``what`` cannot run because ``extra`` is not installed."""
    module = missing(extra, modules)
    if module is not None:
        raise MissingExtra(
            f"{what} needs rlexp's optional '{extra}' extra ({module} is not installed): "
            f"{install_hint(extra)}"
        )


def check_config(config: RootConfig) -> None:
    """The extras a config turns on are installed (W&B logging, mp4 videos, EnvPool)."""
    if config.env.backend == "envpool":
        require("envpool", "env.backend=envpool")
    if config.logger.wandb.enabled:
        require("wandb", "logger.wandb.enabled=true (logger=wandb)")
    for manager in ("train", "eval"):
        for name, event in getattr(config.events, manager).items():
            if event.func in ("record_video", "rlexp.events.builtin.RecordVideo"):
                require("video", f"events.{manager}.{name} (record_video)")


def hint(message: str) -> str:
    """``message`` plus the extra to install, when it says that a module or a Hydra config that
    an uninstalled extra provides is missing, or the package to remove, when it is about a
    config group an installed package clashes in (:data:`CONFLICTS`)."""
    wanted = set()
    for module in re.findall(r"No module named '([\w.]+)'", message):
        wanted |= {e for e, mods in EXTRAS.items() if any(module.startswith(m) for m in mods)}
    for config in re.findall(r"Could not (?:find|load) '([\w/]+)'", message):
        wanted |= {e for prefix, e in HYDRA_CONFIGS.items() if config.startswith(prefix)}
    wanted = {e for e in wanted if missing(e) is not None and install_hint(e) not in message}
    fixes = [f"rlexp's '{e}' extra is not installed: {install_hint(e)}" for e in sorted(wanted)]
    fixes += [
        fix
        for module, (group, fix) in CONFLICTS.items()
        if f"'{group}/" in message and fix not in message and _installed(module)
    ]
    return f"{message} ({'; '.join(fixes)})" if fixes else message
