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
    xs = {module}.inputs(obs)            # every input of the file by name: {names}
    xs = {module}.inputs(obs, info=info)  # with an action mask from info["action_mask"]
    action = {module}.env_action(y[0])   # one row of the file's output -> what env.step() takes

Images are uint8 [n, C, H, W] (the file scales them); FRAME_STACK > 1: the file was trained on the
env's last FRAME_STACK frames of each image (env.frame_stack), which a deployment keeps itself:
obs = stack.reset(obs) / stack.step(obs) with stack = {module}.FrameStack().

MEMORY (a recurrent policy; None otherwise): the file also takes its state after the inputs and
returns the next one after the action; state = {module}.initial_state() at an episode's start,
then feed {{**xs, **state}} and keep the outputs as the next state (docs/export.md).
"""

from collections import deque

import numpy as np

ENV_ID = {env_id!r}
DIM = {dim}
#: The actor's vector parts in layout order (Dict keys sorted by str(key), depth-first; a part's
#: key is its path joined with "/"); what only the critic read is not here.
PARTS = {parts!r}
#: The file's inputs in order (name, kind, key, dtype, shape; an image's part says its layout).
INPUTS = {inputs!r}
FRAME_STACK = {frame_stack!r}
ACTION = {action!r}
#: A recurrent policy's state (the export metadata's memory): inputs named "name" after INPUTS,
#: outputs named "output" after the action; zeros at an episode's start. None: no memory.
MEMORY = {memory!r}


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
        if part.get("indices"):  # env.observation_indices: the Box entries kept, in this order
            columns.append(x.reshape(n, -1)[:, part["indices"]].astype(np.float32))
            continue
        if part["kind"] in ("box", "multi_binary"):
            columns.append(x.reshape(n, part["size"]).astype(np.float32))
            continue
        index = x.reshape(n, -1).astype(np.int64) - np.asarray(part["start"], dtype=np.int64)
        offsets = np.concatenate([[0], np.cumsum(part["nvec"])[:-1]]).astype(np.int64)
        one_hot = np.zeros((n, part["size"]), dtype=np.float32)
        one_hot[np.arange(n)[:, None], offsets + index] = 1.0
        columns.append(one_hot)
    return np.concatenate(columns, axis=1)


def image(obs, part, batch=False):
    """An image leaf (``part``: an image part record) as the file's uint8 [n, C, H, W]."""
    x = np.asarray(_leaf(obs, part["key"]), dtype=np.uint8)
    if not batch:
        x = x[None]
    n, (c, h, w) = x.shape[0], part["shape"]
    source = part["source_layout"]
    if source == "hw":
        x = x[:, None]
    elif source in ("hwc", "stack_hwc"):
        x = np.moveaxis(x, -1, -3)
    return np.ascontiguousarray(x.reshape(n, c, h, w))


def action_mask(obs, info=None, batch=False):
    """The file's action_mask input, bool [n, sum(nvec)], from info[key] (source info: pass the
    info env.reset() / env.step() returned) or the observation's Dict key (source observation)."""
    spec = next(s for s in INPUTS if s["kind"] == "action_mask")
    if spec["source"] == "info":
        if info is None or spec["mask_key"] not in info:
            raise ValueError(
                "this file takes the action mask of info[%r]: call inputs(obs, info=info)"
                % spec["mask_key"]
            )
        x = np.asarray(info[spec["mask_key"]])
    else:
        x = np.asarray(_leaf(obs, spec["mask_key"]))
    return x.reshape(-1 if batch else 1, spec["shape"][1]).astype(bool)


def inputs(obs, batch=False, info=None):
    """The observation (and, for an action mask from info, the step's info) -> {{input name:
    array}} for every input of the file (the actor's only)."""
    out = {{}}
    for spec in INPUTS:
        if spec["kind"] == "vector":
            out[spec["name"]] = flatten(obs, batch)
        elif spec["kind"] == "action_mask":
            out[spec["name"]] = action_mask(obs, info, batch)
        else:
            out[spec["name"]] = image(obs, spec["parts"][0], batch)
    return out


def initial_state(n=1):
    """A recurrent file's state at an episode's start for n envs: {{name: float32 zeros [n, ...]}}
    ({{}} without memory)."""
    if MEMORY is None:
        return {{}}
    return {{s["name"]: np.zeros((n, *s["shape"][1:]), np.float32) for s in MEMORY["state"]}}


def reset_state(state, done):
    """The state with the envs whose episode ended (done: bool [n]) back at zeros."""
    done = np.asarray(done, dtype=bool).reshape(-1, 1, 1)
    return {{k: np.where(done, np.float32(0), v).astype(np.float32) for k, v in state.items()}}


class FrameStack:
    """The last FRAME_STACK frames of each image leaf, stacked on a new first axis (one env;
    newest last; reset fills the stack with its first frame), as rlexp stacked them in training."""

    def __init__(self, n=FRAME_STACK):
        self.n = n
        self.keys = [s["parts"][0]["key"] for s in INPUTS if s["kind"] == "image"]
        self.frames = {{}}

    def reset(self, obs):
        self.frames = {{k: deque([np.array(_leaf(obs, k))] * self.n, self.n) for k in self.keys}}
        return self._current(obs)

    def step(self, obs):
        for k in self.keys:
            self.frames[k].append(np.array(_leaf(obs, k)))
        return self._current(obs)

    def _current(self, obs):
        for k in self.keys:
            frames = list(self.frames[k])
            stacked = np.concatenate(frames) if frames[0].ndim == 4 else np.stack(frames)
            obs = _replace(obs, k.split("/") if k else [], stacked)
        return obs


def _replace(obs, path, value):
    if not path:
        return value
    if isinstance(obs, (tuple, list)):
        i = int(path[0])
        return type(obs)(_replace(v, path[1:], value) if j == i else v for j, v in enumerate(obs))
    return {{k: _replace(v, path[1:], value) if str(k) == path[0] else v for k, v in obs.items()}}


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


def helper_source(
    target: Path,
    env_id: str,
    layout: dict[str, Any],
    action: dict[str, Any],
    inputs: list[dict[str, Any]] | None = None,
    memory: dict[str, Any] | None = None,
) -> str:
    """The helper's text for ``layout`` (``ObsLayout.record()``), ``action`` (the metadata's
    ``action_space``), ``inputs`` (the metadata's: the actor's; None: the whole vector) and
    ``memory`` (the metadata's: a recurrent policy's state; None: none)."""
    if inputs is None:
        vector = [p for p in layout["parts"] if p["kind"] != "image"]
        inputs = [{"name": "observation", "kind": "vector", "parts": vector}]
    vector = next((i["parts"] for i in inputs if i["kind"] == "vector"), [])
    return _TEMPLATE.format(
        env_id=env_id,
        file=target.name,
        module=helper_name(target)[:-3],
        dim=sum(p["size"] for p in vector),
        names=[i["name"] for i in inputs],
        parts=vector,
        inputs=inputs,
        frame_stack=int(layout.get("frame_stack", 1)),
        action=action,
        memory=memory,
    )


def check_helper(
    path: Path, samples: list[tuple[Any, Any]], infos: list[Any] | None = None
) -> None:
    """``ValueError`` unless the helper at ``path`` gives each observation of ``samples``
    (``(observation, {input name: rlexp's array})`` pairs; ``infos``: each one's info, where an
    action mask comes from it) the inputs rlexp gives it, one at a time and as a batch."""
    helper = runpy.run_path(str(path))
    infos = infos or [None] * len(samples)
    info_batch = _stack(infos) if infos[0] is not None else None
    batched = helper["inputs"](_stack([obs for obs, _ in samples]), batch=True, info=info_batch)
    for name in samples[0][1]:
        want = np.stack([np.asarray(arrays[name]) for _, arrays in samples])
        got = np.concatenate(
            [
                helper["inputs"](obs, info=i)[name]
                for (obs, _), i in zip(samples, infos, strict=True)
            ]
        )
        if not (
            got.dtype == want.dtype
            and np.array_equal(got, want)
            and np.array_equal(batched[name], want)
        ):
            raise ValueError(
                f"the observation helper {str(path)!r} does not give the input {name!r} as rlexp "
                "does; please report it"
            )


def rlexp_inputs(encoded: Any, inputs: list[dict[str, Any]]) -> dict[str, np.ndarray]:
    """The file's inputs as rlexp makes them from one observation as its env emits it
    (``ObsLayout.encode``: the flat vector, or a dict of ``vector`` and images): the actor's
    columns of the vector, its images by key."""
    out = {}
    for spec in inputs:
        if spec["kind"] == "vector":
            vector = encoded if isinstance(encoded, np.ndarray) else encoded["vector"]
            cols = [i for p in spec["parts"] for i in range(p["offset"], p["offset"] + p["size"])]
            out[spec["name"]] = np.asarray(vector, dtype=np.float32)[cols]
        else:
            out[spec["name"]] = np.asarray(encoded[spec["key"]])
    return out


def _stack(samples: list[Any]) -> Any:
    """Dict observations stacked leaf by leaf (a vector env's batched observation)."""
    if isinstance(samples[0], dict):
        return {k: _stack([s[k] for s in samples]) for k in samples[0]}
    if isinstance(samples[0], tuple):
        return tuple(_stack([s[i] for s in samples]) for i in range(len(samples[0])))
    return np.stack([np.asarray(s) for s in samples])
