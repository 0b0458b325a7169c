"""``python train.py --config-json FILE [overrides]``: our users' JSON experiment files through Hydra.

The file is loaded and checked before Hydra starts, so a bad file prints one line on stderr and exits
2 without creating a run dir. Its nodes then go into Hydra's ConfigStore (``env=json_task``,
``logger=json_logger`` and ``+experiment=json_experiment`` in package ``_global_``, whose defaults list
chooses the other two): Hydra composes ``conf/`` with them exactly as with a YAML preset, command-line
overrides and group choices (``logger=none``) apply on top, and ``-m`` sweeps run from the JSON base.
"""

from __future__ import annotations

import contextlib
import logging
import sys
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback

from rlexp.config.json_format import JsonExperiment, escape_interpolations, load_json_experiment
from rlexp.config.schema import RootConfig
from rlexp.config.validate import ConfigError

log = logging.getLogger(__name__)

CONFIG_FLAGS = ("--config-json", "--config")  # --config: the name the users' own train.py used
ENV_NODE = "json_task"  # ConfigStore: env=json_task
LOGGER_NODE = "json_logger"  # ConfigStore: logger=json_logger (the file's sinks)
EXPERIMENT = "json_experiment"  # ConfigStore: +experiment=json_experiment


class JsonNotes(Callback):
    """Hydra callback: logs what the loader found (task file used, keys not applicable) in each job."""

    def __init__(self, notes: Sequence[str] = ()) -> None:
        self.notes = [str(n) for n in notes]

    def on_job_start(self, config: Any = None, **kwargs: Any) -> None:
        for note in self.notes:
            if note.startswith("warning: "):
                log.warning(note[len("warning: ") :])
            else:
                log.info(note)


def split_config_arg(argv: Sequence[str]) -> tuple[str | None, list[str]]:
    """(the JSON file of ``--config-json F`` / ``--config F`` / ``--config=F``, the other arguments)."""
    path: str | None = None
    rest: list[str] = []
    args = list(argv)
    i = 0
    while i < len(args):
        arg = args[i]
        flag, eq, value = arg.partition("=")
        if flag in CONFIG_FLAGS:
            if not eq:
                if i + 1 >= len(args) or args[i + 1].startswith("-"):
                    raise ConfigError(f"{flag} needs a file: {flag} path/to/train_config.json")
                value = args[i + 1]
                i += 1
            if path is not None:
                raise ConfigError(f"give one JSON experiment file, got {path!r} and {value!r}")
            path = value
        else:
            rest.append(arg)
        i += 1
    return path, rest


#: Hydra's command-line options that take a value (the next argument unless written ``--opt=value``).
_HYDRA_VALUE_OPTIONS = {
    "--cfg",
    "-c",
    "--package",
    "-p",
    "--config-path",
    "-cp",
    "--config-name",
    "-cn",
    "--config-dir",
    "-cd",
    "--experimental-rerun",
    "--shell-completion",
    "-sc",
}
_HYDRA_INFO_CHOICES = {"all", "config", "defaults", "defaults-tree", "plugins", "searchpath"}


def insert_override(args: Sequence[str], override: str) -> list[str]:
    """``args`` with ``override`` placed just before the first override: Hydra's parser wants the
    overrides next to each other (``--cfg job seed=1`` and ``seed=1 --cfg job`` both stay valid)."""
    args = list(args)
    i = 0
    while i < len(args):
        arg = args[i]
        if not arg.startswith("-"):
            return [*args[:i], override, *args[i:]]
        if arg in _HYDRA_VALUE_OPTIONS:
            i += 1
        elif arg in ("--info", "-i") and i + 1 < len(args) and args[i + 1] in _HYDRA_INFO_CHOICES:
            i += 1
        i += 1
    return [*args, override]


def check_no_tuned_preset(overrides: Sequence[str]) -> None:
    """``+experiment=tuned`` (or ``rl_zoo``) picks ``conf/<group>/<env>.yaml`` by the env chosen in
    ``conf/``; a JSON file's env is none of those (and the run is already
    ``+experiment=json_experiment``): one line, not Hydra's "Multiple values for experiment"."""
    from rlexp.launch.precheck import PRESET_GROUPS

    for o in overrides:
        key, _, group = o.lstrip("+~").partition("=")
        if key == "experiment" and group in PRESET_GROUPS:
            raise ConfigError(
                f"+experiment={group} has no preset for a --config-json run's env (from its JSON "
                f"file; the {group} presets are for the envs of conf/{group}/, docs/results.md): "
                f"set the values in the JSON file or on the command line, or leave out "
                f"+experiment={group}"
            )


def register_json_experiment(exp: JsonExperiment) -> None:
    """Put ``exp`` into Hydra's ConfigStore as ``env/json_task``, ``logger/json_logger`` and
    ``experiment/json_experiment``. The experiment chooses the other two in its defaults list, so a
    group chosen on the command line (``logger=none``) wins over the file, as over any preset."""
    from hydra.core.config_store import ConfigStore

    from rlexp.config.schema import register_configs

    register_configs()
    cs = ConfigStore.instance()
    cs.store(group="env", name=ENV_NODE, node=exp.env)
    cs.store(group="logger", name=LOGGER_NODE, node=exp.logger)
    # The notes quote the files (paths, names): data for OmegaConf, as the files' values are.
    notes = escape_interpolations(exp.notes)
    node = {
        "defaults": [
            {"override /env": ENV_NODE},
            {"override /logger": LOGGER_NODE},
            *({f"override /{group}": option} for group, option in exp.groups.items()),
            "_self_",
        ],
        **exp.root,
        "hydra": {
            "callbacks": {"rlexp_json_notes": {"_target_": f"{__name__}.JsonNotes", "notes": notes}}
        },
    }
    cs.store(group="experiment", name=EXPERIMENT, package="_global_", node=node)


def compose_json_experiment(exp: JsonExperiment, overrides: Sequence[str] = ()) -> RootConfig:
    """The typed config Hydra composes from ``exp`` (plus ``overrides``), in this process."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    from rlexp.config.paths import CONF_DIR
    from rlexp.config.validate import to_root_config

    register_json_experiment(exp)
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            cfg = compose(config_name="config", overrides=[f"+experiment={EXPERIMENT}", *overrides])
        return to_root_config(cfg)
    except ConfigError as exc:
        raise ConfigError(f"{exp.train_path}: {exc}") from None
    except (HydraException, OmegaConfBaseException) as exc:
        raise ConfigError(f"{exp.train_path}: {str(exc).splitlines()[0]}") from None
    finally:
        GlobalHydra.instance().clear()


def check_task_builds(exp: JsonExperiment, config: RootConfig) -> None:
    """Build the native task once with one env, so that a bad term parameter or scene value fails now,
    naming the task file, and not after the run dir exists; check ``policy.action_dim``."""
    e = config.env
    if e.backend != "native" or e.native is None:
        return
    from rlexp.envs.native import make_native_env

    try:
        env = make_native_env(e.native, 1, config.seed, e.max_episode_steps)
    except (KeyError, ValueError, TypeError) as exc:
        msg = str(exc.args[0] if exc.args else exc)
        if msg.startswith(("actions.", "events.", "observations.", "rewards.")):
            msg = "env." + msg  # the env names its terms' keys; in the task file they sit under env
        raise ConfigError(f"{exp.gym_path}: {msg}") from None
    try:
        act_dim = int(env.action_spec.shape[-1])
    finally:
        env.close()
    if exp.action_dim is not None and exp.action_dim != act_dim:
        raise ConfigError(
            f"{exp.train_path}: policy.action_dim={exp.action_dim} but the {e.native.task} task's actions "
            f"have {act_dim} dimensions; remove policy.action_dim or set it to {act_dim}"
        )


def prepare(path: str | Path, cwd: str | Path | None = None) -> JsonExperiment:
    """Load, check, compose and register the JSON experiment ``path`` (ConfigError if it cannot run)."""
    exp = load_json_experiment(path, cwd)
    config = compose_json_experiment(exp)
    check_task_builds(exp, config)
    return exp


@contextlib.contextmanager
def _one_repository(loader: Any) -> Iterator[None]:
    """Meanwhile, Hydra's config loader builds its repository of configs once per (config name,
    overrides): listing the options of ~110 groups builds and deep-copies it for each (~1.2 s of
    ``rlexp train --help``'s 2 s); a listing reads it, never changes it."""
    build = getattr(loader, "_parse_overrides_and_create_caching_repo", None)
    if build is None or "_parse_overrides_and_create_caching_repo" in vars(loader):
        yield
        return
    built: dict[tuple, Any] = {}

    def once(config_name: Any, overrides: list[str]) -> Any:
        key = (config_name, tuple(overrides))
        if key not in built:
            built[key] = build(config_name, overrides)
        return built[key]

    loader._parse_overrides_and_create_caching_repo = once
    try:
        yield
    finally:
        del loader._parse_overrides_and_create_caching_repo


def hide_schemas_in_help() -> None:
    """``--help`` lists each group's options; the typed schemas (``trainer_schema``...) sit in the
    same groups for the YAML files' defaults lists, but are no options a user can choose: drop them
    from the listing (Hydra has no hidden flag for a stored config)."""
    from hydra._internal.hydra import Hydra

    original = Hydra.format_config_groups
    if getattr(original, "hides_schemas", False):
        return

    def format_config_groups(self: Any, predicate: Any, compact: bool = True) -> str:
        with _one_repository(self.config_loader):
            text = original(self, predicate, compact)
        lines = []
        for line in text.splitlines():
            group, sep, options = line.partition(": ")
            if sep and compact:
                kept = [o for o in options.split(", ") if not o.endswith("_schema")]
                line = f"{group}: {', '.join(kept)}"
            elif line.strip().endswith("_schema"):
                continue
            lines.append(line)
        return "\n".join(lines) + ("\n" if text.endswith("\n") else "")

    format_config_groups.hides_schemas = True  # type: ignore[attr-defined]
    Hydra.format_config_groups = format_config_groups  # type: ignore[method-assign]


def main(argv: Sequence[str] | None = None) -> None:
    """``train.py`` entry: strip ``--config-json F``, load F, then hand over to Hydra (rlexp.app.main)."""
    args = list(sys.argv[1:] if argv is None else argv)
    try:
        path, rest = split_config_arg(args)
        if path is not None:
            check_no_tuned_preset(rest)
            prepare(path)
            rest = insert_override(rest, f"+experiment={EXPERIMENT}")
    except ConfigError as exc:
        print(f"config error: {exc}", file=sys.stderr)
        sys.exit(2)
    from rlexp.app import main as app_main

    if "--help" in rest or "-h" in rest:
        hide_schemas_in_help()
    sys.argv = [sys.argv[0], *rest]
    app_main()
