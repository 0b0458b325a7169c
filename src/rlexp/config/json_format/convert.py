"""Both files' keys and values checked and mapped onto RootConfig leaves (``_convert``): the one
mapping that loading a file pair and writing a config back out share."""

from __future__ import annotations

from typing import Any

from rlexp.config.json_format.leaves import _Mapped
from rlexp.config.json_format.task_section import GYM_ENV_KEYS, GYM_KEYS, _map_task
from rlexp.config.json_format.train_section import (
    TRAIN_SECTIONS,
    TRAINER_KEYS,
    _map_algorithm,
    _map_policy,
    _map_trainer,
)
from rlexp.config.json_format.typed_reads import _File
from rlexp.config.validate import escape_interpolations


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
