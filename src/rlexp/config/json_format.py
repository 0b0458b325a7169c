"""Our users' JSON experiment format (a train file plus the task file it names) as one more source of
the typed config.

``load_json_experiment(path)`` parses both files strictly and checks every key and value: an error
names the file and the dotted key (``trainer.eval_freq``), the value, and the fix; a path or content
that is no experiment file at all (a directory, a FIFO, a symlink loop, a huge or deeply nested
file, bytes that are not UTF-8) is one such error too. It then maps the files onto RootConfig's keys
as three plain nodes: the ``env`` group node (the task, built on ``conf/env/<task>.yaml`` with the
file's terms added to the YAML's, replacing same-named ones), the ``logger`` group node (which sinks
are on) and a root node (everything else). Every string the files give is data: escaped so that
OmegaConf never resolves a ``${...}`` in it. ``rlexp.launch.json_entry`` hands the nodes to Hydra
(``env=json_task``, ``logger=json_logger``, ``+experiment=json_experiment``), so a JSON run is
composed, overridden from the command line, swept and validated exactly as a YAML run.

``to_json_experiment(config)`` goes the other way: each run dir gets ``train_config.json`` and
``gym_config.json`` (``write_json_experiment``). What the format has no key for is written under a
top-level ``rlexp`` section (the format's own system ignored unknown top-level keys), so loading the
pair gives back the identical config. The key-by-key table is in docs/json_format.md.
"""

from __future__ import annotations

import dataclasses
import difflib
import json
import logging
import math
import os
import re
import stat
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rlexp.config.validate import ConfigError, escape_interpolations

if typing.TYPE_CHECKING:
    from rlexp.config.schema import RootConfig

log = logging.getLogger(__name__)

#: Task ids of the format -> our native task (conf/env/<name>.yaml). Gymnasium ids of the env YAMLs
#: (e.g. HalfCheetah-v5) are accepted too, so that every rlexp run can be written in this format.
TASK_IDS = {"PushCubeRL": "push_cube", "CartPoleRL": "cart_pole"}
#: Event function names of the format -> rlexp's registered event functions.
EVENT_ALIASES = {"record_camera_data_async": "record_video"}
#: Parameters of record_video the format uses (the registered function may accept more).
RECORD_VIDEO_PARAMS = ("name", "resolution", "eye", "target", "up", "intrinsics", "save_path")
ACTIVATIONS = ("relu", "elu", "tanh", "gelu", "silu", "swish")
POLICIES = ("actor_critic", "actor_only")
ALGORITHMS = ("ppo", "grpo")
#: The format's policy / algorithm name -> the conf/ group option whose schema it is.
GROUP_OPTIONS = {
    "policy": {"actor_critic": "mlp", "actor_only": "actor_only"},
    "algorithm": {"ppo": "ppo", "grpo": "grpo"},
}
NET_TYPES = ("mlp",)
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

TRAIN_SECTIONS = ("trainer", "policy", "algorithm", "rlexp")
TRAINER_KEYS = (
    "exp_name", "gym_config", "seed", "device", "headless", "gpu_id", "renderer", "enable_rt", "num_envs",
    "iterations", "buffer_size", "rollout_steps", "enable_eval", "num_eval_envs", "num_eval_episodes",
    "eval_freq", "save_freq", "use_wandb", "wandb_project_name", "events",
)  # fmt: skip
#: Trainer keys that choose the simulator's window, GPU and ray tracer: nothing to do on MuJoCo/CPU.
TRAINER_NOT_APPLICABLE = ("headless", "gpu_id", "renderer", "enable_rt")
POLICY_KEYS = ("name", "actor", "critic", "action_dim")
NET_KEYS = ("type", "network_cfg")
NETWORK_CFG_KEYS = ("hidden_sizes", "activation")
ALGORITHM_KEYS = ("name", "cfg")
#: PPO keyword of the format -> AlgorithmConfig field, and the format's default.
PPO_KEYS = {
    "learning_rate": ("lr", 3e-4),
    "n_epochs": ("num_epochs", 10),
    "batch_size": ("mini_batch_size", 64),
    "gamma": ("gamma", 0.99),
    "gae_lambda": ("lmbda", 0.95),
    "clip_coef": ("clip_epsilon", 0.2),
    "ent_coef": ("entropy_coeff", 0.01),
    "vf_coef": ("critic_coeff", 0.5),
    "max_grad_norm": ("max_grad_norm", 0.5),
}
#: GRPO keyword of the format -> GRPOConfig field (None: accepted, unused), and the format's default.
GRPO_KEYS = {
    "learning_rate": ("lr", 3e-4),
    "n_epochs": ("num_epochs", 10),
    "batch_size": ("mini_batch_size", 64),
    "gamma": ("gamma", 0.99),
    "gae_lambda": (None, 0.95),
    "clip_coef": ("clip_epsilon", 0.2),
    "ent_coef": ("entropy_coeff", 0.0),
    "kl_coef": ("kl_coeff", 0.02),
    "group_size": ("group_size", 4),
    "eps": ("epsilon", 1e-8),
    "reset_every_rollout": ("reset_every_rollout", True),
    "truncate_at_first_done": ("truncate_at_first_done", True),
    "max_grad_norm": ("max_grad_norm", 0.5),
}
ALGORITHM_FORMAT_KEYS = {"ppo": PPO_KEYS, "grpo": GRPO_KEYS}
GYM_KEYS = (
    "id", "max_episodes", "max_episode_steps", "num_envs", "env", "robot", "sensor", "light", "background",
    "rigid_object", "rigid_object_group", "articulation",
)  # fmt: skip
GYM_ENV_KEYS = ("events", "observations", "rewards", "actions", "extensions", "num_envs")
#: Term kind -> (keys a term may have, defaults filled in, modes).
TERM_KEYS: dict[str, tuple[tuple[str, ...], dict[str, Any], tuple[str, ...]]] = {
    "events": (
        ("func", "mode", "interval_step", "params"),
        {"mode": "reset", "interval_step": 1},
        ("startup", "reset", "interval"),
    ),
    "observations": (("func", "mode", "name", "params"), {"mode": "add"}, ("add", "modify")),
    "rewards": (
        ("func", "mode", "weight", "params"),
        {"mode": "add", "weight": 1.0},
        ("add", "replace"),
    ),
    "actions": (("func", "params"), {}, ()),
}
EVENT_TERM_KEYS = ("func", "mode", "interval_step", "params")

#: Experiment files are a few KiB; anything near this is not one (and would only cost memory).
MAX_FILE_BYTES = 4 * 2**20
#: Nesting the files may use (theirs need ~6): deeper JSON is refused before it is parsed, as the
#: parser, OmegaConf and Hydra recurse once per level.
MAX_DEPTH = 32

_REQUIRED = object()


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


# ------------------------------------------------------------------------------------------ parsing


class _DuplicateKey(ValueError):
    pass


def _no_duplicates(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in pairs:
        if key in out:
            raise _DuplicateKey(key)
        out[key] = value
    return out


def _no_constant(name: str) -> Any:
    raise ValueError(f"{name} is not valid JSON")


def read_json(path: Path, shown: str) -> dict[str, Any]:
    """Strictly parsed JSON object (no duplicate keys, no NaN/Infinity); errors give line and column."""
    text = _read_text(path, shown)
    line = _too_deep(text)
    if line is not None:
        raise ConfigError(
            f"{shown}: JSON nested more than {MAX_DEPTH} levels deep (line {line}); an experiment "
            "file needs a handful"
        )
    try:
        data = json.loads(text, object_pairs_hook=_no_duplicates, parse_constant=_no_constant)
    except json.JSONDecodeError as exc:
        raise ConfigError(
            f"{shown}: invalid JSON at line {exc.lineno}, column {exc.colno}: {exc.msg}"
        ) from None
    except _DuplicateKey as exc:
        line = _line_of(text, exc.args[0])
        raise ConfigError(f"{shown}: duplicate key {exc.args[0]!r}{line}; keep one") from None
    except ValueError as exc:
        raise ConfigError(f"{shown}: invalid JSON: {exc}") from None
    if not isinstance(data, dict):
        raise ConfigError(
            f"{shown}: the file must hold a JSON object {{...}}, got {type(data).__name__}"
        )
    return data


_FILE_KINDS = (
    (stat.S_ISFIFO, "a FIFO"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISSOCK, "a socket"),
)


def _read_text(path: Path, shown: str) -> str:
    """The file's text, refusing what is not a regular UTF-8 file of a sane size (a FIFO is opened
    without blocking, so that a pipe with no writer cannot hang the run)."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    except FileNotFoundError:
        raise ConfigError(f"{shown}: no such file") from None
    except OSError as exc:
        raise ConfigError(f"{shown}: cannot be read ({exc.strerror})") from None
    except ValueError as exc:  # a NUL byte in the path
        raise ConfigError(f"{shown}: cannot be read ({exc})") from None
    try:
        st = os.fstat(fd)
        if stat.S_ISDIR(st.st_mode):
            raise ConfigError(
                f"{shown}: is a directory; give the train file in it "
                f"(e.g. {os.path.join(shown, 'train_config.json')})"
            )
        if not stat.S_ISREG(st.st_mode):
            kind = next((name for test, name in _FILE_KINDS if test(st.st_mode)), "a special file")
            raise ConfigError(f"{shown}: is not a regular file ({kind}); give a JSON file")
        if st.st_size > MAX_FILE_BYTES:
            raise ConfigError(_too_big(shown, st.st_size))
        with open(fd, "rb", closefd=False) as f:
            data = f.read(MAX_FILE_BYTES + 1)
        if len(data) > MAX_FILE_BYTES:  # the size stat gave was wrong (a file still growing)
            raise ConfigError(_too_big(shown, len(data)))
    except OSError as exc:
        raise ConfigError(f"{shown}: cannot be read ({exc.strerror})") from None
    finally:
        os.close(fd)
    try:
        return data.decode("utf-8-sig")  # a byte-order mark (Windows editors) is not an error
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        raise ConfigError(
            f"{shown}: is not UTF-8 text (byte 0x{data[exc.start]:02x} at line {line}); "
            "save it as UTF-8"
        ) from None


def _too_big(shown: str, size: int) -> str:
    return f"{shown}: is {size} bytes; an experiment file may hold at most {MAX_FILE_BYTES // 2**20} MiB"


#: A JSON string (escaped quotes included; an unterminated one runs to the end, so that the scan
#: stays linear): brackets inside one are data, not nesting.
_JSON_STRING = re.compile(r'"[^"\\]*(?:\\.[^"\\]*)*"?', re.DOTALL)


def _too_deep(text: str) -> int | None:
    """The line where ``text`` nests deeper than MAX_DEPTH, else None. Checked before parsing: the
    parser (and everything after it that walks the values) recurses once per level."""
    bare = _JSON_STRING.sub('""', text)  # JSON strings hold no raw newline: lines stay the same
    if bare.count("[") + bare.count("{") <= MAX_DEPTH:
        return None
    depth = 0
    for m in re.finditer(r"[\[\]{}]", bare):
        depth += 1 if m.group() in "[{" else -1
        if depth > MAX_DEPTH:
            return bare.count("\n", 0, m.start()) + 1
    return None


def _line_of(text: str, key: str) -> str:
    """' (line N)' of the second occurrence of ``"key"``, for duplicate-key errors."""
    hits = [m.start() for m in re.finditer(re.escape(json.dumps(key)) + r"\s*:", text)]
    return f" (line {text.count(chr(10), 0, hits[1]) + 1})" if len(hits) > 1 else ""


# ------------------------------------------------------------------------------ values are data

#: A run of backslashes right before "${": what OmegaConf reads as an (escaped) interpolation.
# --------------------------------------------------------------------------------- typed reading


def _show(value: Any) -> str:
    text = json.dumps(value) if not isinstance(value, str) else repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _join(where: str, key: str) -> str:
    return f"{where}.{key}" if where else key


class _File:
    """Typed reads from one file's JSON, with errors that name the file and the dotted key."""

    def __init__(self, shown: str) -> None:
        self.shown = shown

    def error(self, msg: str) -> ConfigError:
        return ConfigError(f"{self.shown}: {msg}")

    def obj(self, value: Any, where: str, known: tuple[str, ...] | None = None) -> dict[str, Any]:
        """``value`` as an object whose keys are all in ``known``."""
        if not isinstance(value, dict):
            raise self.error(f"{where or 'the file'} must be an object {{...}}, got {_show(value)}")
        if known is not None:
            for key in value:
                if key not in known:
                    msg = f"unknown key {_join(where, key)!r}"
                    close = difflib.get_close_matches(key, known, n=1)
                    if close:
                        msg += f"; did you mean {_join(where, close[0])!r}?"
                    msg += f" ({where or 'the file'} accepts {sorted(known)})"
                    raise self.error(msg)
        return value

    def get(
        self,
        d: dict[str, Any],
        key: str,
        where: str,
        kind: str,
        default: Any = _REQUIRED,
        low: float | None = None,
        high: float | None = None,
        choices: tuple[str, ...] | None = None,
        positive: bool = False,
    ) -> Any:
        """``d[key]`` checked against ``kind`` (int, number, bool, str, object, list, ints, numbers),
        the range [low, high] (``positive``: > 0) and ``choices``."""
        dotted = _join(where, key)
        if key not in d:
            if default is _REQUIRED:
                raise self.error(f"{dotted} is required")
            return default
        return self.check(d[key], dotted, kind, low, high, choices, positive)

    def check(
        self,
        value: Any,
        dotted: str,
        kind: str,
        low: float | None = None,
        high: float | None = None,
        choices: tuple[str, ...] | None = None,
        positive: bool = False,
    ) -> Any:
        bad = self.error(f"{dotted}={_show(value)} must be {_KIND_TEXT[kind]}")
        if kind == "int":
            if isinstance(value, bool) or not isinstance(value, int):
                raise bad
        elif kind == "number":
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise bad
        elif kind == "bool":
            if not isinstance(value, bool):
                raise bad
        elif kind == "str":
            if not isinstance(value, str) or not value:
                raise bad
        elif kind == "object":
            if not isinstance(value, dict):
                raise bad
        elif kind == "list":
            if not isinstance(value, list):
                raise bad
        elif kind in ("ints", "numbers"):
            if not isinstance(value, list):
                raise bad
            for i, item in enumerate(value):
                self.check(
                    item,
                    f"{dotted}[{i}]",
                    "int" if kind == "ints" else "number",
                    low,
                    high,
                    None,
                    positive,
                )
            return [float(v) for v in value] if kind == "numbers" else value
        if kind in ("int", "number"):
            if positive and value <= 0:
                raise self.error(f"{dotted}={_show(value)} is out of range: must be > 0")
            if (low is not None and value < low) or (high is not None and value > high):
                rng = f">= {low:g}" if high is None else f"in [{low:g}, {high:g}]"
                raise self.error(f"{dotted}={_show(value)} is out of range: must be {rng}")
        if choices is not None and value not in choices:
            msg = f"{dotted}={_show(value)}: choose from {list(choices)}"
            close = difflib.get_close_matches(str(value), choices, n=1)
            raise self.error(msg + (f"; did you mean {close[0]!r}?" if close else ""))
        return float(value) if kind == "number" else value


_KIND_TEXT = {
    "int": "an integer",
    "number": "a number",
    "bool": "true or false",
    "str": "a non-empty string",
    "object": "an object {...}",
    "list": "a list [...]",
    "ints": "a list of integers",
    "numbers": "a list of numbers",
}


# ------------------------------------------------------------------------------ schema flattening


def _dataclass_of(tp: Any) -> type | None:
    """The dataclass in a field type (``X``, ``X | None``), else None."""
    if dataclasses.is_dataclass(tp):
        return tp
    for arg in typing.get_args(tp):
        if dataclasses.is_dataclass(arg):
            return arg
    return None


def flatten(node: dict[str, Any], cls: type, prefix: str = "") -> dict[str, Any]:
    """Dotted leaves of a RootConfig-shaped dict: nested schema dataclasses are opened, every other
    field (numbers, lists, the term dicts) is one leaf, compared and replaced whole."""
    from rlexp.config.schema import VARIANTS

    hints = typing.get_type_hints(cls)
    out: dict[str, Any] = {}
    for key, value in node.items():
        sub = _dataclass_of(hints.get(key))
        if sub is not None and not prefix and key in VARIANTS:  # the schema its name names
            variants = VARIANTS[key]
            if isinstance(value, dict) and value.get("name") in variants:
                sub = variants[value["name"]]
            else:  # a partial section (the rlexp section's): any variant's keys
                union = {
                    n: t for v in variants.values() for n, t in typing.get_type_hints(v).items()
                }
                sub = dataclasses.make_dataclass(sub.__name__, list(union.items()))
        if sub is not None and isinstance(value, dict):
            out.update(flatten(value, sub, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def nest(flat: dict[str, Any]) -> dict[str, Any]:
    """The inverse of ``flatten``."""
    out: dict[str, Any] = {}
    for dotted, value in flat.items():
        *parents, last = dotted.split(".")
        node = out
        for p in parents:
            node = node.setdefault(p, {})
        node[last] = value
    return out


def _overlay(flat: dict[str, Any], new: dict[str, Any]) -> dict[str, Any]:
    """``flat`` with the leaves of ``new`` set; a leaf replaces whatever lay above or below it."""
    out = dict(flat)
    for key, value in new.items():
        for old in list(out):
            if old.startswith(key + ".") or key.startswith(old + "."):
                del out[old]
        out[key] = value
    return out


# --------------------------------------------------------------------------- registries (lazy)


def _native() -> Any:
    """``rlexp.envs.native`` (imported when first needed: it imports MuJoCo)."""
    import rlexp.envs.native as native

    return native


def _term_registry(kind: str) -> list[str]:
    """Registered names of one kind of task term."""
    reg = {
        "events": "EVENTS",
        "observations": "OBSERVATIONS",
        "rewards": "REWARDS",
        "actions": "ACTIONS",
    }[kind]
    return list(getattr(_native(), reg))


def _registered_events() -> dict[str, Any]:
    """rlexp's event registry with the built-in events loaded."""
    from rlexp.events import builtin  # noqa: F401  (registers the built-in events)
    from rlexp.events.manager import EVENT_FUNCS

    return EVENT_FUNCS


def _event_names() -> list[str]:
    """Registered event functions, plus record_video (the format's eval video) and its alias."""
    return sorted({"record_video", *EVENT_ALIASES, *_registered_events()})


def _record_video_params() -> set[str]:
    """Parameters record_video accepts: the format's, plus keyword ones of the registered function
    (for a class: of its ``__call__`` and ``finalize``)."""
    import inspect

    params = set(RECORD_VIDEO_PARAMS)
    func = _registered_events().get("record_video")
    if func is None:
        return params
    targets = (
        [func] if not isinstance(func, type) else [func.__call__, getattr(func, "finalize", None)]
    )
    for target in targets:
        if target is None:
            continue
        for p in inspect.signature(target).parameters.values():
            if p.kind in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD) and p.name not in (
                "self",
                "ctx",
            ):
                params.add(p.name)
    return params


def _task_spec(task: str) -> tuple[tuple[str, ...], int | None]:
    """(scene object uids, number of robot joints) of a native task."""
    spec = _native().get_task(task)
    return tuple(spec.objects), len(spec.robot_joints)


# ------------------------------------------------------------------------------------ env groups


def _conf_dir() -> Path:
    from rlexp.paths import CONF_DIR

    return CONF_DIR


def _env_yaml(group: str) -> dict[str, Any] | None:
    """conf/env/<group>.yaml as a plain dict (without its defaults list), or None."""
    from omegaconf import OmegaConf

    path = _conf_dir() / "env" / f"{group}.yaml"
    if not path.is_file():
        return None
    node = OmegaConf.to_container(OmegaConf.load(path), resolve=False)
    node.pop("defaults", None)
    return node


def _gym_ids() -> dict[str, str]:
    """Gymnasium ids of the env YAMLs -> their group (HalfCheetah-v5 -> half_cheetah)."""
    out = {}
    for path in sorted((_conf_dir() / "env").glob("*.yaml")):
        node = _env_yaml(path.stem) or {}
        if node.get("backend", "gymnasium") != "native" and isinstance(node.get("name"), str):
            out[node["name"]] = path.stem
    return out


# ------------------------------------------------------------------------------------- converting


@dataclass
class _Mapped:
    """What the two files say, as RootConfig leaves, plus what to tell the user."""

    env_group: str = ""  # conf/env group of the task ("" for a Gymnasium id without one)
    env_base: dict[str, Any] = field(default_factory=dict)  # env.* leaves of conf/env/<group>.yaml
    leaves: dict[str, Any] = field(default_factory=dict)  # dotted RootConfig leaves the files set
    # leaves whose value is the task YAML's dict with the file's entries added: the YAML's part
    yaml_parts: dict[str, dict[str, Any]] = field(default_factory=dict)
    not_applicable: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    action_dim: int | None = None
    groups: dict[str, str] = field(default_factory=dict)  # policy / algorithm group options


def _convert(
    train: dict[str, Any],
    gym: dict[str, Any],
    tf: _File,
    gf: _File,
    rlexp_env: dict[str, Any],
    escape: bool = False,
) -> _Mapped:
    """Check the two files' keys and values and map them onto RootConfig leaves (``escape``: every
    string the files give escaped for OmegaConf, see ``escape_interpolations``)."""
    tf.obj(train, "", TRAIN_SECTIONS)
    t = tf.obj(tf.get(train, "trainer", "", "object"), "trainer", TRAINER_KEYS)
    g = gf.obj(gym, "", GYM_KEYS)
    genv = gf.obj(gf.get(g, "env", "", "object", {}), "env", GYM_ENV_KEYS)
    m = _Mapped()
    _map_trainer(tf, gf, t, g, genv, m)
    _map_policy(tf, train, m)
    _map_algorithm(tf, train, m)
    _map_task(gf, g, genv, rlexp_env, m)
    if escape:
        m.leaves = {k: escape_interpolations(v) for k, v in m.leaves.items()}
    for key, base in m.yaml_parts.items():  # rlexp's own YAML is config, not data: not escaped
        m.leaves[key] = {**base, **m.leaves[key]}
    if m.not_applicable:
        m.notes.append(
            "accepted but not applicable to the MuJoCo CPU rebuild (ignored): "
            + ", ".join(m.not_applicable)
        )
    return m


def _map_trainer(
    tf: _File, gf: _File, t: dict[str, Any], g: dict[str, Any], genv: dict[str, Any], m: _Mapped
) -> None:
    """trainer.*: budget, evaluation, checkpoints, device, W&B, events."""
    out = m.leaves
    out["trainer.exp_name"] = tf.get(t, "exp_name", "trainer", "str", "generic_exp")
    out["seed"] = tf.get(t, "seed", "trainer", "int", 1, low=0)
    device = tf.get(t, "device", "trainer", "str", "cpu")
    if not re.fullmatch(r"auto|cpu|cuda(:\d+)?", device):
        raise tf.error(f"trainer.device={device!r}: choose cpu, cuda, cuda:N (or auto)")
    out["trainer.device"] = device
    kinds = {"headless": "bool", "enable_rt": "bool", "gpu_id": "int", "renderer": "str"}
    for key in TRAINER_NOT_APPLICABLE:
        if key in t:
            tf.get(t, key, "trainer", kinds[key])
            m.not_applicable.append(f"trainer.{key}")

    if "buffer_size" in t and "rollout_steps" in t:
        raise tf.error(
            "trainer.rollout_steps is the older name of trainer.buffer_size: give only buffer_size"
        )
    old = "rollout_steps" in t
    buffer_size = tf.get(
        t, "rollout_steps" if old else "buffer_size", "trainer", "int", 2048, low=1
    )
    if old:
        m.notes.append("trainer.rollout_steps read as trainer.buffer_size (its older name)")

    # num_envs: the train file's, else the task file's (top level, or inside env in older files), else 1
    num_envs, source = 1, None
    for f, d, where in ((gf, genv, "env"), (gf, g, ""), (tf, t, "trainer")):  # the last found wins
        if "num_envs" in d:
            num_envs = f.get(d, "num_envs", where, "int", low=1)
            source = f"{f.shown}: {_join(where, 'num_envs')}"
    if source is not None and "num_envs" not in t:
        m.notes.append(f"num_envs={num_envs} from the task file ({source})")
    out["env.num_envs"] = num_envs
    out["trainer.frames_per_batch"] = buffer_size * num_envs
    out["trainer.iterations"] = tf.get(t, "iterations", "trainer", "int", 250, low=1)

    enable_eval = tf.get(t, "enable_eval", "trainer", "bool", False)
    num_eval_envs = tf.get(t, "num_eval_envs", "trainer", "int", 4, low=1)
    num_eval_episodes = tf.get(t, "num_eval_episodes", "trainer", "int", 5, low=1)
    eval_freq = tf.get(t, "eval_freq", "trainer", "int", 10000, low=0)
    out["env.num_eval_envs"] = num_eval_envs if enable_eval else 0
    out["trainer.eval_every"] = eval_freq if enable_eval else 0
    out["trainer.eval_episodes"] = num_eval_episodes * num_eval_envs
    out["trainer.save_every"] = tf.get(t, "save_freq", "trainer", "int", 50000, low=0)
    out["logger.wandb.enabled"] = tf.get(t, "use_wandb", "trainer", "bool", False)
    if "wandb_project_name" in t:
        out["logger.wandb.project"] = tf.get(t, "wandb_project_name", "trainer", "str")

    events = tf.get(t, "events", "trainer", "object", {})
    events = tf.obj(events, "trainer.events", ("train", "eval"))
    for phase in ("train", "eval"):
        where = f"trainer.events.{phase}"
        out[f"events.{phase}"] = _events(
            tf, tf.get(events, phase, "trainer.events", "object", {}), where
        )


def _named_section(
    tf: _File,
    train: dict[str, Any],
    section: str,
    keys: tuple[str, ...],
    choices: tuple[str, ...],
    m: _Mapped,
) -> dict[str, Any]:
    """The ``policy`` / ``algorithm`` object: its keys checked, its ``name`` one rlexp supports
    (mapped to ``<section>.name``)."""
    obj = tf.obj(tf.get(train, section, "", "object"), section, keys)
    name = tf.get(obj, "name", section, "str", choices=choices)
    m.leaves[f"{section}.name"] = name
    m.groups[section] = GROUP_OPTIONS[section][name]
    return obj


def _map_policy(tf: _File, train: dict[str, Any], m: _Mapped) -> None:
    """policy.*: the actor's (and the actor-critic's critic's) MLP."""
    p = _named_section(tf, train, "policy", POLICY_KEYS, POLICIES, m)
    parts = ("actor", "critic") if m.leaves["policy.name"] == "actor_critic" else ("actor",)
    if "critic" in p and "critic" not in parts:
        m.notes.append(
            "warning: policy.critic is not used: policy.name='actor_only' has no critic (ignored)"
        )
    for part in parts:
        where = f"policy.{part}"
        net = tf.obj(tf.get(p, part, "policy", "object"), where, NET_KEYS)
        tf.get(net, "type", where, "str", "mlp", choices=NET_TYPES)
        cfg = tf.get(net, "network_cfg", where, "object")
        cfg = tf.obj(cfg, f"{where}.network_cfg", NETWORK_CFG_KEYS)
        m.leaves[f"{where}.hidden_sizes"] = tf.get(
            cfg, "hidden_sizes", f"{where}.network_cfg", "ints", low=1
        )
        m.leaves[f"{where}.activation"] = tf.get(
            cfg, "activation", f"{where}.network_cfg", "str", "relu", choices=ACTIVATIONS
        )
    m.action_dim = tf.get(p, "action_dim", "policy", "int", None, low=1)


def _map_algorithm(tf: _File, train: dict[str, Any], m: _Mapped) -> None:
    """algorithm.*: PPO's or GRPO's keyword arguments under rlexp's (TorchRL's) names."""
    a = _named_section(tf, train, "algorithm", ALGORITHM_KEYS, ALGORITHMS, m)
    name = m.leaves["algorithm.name"]
    format_keys = ALGORITHM_FORMAT_KEYS[name]
    c = tf.obj(tf.get(a, "cfg", "algorithm", "object", {}), "algorithm.cfg", tuple(format_keys))
    frames, num_envs = m.leaves["trainer.frames_per_batch"], m.leaves["env.num_envs"]
    if name == "ppo" and m.leaves["policy.name"] != "actor_critic":
        raise tf.error(
            f"algorithm.name='ppo' needs a critic, but policy.name={m.leaves['policy.name']!r} has "
            'none; use policy "actor_critic" (or algorithm "grpo")'
        )
    ranges: dict[str, tuple[str, float | None, float | None]] = {  # kind, low, high (low None: > 0)
        "learning_rate": ("number", 0.0, None),  # 0: a policy that does not learn (a baseline)
        "n_epochs": ("int", 1, None),
        "batch_size": ("int", 1, frames),
        "gamma": ("number", 0.0, 1.0),
        "gae_lambda": ("number", 0.0, 1.0),
        "clip_coef": ("number", None, None),
        "ent_coef": ("number", -math.inf, None),
        "vf_coef": ("number", 0.0, None),
        "max_grad_norm": ("number", -math.inf, None),
        "kl_coef": ("number", 0.0, None),
        "group_size": ("int", 2, None),
        "eps": ("number", None, None),
        "reset_every_rollout": ("bool", None, None),
        "truncate_at_first_done": ("bool", None, None),
    }
    batch = c.get("batch_size")
    if isinstance(batch, int) and not isinstance(batch, bool) and batch > frames:
        raise tf.error(
            f"algorithm.cfg.batch_size={batch} is larger than a rollout: trainer.buffer_size x "
            f"num_envs = {frames // num_envs} x {num_envs} = {frames}"
        )
    for key, (target, default) in format_keys.items():
        kind, low, high = ranges[key]
        positive = low is None and kind == "number"
        value = tf.get(c, key, "algorithm.cfg", kind, default, low, high, positive=positive)
        if target is not None:
            m.leaves[f"algorithm.{target}"] = value
    group = m.leaves.get("algorithm.group_size")
    if group is not None and num_envs % group:
        raise tf.error(
            f"algorithm.cfg.group_size={group} must divide trainer.num_envs={num_envs}: groups are "
            "blocks of consecutive envs"
        )


def _task_of(gf: _File, task_id: str, rlexp_env: dict[str, Any]) -> tuple[str, str | None]:
    """(env group, native task or None) of a task file's ``id``."""
    if task_id in TASK_IDS:
        return TASK_IDS[task_id], TASK_IDS[task_id]
    gym_ids = _gym_ids()
    if task_id in gym_ids:
        return gym_ids[task_id], None
    if rlexp_env.get("env.backend", "native") != "native":
        return "", None  # a Gymnasium id no env YAML has: the rlexp section says how to build it
    choices = [*TASK_IDS, *gym_ids]
    close = difflib.get_close_matches(task_id, choices, n=1)
    raise gf.error(
        f"id={task_id!r} is not a known task; choose from {choices}"
        + (f"; did you mean {close[0]!r}?" if close else "")
    )


def _map_task(
    gf: _File, g: dict[str, Any], genv: dict[str, Any], rlexp_env: dict[str, Any], m: _Mapped
) -> None:
    """The task file: env group, time limit, term sections (added to the YAML's), scene."""
    from rlexp.config.schema import EnvConfig

    out = m.leaves
    task_id = gf.get(g, "id", "", "str")
    group, task = _task_of(gf, task_id, rlexp_env)
    yaml_node = _env_yaml(group) if group else None
    base = yaml_node if yaml_node is not None else {}
    if task is not None:
        base.setdefault("name", task)
        base.setdefault("backend", "native")
        base.setdefault("native", {}).setdefault("task", task)
        out["env.backend"] = "native"
        out["env.native.task"] = task
    else:
        out["env.name"] = task_id
    m.env_group = group
    m.env_base = {f"env.{k}": v for k, v in flatten(base, EnvConfig).items()}
    out["env.max_episode_steps"] = gf.get(g, "max_episode_steps", "", "int", 300, low=1)
    if "max_episodes" in g:
        gf.get(g, "max_episodes", "", "int", low=0)
        m.not_applicable.append("max_episodes")

    terms = {
        kind: _terms(gf, gf.get(genv, kind, "env", "object", {}), kind, task is not None)
        for kind in ("events", "observations", "rewards", "actions")
    }
    extensions = gf.get(genv, "extensions", "env", "object", {})
    if task is None:
        if any(terms.values()) or extensions:
            raise gf.error(
                f"env terms apply to the native tasks {list(TASK_IDS)} only, not to {task_id!r}; "
                "leave env empty"
            )
        scene_keys = ("robot", "sensor", "light", "background", "rigid_object")
        m.not_applicable += [
            k for k in (*scene_keys, "rigid_object_group", "articulation") if g.get(k)
        ]
        return
    # The task's own terms (conf/env/<task>.yaml: e.g. CartPole's upright reward, which the task
    # defines and the users' file only adds a penalty to) stay; the file's terms are added, and
    # replace a YAML term of the same name.
    yaml_terms = (yaml_node or {}).get("native", {}) if yaml_node is not None else {}
    for kind, value in terms.items():
        out[f"env.native.{kind}"] = value
        m.yaml_parts[f"env.native.{kind}"] = dict(yaml_terms.get(kind) or {})
    out["env.native.extensions"] = extensions
    out["env.native.scene"] = _scene(gf, g, task, m.not_applicable)
    m.yaml_parts["env.native.scene"] = dict(m.env_base.get("env.native.scene") or {})
    if yaml_node is not None:
        kept = [
            f"{kind}.{name}"
            for kind in terms
            for name in (yaml_terms.get(kind) or {})
            if name not in terms[kind]
        ]
        if kept:
            m.notes.append(
                f"task terms of conf/env/{group}.yaml kept beside the file's: " + ", ".join(kept)
            )


def _events(tf: _File, events: dict[str, Any], where: str) -> dict[str, Any]:
    """The trainer's train / eval events as EventTermConfig dicts (format aliases resolved)."""
    from rlexp.events import MODES

    known = _event_names()
    out = {}
    for name, ev in events.items():
        w = f"{where}.{name}"
        ev = tf.obj(ev, w, EVENT_TERM_KEYS)
        func = tf.get(ev, "func", w, "str")
        if func not in known and "." not in func:
            close = difflib.get_close_matches(func, known, n=1)
            raise tf.error(
                f"{w}.func={func!r} is not a known event function; choose from {known}"
                + (f"; did you mean {close[0]!r}?" if close else "")
            )
        if "." in func:
            from rlexp.events.manager import resolve_event_func

            try:
                resolve_event_func(func, w)
            except ValueError as exc:
                raise tf.error(str(exc)) from None
        func = EVENT_ALIASES.get(func, func)
        params = tf.get(ev, "params", w, "object", {})
        if func == "record_video":
            _check_record_video(tf, params, f"{w}.params")
        out[name] = {
            "func": func,
            "mode": tf.get(ev, "mode", w, "str", "reset", choices=MODES),
            "interval_step": tf.get(ev, "interval_step", w, "int", 1, low=1),
            "params": params,
        }
    return out


def _check_record_video(tf: _File, params: dict[str, Any], where: str) -> None:
    known = tuple(sorted(_record_video_params()))
    tf.obj(params, where, known)
    shapes = {
        "resolution": ("ints", 2),
        "eye": ("numbers", 3),
        "target": ("numbers", 3),
        "up": ("numbers", 3),
        "intrinsics": ("numbers", 4),
    }
    for key, (kind, n) in shapes.items():
        if key in params:
            value = tf.get(params, key, where, kind, positive=key == "resolution")
            if len(value) != n:
                raise tf.error(f"{where}.{key}={_show(params[key])} must have {n} values")
    for key in ("name", "save_path"):
        if key in params:
            tf.get(params, key, where, "str")


def _terms(gf: _File, terms: dict[str, Any], kind: str, native: bool) -> dict[str, Any]:
    """One kind of task term (env.events / observations / rewards / actions) as schema dicts."""
    keys, defaults, modes = TERM_KEYS[kind]
    names = _term_registry(kind) if native else None
    out = {}
    for name, term in terms.items():
        w = f"env.{kind}.{name}"
        term = gf.obj(term, w, keys)
        func = gf.get(term, "func", w, "str")
        if names is not None and func not in names:
            close = difflib.get_close_matches(func, names, n=1)
            raise gf.error(
                f"{w}.func={func!r} is not a known {kind[:-1]} term; choose from {sorted(names)}"
                + (f"; did you mean {close[0]!r}?" if close else "")
            )
        entry: dict[str, Any] = {"func": func}
        if "mode" in keys:
            entry["mode"] = gf.get(term, "mode", w, "str", defaults["mode"], choices=modes)
        if kind == "events":
            entry["interval_step"] = gf.get(term, "interval_step", w, "int", 1, low=1)
        if kind == "observations":
            obs_name = gf.get(term, "name", w, "str")
            if not re.fullmatch(r"[^/]+/[^/]+", obs_name):
                raise gf.error(f"{w}.name={obs_name!r} must be 'group/key' (e.g. 'robot/qpos')")
            entry["name"] = obs_name
        if kind == "rewards":
            entry["weight"] = gf.get(term, "weight", w, "number", 1.0)
        entry["params"] = gf.get(term, "params", w, "object", {})
        out[name] = entry
    return out


def _scene(gf: _File, g: dict[str, Any], task: str, na: list[str]) -> dict[str, Any]:
    """The parts of robot / rigid_object that shape the rebuild, as env.native.scene overrides:
    ``init_qpos``, ``<uid>_init_pos``, ``<uid>_size``, ``<uid>_mass``, ``<uid>_friction``."""
    objects, num_joints = _task_spec(task)
    scene: dict[str, Any] = {}
    robot = gf.obj(gf.get(g, "robot", "", "object", {}), "robot")
    for key in sorted(robot):
        if key == "init_qpos":
            qpos = gf.get(robot, "init_qpos", "robot", "numbers")
            if num_joints is not None and len(qpos) < num_joints:
                raise gf.error(
                    f"robot.init_qpos has {len(qpos)} values; the {task} rebuild has {num_joints} robot joints"
                )
            if num_joints is not None and len(qpos) > num_joints:
                na.append(
                    f"robot.init_qpos[{num_joints}:] (joints the {task} rebuild does not have)"
                )
                qpos = qpos[:num_joints]
            scene["init_qpos"] = qpos
        elif key != "uid" and robot[key] not in ({}, [], None, ""):
            na.append(f"robot.{key}")
    for key in ("sensor", "background", "rigid_object_group", "articulation"):
        if gf.get(g, key, "", "list", []):
            na.append(key)
    if gf.get(g, "light", "", "object", {}):
        na.append("light")
    for i, obj in enumerate(gf.get(g, "rigid_object", "", "list", [])):
        w = f"rigid_object[{i}]"
        obj = gf.obj(obj, w)
        uid = gf.get(obj, "uid", w, "str")
        if uid not in objects:
            na.append(f"{w} (uid {uid!r}: the {task} rebuild has objects {list(objects)})")
            continue
        for key in sorted(obj):
            if key == "init_pos":
                pos = gf.get(obj, "init_pos", w, "numbers")
                if len(pos) != 3:
                    raise gf.error(f"{w}.init_pos={_show(pos)} must have 3 values")
                scene[f"{uid}_init_pos"] = pos
            elif key == "shape":
                shape = gf.obj(obj["shape"], f"{w}.shape")
                stype = gf.get(shape, "shape_type", f"{w}.shape", "str", "Cube")
                if stype != "Cube":
                    raise gf.error(
                        f"{w}.shape.shape_type={stype!r}: the {task} rebuild's {uid} is a Cube"
                    )
                if "size" in shape:
                    size = gf.get(shape, "size", f"{w}.shape", "numbers", positive=True)
                    if len(size) != 3:
                        raise gf.error(f"{w}.shape.size={_show(size)} must have 3 values")
                    scene[f"{uid}_size"] = size
                na.extend(f"{w}.shape.{k}" for k in shape if k not in ("shape_type", "size"))
            elif key == "attrs":
                attrs = gf.obj(obj["attrs"], f"{w}.attrs")
                if "mass" in attrs:
                    scene[f"{uid}_mass"] = gf.get(
                        attrs, "mass", f"{w}.attrs", "number", positive=True
                    )
                # MuJoCo has one Coulomb coefficient: the sliding (dynamic) one, as a pushed cube slides
                for k in ("dynamic_friction", "static_friction"):
                    if k in attrs:
                        scene[f"{uid}_friction"] = [
                            gf.get(attrs, k, f"{w}.attrs", "number", low=0.0)
                        ]
                        break
                if "dynamic_friction" in attrs and "static_friction" in attrs:
                    gf.get(attrs, "static_friction", f"{w}.attrs", "number", low=0.0)
                    na.append(
                        f"{w}.attrs.static_friction (MuJoCo has one coefficient: dynamic_friction is used)"
                    )
                na.extend(
                    f"{w}.attrs.{k}"
                    for k in attrs
                    if k not in ("mass", "static_friction", "dynamic_friction")
                )
            elif key == "body_type":
                if gf.get(obj, "body_type", w, "str") != "dynamic":
                    na.append(f"{w}.body_type")
            elif key != "uid":
                na.append(f"{w}.{key}")
    return scene


# ---------------------------------------------------------------------------------------- loading


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


# ----------------------------------------------------------------------------------- writing back


def _plain(config: RootConfig) -> dict[str, Any]:
    """``config`` as plain dicts, strings as they are: not through OmegaConf, which would read a
    ``"${...}"`` in a value (data, from a file) as an interpolation and resolve it."""
    return dataclasses.asdict(config)


def _task_id(env: Any) -> str:
    if env.backend == "native" and env.native is not None:
        for task_id, task in TASK_IDS.items():
            if task == env.native.task:
                return task_id
        return env.native.task
    return env.name


def _format_dicts(config: RootConfig) -> tuple[dict[str, Any], dict[str, Any]]:
    """The format's keys for ``config`` (no ``rlexp`` section)."""
    t, e, p, a, lg = config.trainer, config.env, config.policy, config.algorithm, config.logger
    d = _plain(config)
    trainer: dict[str, Any] = {
        "exp_name": t.exp_name,
        "gym_config": "gym_config.json",
        "seed": config.seed,
        "device": t.device,
        "num_envs": e.num_envs,
        "iterations": t.iterations
        if t.iterations is not None
        else max(1, -(-t.total_frames // t.frames_per_batch)),
        "buffer_size": t.frames_per_batch // e.num_envs,
        "enable_eval": e.num_eval_envs > 0,
    }
    if e.num_eval_envs > 0:
        trainer["num_eval_envs"] = e.num_eval_envs
        trainer["num_eval_episodes"] = max(1, -(-t.eval_episodes // e.num_eval_envs))
        trainer["eval_freq"] = t.eval_every
    trainer["save_freq"] = t.save_every
    trainer["use_wandb"] = lg.wandb.enabled
    trainer["wandb_project_name"] = lg.wandb.project
    reverse = {v: k for k, v in EVENT_ALIASES.items()}
    trainer["events"] = {
        phase: {
            name: {**ev, "func": reverse.get(ev["func"], ev["func"])}
            for name, ev in d["events"][phase].items()
        }
        for phase in ("train", "eval")
    }
    policy = {"name": p.name}
    for part in ("actor", "critic"):
        net = getattr(p, part, None)
        if net is None:  # actor_only: no critic
            continue
        policy[part] = {
            "type": "mlp",
            "network_cfg": {"hidden_sizes": list(net.hidden_sizes), "activation": net.activation},
        }
    algorithm = {
        "name": a.name,
        "cfg": {
            key: getattr(a, target)
            for key, (target, _) in ALGORITHM_FORMAT_KEYS[a.name].items()
            if target is not None
        },
    }
    train = {"trainer": trainer, "policy": policy, "algorithm": algorithm}

    gym: dict[str, Any] = {"id": _task_id(e)}
    if e.max_episode_steps is not None:
        gym["max_episode_steps"] = e.max_episode_steps
    gym["num_envs"] = e.num_envs
    if e.backend == "native" and e.native is not None:
        nd = d["env"]["native"]
        gym["env"] = {
            k: nd[k] for k in ("events", "observations", "rewards", "actions", "extensions")
        }
        scene = dict(nd.get("scene") or {})
        if "init_qpos" in scene:
            gym["robot"] = {"init_qpos": scene["init_qpos"]}
        uids = sorted(
            {
                k.rsplit("_", 1)[0]
                for k in scene
                if k != "init_qpos" and k.endswith(("_size", "_mass", "_friction"))
            }
            | {k[: -len("_init_pos")] for k in scene if k.endswith("_init_pos")}
        )
        objects = []
        for uid in uids:
            obj: dict[str, Any] = {"uid": uid}
            if f"{uid}_size" in scene:
                obj["shape"] = {"shape_type": "Cube", "size": scene[f"{uid}_size"]}
            obj["body_type"] = "dynamic"
            if f"{uid}_init_pos" in scene:
                obj["init_pos"] = scene[f"{uid}_init_pos"]
            attrs = {}
            if f"{uid}_mass" in scene:
                attrs["mass"] = scene[f"{uid}_mass"]
            friction = scene.get(f"{uid}_friction")
            if isinstance(friction, list) and len(friction) == 1:
                attrs["dynamic_friction"] = friction[0]
            if attrs:
                obj["attrs"] = attrs
            objects.append(obj)
        if objects:
            gym["rigid_object"] = objects
    return train, gym


def to_json_experiment(config: RootConfig) -> tuple[dict[str, Any], dict[str, Any]]:
    """(train file, task file) dicts in the format that load back to exactly ``config``: the format's
    keys, plus an ``rlexp`` section with every other config key (and any the format rounds)."""
    from rlexp.config.schema import RootConfig

    train, gym = _format_dicts(config)
    env_backend = {"env.backend": config.env.backend}
    mapped = _convert(
        json.loads(json.dumps(train)),
        json.loads(json.dumps(gym)),
        _File("train_config.json"),
        _File("gym_config.json"),
        env_backend,
    )
    leaves = flatten(_plain(config), RootConfig)
    extra = {
        k: v for k, v in leaves.items() if k not in mapped.leaves or not _same(mapped.leaves[k], v)
    }
    if extra:
        train["rlexp"] = nest(extra)
    return train, gym


def _same(a: Any, b: Any) -> bool:
    """Equal as JSON values (1 == 1.0, but True != 1)."""
    if isinstance(a, bool) or isinstance(b, bool):
        return type(a) is type(b) and a == b
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, float) or isinstance(b, float):
        return (
            isinstance(a, (int, float))
            and isinstance(b, (int, float))
            and (a == b or (math.isnan(a) and math.isnan(b)))
        )
    return a == b


def dumps(value: Any, indent: int = 0) -> str:
    """JSON with objects one key a line and lists of plain values on one line (as the users' files)."""
    pad, inner = "  " * indent, "  " * (indent + 1)
    if isinstance(value, dict) and value:
        items = [f"{inner}{json.dumps(str(k))}: {dumps(v, indent + 1)}" for k, v in value.items()]
        return "{\n" + ",\n".join(items) + f"\n{pad}}}"
    if isinstance(value, list) and any(isinstance(v, (dict, list)) for v in value):
        return "[\n" + ",\n".join(f"{inner}{dumps(v, indent + 1)}" for v in value) + f"\n{pad}]"
    return json.dumps(value)


def write_json_experiment(config: RootConfig, run_dir: Path) -> None:
    """Write ``train_config.json`` + ``gym_config.json`` (the resolved config in the users' format)
    into ``run_dir``; a config the format cannot express is logged, not fatal."""
    try:
        train, gym = to_json_experiment(config)
    except ConfigError as exc:
        log.warning("config not written as JSON (train_config.json): %s", exc)
        return
    (Path(run_dir) / "train_config.json").write_text(dumps(train) + "\n")
    (Path(run_dir) / "gym_config.json").write_text(dumps(gym) + "\n")
