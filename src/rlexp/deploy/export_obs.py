"""The observation helper ``rlexp export`` writes beside an exported file of a Gymnasium env: a small
``.py`` that needs numpy only (no rlexp, no torch) and turns the env's observation, as the env
returns it (a Dict, a Tuple, a Discrete index, ...), into the file's float32 input, and the file's
output into the action the env takes (docs/export.md, "Deploying"). Its tables are the metadata's
``observation_layout`` and ``action_space``; ``check_helper`` runs it against rlexp's own flattening
before the export reports success.
"""

from __future__ import annotations

import re
import runpy
from pathlib import Path
from typing import Any

import numpy as np

_TEMPLATE = '''"""{env_id}: its observations as the input of {file}, that file's output as its actions.

Written by `rlexp export` (numpy only: no rlexp, no torch needed). The tables are the export
metadata's observation_layout and action_space ({file}.json).

    import {module}
    x = {module}.flatten(obs)            # obs as env.reset() / env.step() give it -> float32 [1, {dim}]
    x = {module}.flatten(obs, batch=True)  # a vector env's batched obs -> float32 [n, {dim}]
    action = {module}.env_action(y[0])   # one row of the file's output -> what env.step() takes
"""

import numpy as np

ENV_ID = {env_id!r}
DIM = {dim}
#: Dict keys sorted by str(key), depth-first; a part's key is its path joined with "/".
PARTS = {parts!r}
ACTION = {action!r}


def _leaf(obs, key):
    if not key:
        return obs
    for name in key.split("/"):
        if isinstance(obs, (tuple, list)):
            obs = obs[int(name)]
        elif name in obs:
            obs = obs[name]
        else:  # a non-str key: matched by str()
            obs = next(v for k, v in obs.items() if str(k) == name)
    return obs


def flatten(obs, batch=False):
    """The observation (batch=True: every leaf with a leading batch axis) -> float32 [n, DIM]."""
    columns = []
    for part in PARTS:
        x = np.asarray(_leaf(obs, part["key"]))
        if not batch:
            x = x[None]
        n = x.shape[0]
        if part["kind"] in ("box", "multi_binary"):
            columns.append(x.reshape(n, part["size"]).astype(np.float32))
            continue
        index = x.reshape(n, -1).astype(np.int64) - np.asarray(part["start"], dtype=np.int64)
        offsets = np.concatenate([[0], np.cumsum(part["nvec"])[:-1]]).astype(np.int64)
        one_hot = np.zeros((n, part["size"]), dtype=np.float32)
        one_hot[np.arange(n)[:, None], offsets + index] = 1.0
        columns.append(one_hot)
    return np.concatenate(columns, axis=1)


def env_action(y, batch=False):
    """The file's output (one row; batch=True: every row) -> the action env.step() takes."""
    y = np.asarray(y)
    shape = tuple(ACTION["shape"])
    if ACTION["kind"] == "box":  # float64, as rlexp hands Box actions to the env
        y = y.astype(np.float64)
        return y.reshape(-1, *shape) if batch else y.reshape(shape)
    if ACTION["kind"] == "discrete":
        column = y.reshape(-1, 1)[:, 0].astype(ACTION["dtype"])
        return column if batch else int(column[0])
    y = y.astype(ACTION["dtype"])
    return y.reshape(-1, *shape) if batch else y.reshape(shape)
'''


def helper_name(target: Path) -> str:
    """The helper's file name for the exported file ``target``: an importable module name made
    of the file's name (``best.pt`` -> ``best_pt_obs.py``; a .pt and an .onnx do not share one)."""
    base = re.sub(r"\W", "_", target.name)
    return ("_" if base[0].isdigit() else "") + base + "_obs.py"


def helper_source(target: Path, env_id: str, layout: dict[str, Any], action: dict[str, Any]) -> str:
    """The helper's text for ``layout`` (``ObsLayout.record()``) and ``action`` (the metadata's
    ``action_space``)."""
    return _TEMPLATE.format(
        env_id=env_id,
        file=target.name,
        module=helper_name(target)[:-3],
        dim=layout["dim"],
        parts=layout["parts"],
        action=action,
    )


def check_helper(path: Path, samples: list[tuple[Any, Any]]) -> None:
    """``ValueError`` unless the helper at ``path`` flattens each observation of ``samples``
    (``(observation, rlexp's flat vector)`` pairs) as rlexp does, one at a time and as a batch."""
    helper = runpy.run_path(str(path))
    want = np.stack([np.asarray(flat, dtype=np.float32) for _, flat in samples])
    got = np.concatenate([helper["flatten"](obs) for obs, _ in samples])
    batched = helper["flatten"](_stack([obs for obs, _ in samples]), batch=True)
    if not (np.array_equal(got, want) and np.array_equal(batched, want)):
        raise ValueError(
            f"the observation helper {str(path)!r} does not flatten as rlexp does; please report it"
        )


def _stack(samples: list[Any]) -> Any:
    """Dict observations stacked leaf by leaf (a vector env's batched observation)."""
    if isinstance(samples[0], dict):
        return {k: _stack([s[k] for s in samples]) for k in samples[0]}
    if isinstance(samples[0], tuple):
        return tuple(_stack([s[i] for s in samples]) for i in range(len(samples[0])))
    return np.stack([np.asarray(s) for s in samples])
