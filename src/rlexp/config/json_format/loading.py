"""Loading a JSON experiment: the train file, the task file it names (``find_task_file``) and its
``rlexp`` section, checked and mapped onto the nodes Hydra composes (``load_json_experiment`` ->
``JsonExperiment``)."""

from __future__ import annotations

import os
import re
import stat
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rlexp.config.json_format.convert import _convert
from rlexp.config.json_format.leaves import _overlay, flatten, nest
from rlexp.config.json_format.reading import read_json
from rlexp.config.json_format.train_section import TRAIN_SECTIONS, TRAINER_KEYS
from rlexp.config.json_format.typed_reads import _File
from rlexp.config.validate import ConfigError, escape_interpolations

if typing.TYPE_CHECKING:
    from rlexp.config.schema import RootConfig

#: The logger the format's system always had (its charts were TensorBoard); ``use_wandb`` adds W&B.
FORMAT_LOGGER = "tensorboard"
#: Logger leaves that turn a sink on or off. A JSON file's values for them go into its logger group
#: node (``logger=json_logger``), so that ``logger=none`` on the command line replaces them, as it
#: replaces any group choice; the sinks' settings (W&B project, tags...) stay with the experiment.
LOGGER_SWITCHES = (
    "logger.tensorboard.enabled",
    "logger.wandb.enabled",
    "logger.jsonl",
    "logger.console",
)


@dataclass
class JsonExperiment:
    """A loaded train file + task file, as RootConfig-shaped nodes for Hydra."""

    train_path: Path
    gym_path: Path
    env_group: str  # the conf/env group the task maps to (push_cube), or "" for none
    env: dict[str, Any]  # the whole env group node
    groups: dict[str, str]  # policy / algorithm group options the file chooses (grpo, actor_only)
    root: dict[str, Any]  # every other key, in RootConfig's shape (seed, trainer, policy, ...)
    logger: dict[str, Any]  # the logger group node: which sinks are on (LOGGER_SWITCHES)
    notes: list[str] = field(default_factory=list)  # lines each run logs once
    action_dim: int | None = None  # policy.action_dim, checked against the env once it is built


def _resolve(path: Path) -> Path:
    """``path`` made absolute, symlinks resolved where they can be: a symlink loop, an unknown
    ``~user`` or a NUL byte is reported when the file is read, not as a traceback here."""
    try:
        return path.expanduser().resolve()
    except (OSError, RuntimeError, ValueError):
        return Path(os.path.abspath(path))


def _file_state(path: Path) -> str | None:
    """None for a regular file, else why ``path`` cannot be one (for the "tried ..." list)."""
    try:
        mode = path.stat().st_mode
    except (OSError, ValueError):
        try:
            path.lstat()
        except (OSError, ValueError):
            return "missing"
        return "not a regular file"  # e.g. a symlink loop
    return None if stat.S_ISREG(mode) else "not a regular file"


def find_task_file(ref: str, train_path: Path, cwd: Path) -> tuple[Path, str]:
    """The task file ``ref`` names: relative to the working dir, then to the train file's folder, then
    the train file's folder with ``ref``'s base name (the shared files name their original repo's paths)."""
    p = _resolve(Path(ref)) if ref.startswith("~") else Path(ref)
    if p.is_absolute():
        candidates = [(p, "absolute path")]
    else:
        folder = train_path.parent
        candidates = [
            (cwd / p, "relative to the working dir"),
            (folder / p, "relative to the train file's folder"),
            (folder / p.name, f"the train file's folder, by base name ({ref!r} does not exist)"),
        ]
    seen: list[Path] = []
    tried: list[str] = []
    for path, how in candidates:
        path = _resolve(path)
        if path in seen:
            continue
        seen.append(path)
        state = _file_state(path)
        if state is None:
            return path, how
        tried.append(str(path) if state == "missing" else f"{path} ({state})")
    raise ConfigError(
        f"{train_path}: trainer.gym_config={ref!r}: task file not found; tried {', '.join(tried)}"
    )


def _rlexp_section(tf: _File, section: Any, names: dict[str, Any]) -> dict[str, Any]:
    """The ``rlexp`` section (RootConfig keys the format has none for) as dotted leaves, checked
    against the schema (the policy and algorithm schemas the file's ``name``s choose); its strings
    are data (escaped), as every other value of the file."""
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    from rlexp.config.schema import RootConfig

    section = escape_interpolations(tf.obj(section, "rlexp"))
    try:
        merged = OmegaConf.merge(OmegaConf.structured(default_root_config(**names)), section)
        # resolving turns an escaped string back into the file's string, checked against its field
        OmegaConf.to_container(merged, resolve=True)
    except OmegaConfBaseException as exc:
        key = getattr(exc, "full_key", "") or ""
        msg = re.sub(r"^While dereferencing interpolation '.*?': ", "", str(exc).splitlines()[0])
        raise tf.error(f"rlexp.{key}: {msg}" if key else f"rlexp: {msg}") from None
    return flatten(section, RootConfig)


def default_root_config(policy: Any = None, algorithm: Any = None) -> RootConfig:
    """A RootConfig with every group at its schema default (``policy`` / ``algorithm``: the name of
    the section's schema, e.g. ``grpo``; actor_critic and ppo when not one of the names)."""
    from rlexp.config import schema

    return schema.RootConfig(
        trainer=schema.TrainerConfig(),
        policy=schema.VARIANTS["policy"].get(policy, schema.PolicyConfig)(),
        algorithm=schema.VARIANTS["algorithm"].get(algorithm, schema.AlgorithmConfig)(),
        env=schema.EnvConfig(),
        events=schema.EventsConfig(),
        logger=schema.LoggerConfig(),
    )


def load_json_experiment(path: str | Path, cwd: str | Path | None = None) -> JsonExperiment:
    """Parse and check a train file and its task file; map them onto RootConfig-shaped nodes."""
    shown = str(path)
    cwd = Path.cwd() if cwd is None else Path(cwd)
    train_path = _resolve(Path(path))
    train = read_json(train_path, shown)
    tf = _File(shown)
    tf.obj(train, "", TRAIN_SECTIONS)
    t = tf.obj(tf.get(train, "trainer", "", "object"), "trainer", TRAINER_KEYS)
    gym_path, how = find_task_file(tf.get(t, "gym_config", "trainer", "str"), train_path, cwd)
    gym = read_json(gym_path, str(gym_path))
    names = {
        section: train[section].get("name")
        for section in ("policy", "algorithm")
        if isinstance(train.get(section), dict)
    }
    rlexp = _rlexp_section(tf, train["rlexp"], names) if "rlexp" in train else {}
    mapped = _convert(
        train,
        gym,
        tf,
        _File(str(gym_path)),
        {k: v for k, v in rlexp.items() if k.startswith("env.")},
        escape=True,
    )

    notes = [f"JSON experiment {train_path} with task file {gym_path} ({how})"]
    if how.startswith("relative to the working dir"):
        other = _resolve(train_path.parent / Path(t["gym_config"]).name)
        if other != gym_path and _file_state(other) is None:
            notes.append(
                f"warning: {other} beside the train file was not used ({gym_path} comes first)"
            )
    notes += mapped.notes
    env_leaves = _overlay(
        mapped.env_base, {k: v for k, v in mapped.leaves.items() if k.startswith("env.")}
    )
    env_leaves = _overlay(env_leaves, {k: v for k, v in rlexp.items() if k.startswith("env.")})
    root_leaves = _overlay(
        {k: v for k, v in mapped.leaves.items() if not k.startswith("env.")},
        {k: v for k, v in rlexp.items() if not k.startswith("env.")},
    )
    # Which sinks are on is a logger group choice, so that logger=... on the command line wins.
    switches = {
        k[len("logger.") :]: root_leaves.pop(k) for k in LOGGER_SWITCHES if k in root_leaves
    }
    return JsonExperiment(
        train_path=train_path,
        gym_path=gym_path,
        env_group=mapped.env_group,
        groups=dict(mapped.groups),
        env=nest({k[len("env.") :]: v for k, v in env_leaves.items()}),
        root=nest(root_leaves),
        logger={"defaults": [FORMAT_LOGGER, "_self_"], **nest(switches)},
        notes=notes,
        action_dim=mapped.action_dim,
    )
