"""Where configs come from: rlexp's own ``conf/`` (shipped in the package) and the user's.

``CONF_DIR`` is rlexp's primary config dir: ``rlexp/conf`` inside an installed wheel (the build
copies the repository's top-level ``conf/`` there, see setup.py), the repository's ``conf/`` in an
editable checkout. A user's project adds one config dir of its own to Hydra's search path, after
rlexp's: Hydra's ``--config-dir DIR`` (``-cd DIR``), or else the ``conf/`` of the working directory
when there is one. Its files add options to rlexp's groups (``experiment/``, ``env/``, ``events/``,
``sweep/``...); a file at the same path as one of rlexp's is shadowed by rlexp's (Hydra takes the
first match), so a project names its options differently. docs/user_project.md.
"""

from __future__ import annotations

import contextlib
import io
import logging
import os
from collections.abc import Iterator, Sequence
from importlib import resources
from pathlib import Path

log = logging.getLogger(__name__)


def find_conf_dir() -> Path:
    """rlexp's ``conf/``: the copy inside the installed package, else the checkout's top level."""
    packaged = Path(str(resources.files("rlexp") / "conf"))
    if (packaged / "config.yaml").is_file():
        return packaged
    checkout = Path(__file__).resolve().parents[3] / "conf"
    if (checkout / "config.yaml").is_file():
        return checkout
    raise FileNotFoundError(
        f"rlexp's configs are missing: neither {packaged} (an installed wheel) nor {checkout} (a "
        "checkout) holds config.yaml; reinstall rlexp"
    )


CONF_DIR: Path = find_conf_dir()


def config_dir_arg(argv: Sequence[str]) -> str | None:
    """The ``--config-dir`` / ``-cd`` of a command line, read by Hydra's own parser (None: none, or
    a command line Hydra will refuse itself)."""
    from hydra._internal.utils import get_args_parser

    try:
        with contextlib.redirect_stderr(io.StringIO()):  # Hydra prints its own usage error later
            return get_args_parser().parse_args(list(argv)).config_dir
    except SystemExit:
        return None


def with_user_config_dir(argv: Sequence[str], cwd: Path | None = None) -> list[str]:
    """``argv`` with ``--config-dir <cwd>/conf`` added when the working directory has a ``conf/``
    of its own and the command line names no config dir (an explicit ``--config-dir`` wins)."""
    argv = list(argv)
    conf = Path(cwd or os.getcwd()) / "conf"
    if config_dir_arg(argv) is not None or not conf.is_dir() or _same_dir(conf, CONF_DIR):
        return argv
    log.info("config dir %s added to rlexp's configs (your project's options)", conf)
    return [f"--config-dir={conf.resolve()}", *argv]


def _same_dir(a: Path, b: Path) -> bool:
    try:
        return a.resolve() == b.resolve() or a.samefile(b)
    except OSError:
        return False


def check_user_config_dir(config_dir: str) -> Path:
    """The user's config dir as an absolute path; ``ConfigError`` naming it when it is no directory,
    and a warning when it holds a ``config.yaml`` that rlexp's root config shadows."""
    from rlexp.config.validate import ConfigError

    path = Path(config_dir).expanduser().absolute()
    if not path.is_dir():
        raise ConfigError(f"--config-dir {config_dir}: no such directory ({path})")
    if (path / "config.yaml").is_file() and not _same_dir(path, CONF_DIR):
        log.warning(
            "%s is not used: rlexp's own config.yaml is the root config; put presets in %s/experiment/ "
            "and select them with +experiment=NAME",
            path / "config.yaml",
            path,
        )
    return path


@contextlib.contextmanager
def initialize_hydra(conf_dir: Path, user_dir: str | None = None) -> Iterator[None]:
    """Hydra initialised on ``conf_dir`` plus ``user_dir`` after it, as ``rlexp train
    --config-dir USER_DIR`` searches them (inside the ``with``; Hydra's state is restored after)."""
    from hydra import initialize_config_dir

    with initialize_config_dir(config_dir=str(conf_dir), version_base="1.3"):
        if user_dir is not None:
            _search_also(conf_dir, check_user_config_dir(user_dir))
        yield


def _search_also(conf_dir: Path, user_dir: Path) -> None:
    """Re-initialise Hydra with ``user_dir`` where Hydra's own ``--config-dir`` puts it: after the
    primary dir and the plugins' dirs, before the ConfigStore schemas."""
    from hydra._internal.hydra import Hydra
    from hydra._internal.utils import create_config_search_path
    from hydra.core.config_search_path import SearchPathQuery
    from hydra.core.global_hydra import GlobalHydra

    search_path = create_config_search_path(str(conf_dir))
    search_path.prepend(
        provider="command-line",
        path=f"file://{user_dir}",
        anchor=SearchPathQuery(provider="schema"),
    )
    GlobalHydra.instance().clear()
    Hydra.create_main_hydra2(task_name="app", config_search_path=search_path)
