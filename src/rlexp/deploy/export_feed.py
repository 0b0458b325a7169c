"""``rlexp eval`` of an exported file: the env's observation -> the file's inputs (the actor's only).

The metadata's ``inputs`` name the observation parts the actor reads (key, kind, shape). They are
looked up by key in the layout of the env ``rlexp eval`` builds, which may lack what only the critic
read (a deployment env without privileged state): the actor's vector columns are gathered from the
env's vector, its images taken by their TensorDict key; the critic's parts are never read. A part the
actor reads that the env does not give, or gives in another shape, is one line naming it.

Exports made before ``inputs`` existed take the env's whole flat vector, checked as they were.

``ExportedPolicy`` is the file acting in the eval loop: the action as the run's env takes it, and for
a recurrent policy (metadata ``memory``) the state carried from step to step, zeros at each
episode's start (``episodes_ended``).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
from tensordict import TensorDictBase

#: The fields of a part record that must agree between the export and the env (not its offset).
_SAME = ("kind", "shape", "size", "nvec", "start")


def actor_feed(meta: dict[str, Any], env: Any, where: str) -> Callable[[Any], list[torch.Tensor]]:
    """The function ``observation -> [the file's inputs]`` for ``env``; ``ValueError`` (one line)
    when the env does not give what the actor reads."""
    if not meta.get("inputs"):
        return _whole_vector(meta, env, where)
    from rlexp.policies.inputs import layout_of

    layout = layout_of(env)
    parts = {p.key: p for p in layout.parts if p.kind != "image"}
    images = {p.image_key: p for p in layout.images}
    index: list[int] | None = None
    keys: list[str] = []
    mask_key: str | None = None  # the action mask's entry (last input), where the file takes one
    for spec in meta["inputs"]:
        if spec["kind"] == "vector":
            index = []
            for saved in spec["parts"]:
                part = parts.get(saved["key"])
                _check_part(saved, part, where, sorted(parts))
                index += range(part.offset, part.offset + part.size)
        elif spec["kind"] == "action_mask":
            _check_mask(spec, getattr(layout, "mask", None), where)
            mask_key = spec["key"]
        else:
            part = images.get(spec["key"])
            _check_part(spec["parts"][0], part, where, sorted(images))
            keys.append(spec["key"])
    gather = None
    if index is not None and index != list(range(layout.dim)):
        gather = torch.tensor(index, dtype=torch.long)

    def feed(obs: Any) -> list[torch.Tensor]:
        inputs = []
        if index is not None:
            x = obs.get("vector") if isinstance(obs, TensorDictBase) else obs
            x = x.cpu()
            inputs.append(x if gather is None else x.index_select(-1, gather))
        inputs += [obs.get(k).cpu() for k in keys]
        return inputs if mask_key is None else [*inputs, obs.get(mask_key).cpu()]

    return feed


def _check_mask(spec: dict[str, Any], mask: Any, where: str) -> None:
    """The env gives the action mask the file takes (same width), or one line saying it does not."""
    if mask is None:
        raise ValueError(
            f"{where}: it takes an action mask ({spec['source']} key {spec['mask_key']!r}, "
            f"{spec['shape'][1]} values) and the env of its config gives none; evaluate it on the "
            "env it was trained on (env.action_mask must not be off)"
        )
    if mask.width != spec["shape"][1]:
        raise ValueError(
            f"{where}: its action mask has {spec['shape'][1]} values; the env's has {mask.width}: "
            "the action space changed"
        )


def _check_part(saved: dict[str, Any], part: Any, where: str, have: list[str]) -> None:
    name = saved.get("image_key") or saved["key"] or "(root)"
    if part is None:
        raise ValueError(
            f"{where}: its actor reads the observation {name!r}, which the env of its config does "
            f"not give (it gives {[k or '(root)' for k in have]}); evaluate it on the env it was "
            "trained on"
        )
    now = part.record()
    diff = {k: now.get(k) for k in _SAME if saved.get(k) != now.get(k)}
    if diff:
        said = {k: saved.get(k) for k in diff}
        raise ValueError(
            f"{where}: its actor reads the observation {name!r} as {said}; the env of its config "
            f"gives {diff}: the observation space changed"
        )


def _whole_vector(
    meta: dict[str, Any], env: Any, where: str
) -> Callable[[Any], list[torch.Tensor]]:
    """An export without ``inputs`` (older rlexp): the env's whole flat vector, as then."""
    from rlexp.envs.layout_check import check_layout

    spec = env.observation_spec["observation"]
    obs_dim = int(spec.shape[-1]) if not hasattr(spec, "keys") else -1
    if obs_dim != meta["observation_dim"]:
        raise ValueError(
            f"{where} takes {meta['observation_dim']} observations; the env of its config gives "
            f"{obs_dim if obs_dim >= 0 else 'a TensorDict'}"
        )
    check_layout(meta.get("observation_layout"), env, where)
    return lambda obs: [obs.cpu()]


def env_actions(meta: dict[str, Any]) -> Callable[[torch.Tensor], torch.Tensor] | None:
    """The file's action -> the action the run's env takes (None: the same): categorical values
    back to indices (``start`` subtracted); an ``env.rescale_actions`` run's output (in the env's
    bounds) back to the [-1, 1] the env maps onto them itself."""
    space = meta.get("action_space") or {}
    if space.get("kind", "box") != "box":
        start = torch.tensor(space["start"], dtype=torch.int64)
        return lambda action: action - start
    if meta.get("actions_rescaled"):
        low = torch.tensor(meta["action_low"], dtype=torch.float64)
        half = (torch.tensor(meta["action_high"], dtype=torch.float64) - low) / 2.0
        return lambda action: ((action.double() - low) / half - 1.0).float()
    return None


class ExportedPolicy:
    """An exported file acting in TorchRL's loop: ``observation`` -> ``action`` (``feed``: the
    observation, a tensor or a TensorDict, -> the file's inputs on the CPU; ``post``: the file's
    action -> the env's). ``memory`` (the metadata's, recurrent policies): the file also takes its
    state and returns the next one; it starts at zeros and is zeroed for the copies whose episode
    ended (``episodes_ended``), as the metadata's ``reset`` says."""

    def __init__(
        self,
        act: Callable[..., Any],
        feed: Callable[[Any], list[Any]],
        post: Callable[[torch.Tensor], torch.Tensor] | None = None,
        memory: dict[str, Any] | None = None,
    ) -> None:
        self.act, self.feed, self.post, self.memory = act, feed, post, memory
        self.state: list[torch.Tensor] | None = None

    def __call__(self, td: Any) -> Any:
        obs = td.get("observation")  # the file runs on the CPU; the env may be on a GPU
        inputs = self.feed(obs)
        if self.memory is None:
            action = self.act(*inputs)
        else:
            if self.state is None:  # every copy at an episode's start
                batch = int(inputs[0].shape[0])
                self.state = [
                    torch.zeros(batch, *s["shape"][1:], dtype=torch.float32)
                    for s in self.memory["state"]
                ]
            action, *self.state = self.act(*inputs, *self.state)
        if self.post is not None:
            action = self.post(action)
        td.set("action", action.to(obs.device))
        return td

    def episodes_ended(self, done: torch.Tensor) -> None:
        """Zero the state of the copies whose episode ended (``done``: bool [num_copies])."""
        if self.state is not None:
            ended = done.reshape(-1, 1, 1).bool().cpu()
            self.state = [s.masked_fill(ended, 0.0) for s in self.state]
