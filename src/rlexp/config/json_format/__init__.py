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

The package, one role a module (each imports only modules listed above it):

- ``reading``: a file's text, its size and nesting limits, strict JSON parsing (``read_json``)
- ``typed_reads``: ``_File``, typed reads of one file's values, errors naming the dotted key
- ``leaves``: RootConfig leaves (``flatten`` / ``nest`` / ``_overlay``) and ``_Mapped``
- ``trainer_events``: ``trainer.events`` checked against rlexp's event registry
- ``train_section``: the ``trainer`` / ``policy`` / ``algorithm`` keys (PPO_KEYS, GRPO_KEYS), mapped
- ``task_section``: the task file (id, terms, scene), mapped onto ``env.*``
- ``convert``: both files mapped onto RootConfig leaves; loading and writing share it
- ``loading``: ``find_task_file``, the ``rlexp`` section, ``load_json_experiment``
- ``writing``: ``to_json_experiment``, ``dumps``, ``write_json_experiment``

Part of ``config`` (layer 1). May import: layers 0-1; the events and native-task registries lazily,
to check names (the exception tests/test_structure.py lists).
"""

from rlexp.config.json_format.leaves import (
    flatten,
    nest,
)
from rlexp.config.json_format.loading import (
    FORMAT_LOGGER,
    LOGGER_SWITCHES,
    JsonExperiment,
    default_root_config,
    find_task_file,
    load_json_experiment,
)
from rlexp.config.json_format.reading import (
    MAX_DEPTH,
    MAX_FILE_BYTES,
    read_json,
)
from rlexp.config.json_format.task_section import (
    GYM_ENV_KEYS,
    GYM_KEYS,
    TASK_IDS,
    TERM_KEYS,
)
from rlexp.config.json_format.train_section import (
    ACTIVATIONS,
    ALGORITHM_FORMAT_KEYS,
    ALGORITHM_KEYS,
    ALGORITHMS,
    GROUP_OPTIONS,
    GRPO_KEYS,
    NET_KEYS,
    NET_TYPES,
    NETWORK_CFG_KEYS,
    POLICIES,
    POLICY_KEYS,
    PPO_KEYS,
    TRAIN_SECTIONS,
    TRAINER_KEYS,
    TRAINER_NOT_APPLICABLE,
)
from rlexp.config.json_format.trainer_events import (
    EVENT_ALIASES,
    EVENT_TERM_KEYS,
    RECORD_VIDEO_PARAMS,
)
from rlexp.config.json_format.writing import (
    dumps,
    to_json_experiment,
    write_json_experiment,
)
from rlexp.config.validate import ConfigError, escape_interpolations

__all__ = [
    "ACTIVATIONS",
    "ALGORITHMS",
    "ALGORITHM_FORMAT_KEYS",
    "ALGORITHM_KEYS",
    "ConfigError",
    "EVENT_ALIASES",
    "EVENT_TERM_KEYS",
    "FORMAT_LOGGER",
    "GROUP_OPTIONS",
    "GRPO_KEYS",
    "GYM_ENV_KEYS",
    "GYM_KEYS",
    "JsonExperiment",
    "LOGGER_SWITCHES",
    "MAX_DEPTH",
    "MAX_FILE_BYTES",
    "NETWORK_CFG_KEYS",
    "NET_KEYS",
    "NET_TYPES",
    "POLICIES",
    "POLICY_KEYS",
    "PPO_KEYS",
    "RECORD_VIDEO_PARAMS",
    "TASK_IDS",
    "TERM_KEYS",
    "TRAINER_KEYS",
    "TRAINER_NOT_APPLICABLE",
    "TRAIN_SECTIONS",
    "default_root_config",
    "dumps",
    "escape_interpolations",
    "find_task_file",
    "flatten",
    "load_json_experiment",
    "nest",
    "read_json",
    "to_json_experiment",
    "write_json_experiment",
]
