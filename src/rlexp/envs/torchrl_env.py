"""``env.backend=torchrl``: any TorchRL ``EnvBase`` a factory builds, as an rlexp env.

TorchRL's own wrappers (Isaac Lab, DMControl, Brax, MuJoCo Playground, ...) and a user's EnvBase
alike (docs/batched_envs.md):

- **observations**: every entry of the env's observation spec (nested keys included; non-tensor
  entries left out) flattened per env and concatenated into one float32 vector, depth-first with
  each level's keys sorted (as a Gymnasium ``Dict``); a part's key is its path joined with ``/``
  (selectable as ``a/b``, or ``a`` for every entry under it); the layout is recorded in checkpoints
  and export metadata. **Groups**: each entry is of group ``policy``, except under a top-level entry
  named ``critic``, and, when the env has a top-level ``policy`` entry (Isaac Lab's groups), every
  top-level entry is a group of its own name; the ``policy`` group's entries come first.
  Images (uint8 entries of rank 3, HWC or CHW, or 4, stacked frames; ``images.image_layout``) are
  not flattened: the observation is then a TensorDict of ``vector`` and one uint8 [N, C, H, W]
  entry per image (its key with "/" as "."), as the Gymnasium backends give it.
- **actions**: one action key. ``Bounded`` / ``Unbounded`` continuous specs become rlexp's Gaussian
  actions (flattened; bounds +-inf where the spec has none; actions clipped to finite bounds);
  ``Categorical`` and ``OneHot`` (one component), ``MultiCategorical`` and ``Binary`` become
  categorical actions, handed to the env in its spec's own form (one-hot where it asks for it).
- **autoreset**: TorchRL's own ``step_and_maybe_reset``: the step's ``"next"`` holds the true final
  observation, the returned root the reset one. (TorchRL reads one flag back per step to decide
  whether any copy needs a reset, unless the env resets natively.)
- **batch**: ``batch_size`` [N] (an unbatched env, ``batch_size`` [], is one copy); ``device`` is
  the env's.
- **resume**: the env's ``get_state()`` / ``set_state(state)`` when it defines them (rlexp's state
  protocol, not TorchRL's), with the root tensordict; else the documented restart (``set_seed``).
"""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import (
    Binary,
    Bounded,
    Categorical,
    MultiCategorical,
    MultiOneHot,
    NonTensor,
    OneHot,
    Unbounded,
)
from torchrl.envs import EnvBase

from rlexp.envs.batched_base import FLOATS, BatchedAdapter, check_tensor
from rlexp.envs.env_state import plain_state
from rlexp.envs.groups import group_rule
from rlexp.envs.images import VECTOR_KEY, image_key_of, image_layout
from rlexp.envs.spaces import ActionCoding, ObsLayout, ObsPart, UnsupportedSpace

#: Observation dtypes rlexp reads (cast to float32): floats, integers, booleans.
OBS_DTYPES = (*FLOATS, torch.bool, torch.uint8, torch.int8, torch.int16, torch.int32, torch.int64)


def _name(key: Any) -> str:
    return "/".join(key) if isinstance(key, tuple) else str(key)


def _path(key: Any) -> tuple[str, ...]:
    """A key as its path: sorting paths orders entries depth-first, each level's names sorted
    (rlexp.envs.spaces.FLATTEN_ORDER, as for a Gymnasium Dict)."""
    return tuple(key) if isinstance(key, tuple) else (str(key),)


class TorchRLAdapter(BatchedAdapter):
    """A TorchRL ``EnvBase`` (``raw``) as rlexp's batched env, on the env's own device."""

    contract = "torchrl"

    def __init__(self, raw: EnvBase, name: str) -> None:
        where = f"env.name={name!r}"
        batch = tuple(raw.batch_size)
        if len(batch) > 1:
            raise ValueError(
                f"{where}: the env's batch_size is {list(batch)}; rlexp takes envs batched in one "
                "dimension ([num_envs]) or unbatched ([])"
            )
        n = batch[0] if batch else 1
        device = raw.device if raw.device is not None else torch.device("cpu")
        if len(raw.action_keys) != 1 or len(raw.reward_keys) != 1:
            raise ValueError(
                f"{where}: the env has action keys {raw.action_keys} and reward keys "
                f"{raw.reward_keys}; rlexp takes one of each (no multi-agent envs)"
            )
        self._action_key, self._reward_key = raw.action_keys[0], raw.reward_keys[0]
        spec = raw.full_action_spec[self._action_key]
        coding, self._action_shape, self._one_hot = _action(spec, len(batch), where)
        self._action_dtype = spec.dtype
        self._keys, layout = _observations(raw, len(batch), where)
        # image entries: (key, TensorDict key, source layout, CHW shape); the rest is the vector
        self._images = [
            (k, p.image_key, p.source_layout, p.shape)
            for k, p in zip(self._keys, layout.parts, strict=True)
            if p.kind == "image"
        ]
        self._vector_keys = [k for k, p in zip(self._keys, layout.parts, strict=True) if p.size]
        done_keys = {_name(k).rsplit("/", 1)[-1]: k for k in raw.done_keys}
        if "done" not in done_keys:
            raise ValueError(
                f"{where}: the env has no 'done' entry (its done keys: {raw.done_keys})"
            )
        self._done_key, self._truncated_key = done_keys["done"], done_keys.get("truncated")
        self._root: TensorDictBase | None = None  # the env's tensordict to step from
        super().__init__(raw, name, n, device, layout, coding)
        self._shapes = {
            k: (n, *raw.full_observation_spec[k].shape[len(batch) :]) for k in self._keys
        }
        self._no_truncation = torch.zeros(n, 1, dtype=torch.bool, device=self.device)

    def _flat(self, td: TensorDictBase) -> torch.Tensor | TensorDictBase:
        n = self.num_envs
        if self._images:
            return self._structured(td)
        parts = [td.get(k).reshape(n, -1) for k in self._keys]
        flat = parts[0] if len(parts) == 1 else torch.cat([p.to(torch.float32) for p in parts], -1)
        return flat.to(torch.float32)

    def _structured(self, td: TensorDictBase) -> TensorDictBase:
        """The observation with images: ``vector`` (float32, when there is one) and each image
        as uint8 [N, C, H, W]."""
        n, out = self.num_envs, {}
        if self._vector_keys:
            parts = [td.get(k).reshape(n, -1).to(torch.float32) for k in self._vector_keys]
            out[VECTOR_KEY] = parts[0] if len(parts) == 1 else torch.cat(parts, -1)
        for key, name, source, chw in self._images:
            x = td.get(key).reshape(n, *self._shapes[key][1:])
            if source.endswith("hwc"):
                x = x.movedim(-1, -3)
            out[name] = x.reshape(n, *chw).contiguous()
        return TensorDict._new_unsafe(out, batch_size=self.batch_size, device=self.device)

    def _check_obs(self, td: TensorDictBase, what: str) -> None:
        for key in self._keys:
            shape = self._shapes[key]
            value = td.get(key, None)
            label = f"{what} {_name(key)!r}"
            if value is None:
                raise ValueError(f"{self.where}: {what} has no entry {_name(key)!r}")
            check_tensor(self.where, label, value.reshape(shape), None, OBS_DTYPES, self.device)

    # -- the contract ------------------------------------------------------------------------------
    def _raw_seed(self, seed: int) -> bool:
        self.raw.set_seed(seed)
        return True

    def _raw_reset(self) -> torch.Tensor:
        self._root = self.raw.reset()
        self._check_obs(self._root, "reset()'s observation")
        return self._flat(self._root)

    def _raw_step(
        self, action: torch.Tensor, prev: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        n = self.num_envs
        if self._one_hot:
            action = torch.nn.functional.one_hot(action[..., 0], self._one_hot)
        self._root.set(self._action_key, action.reshape(self._action_shape).to(self._action_dtype))
        out, self._root = self.raw.step_and_maybe_reset(self._root)
        nxt = out.get("next")
        if not self._live.checked:
            self._check_step(nxt)
        reward = nxt.get(self._reward_key).reshape(n, 1).to(torch.float32)
        done = nxt.get(self._done_key).reshape(n, 1)
        truncated = self._no_truncation
        if self._truncated_key is not None:
            truncated = done & nxt.get(self._truncated_key).reshape(n, 1)
        return self._flat(self._root), self._flat(nxt), reward, done, truncated

    def _check_step(self, nxt: TensorDictBase) -> None:
        self._check_obs(nxt, "step()'s observation")
        n, reward = self.num_envs, nxt.get(self._reward_key, None)
        check_tensor(self.where, "step()'s reward", reward, None, FLOATS, self.device)
        if reward.numel() != n:
            raise ValueError(
                f"{self.where}: step()'s reward has shape {list(reward.shape)}, expected [{n}, 1]"
            )
        self._live.checked = True

    def _extra_state(self) -> dict:
        return {"root": plain_state(self._root.to_dict(), self.env_id, "the root tensordict")}

    def _load_extra(self, sd: dict) -> None:
        root = TensorDict(sd["root"], batch_size=self.raw.batch_size)
        self._root = root.to(self.raw.device) if self.raw.device is not None else root


def _observations(raw: EnvBase, dims: int, where: str) -> tuple[list[Any], ObsLayout]:
    """The observation entries rlexp reads, in order, and the flat vector's layout."""
    spec = raw.full_observation_spec
    keys = sorted(
        (k for k in spec.keys(True, True) if not isinstance(spec[k], NonTensor)), key=_path
    )
    if not keys:
        raise ValueError(f"{where}: the env's observation spec has no tensor entries")
    top_group = group_rule(_path(k)[0] for k in keys)  # Isaac Lab's / rsl_rl's groups (groups.py)

    def group(key: Any) -> str:
        return top_group(_path(key)[0])

    keys.sort(key=lambda k: group(k) != "policy")  # stable: the policy group first, sorted within
    parts, offset = [], 0
    for key in keys:
        shape = tuple(int(s) for s in spec[key].shape[dims:])
        if spec[key].dtype == torch.uint8:
            at = f" {_name(key)!r}"
            image = image_layout(shape, "uint8", False, at, where, UnsupportedSpace)
            if image is not None:
                chw, source = image
                parts.append(
                    ObsPart(_name(key), "image", chw, -1, 0, group=group(key),
                            image_key=image_key_of(_name(key)), source_layout=source)
                )  # fmt: skip
                continue
        size = 1
        for s in shape:
            size *= s
        parts.append(ObsPart(_name(key), "box", shape, offset, size, group=group(key)))
        offset += size
    plain = len(keys) == 1 and len(parts[0].shape) == 1 and parts[0].kind != "image"
    return keys, ObsLayout("Composite", tuple(parts), offset, plain)


def _action(spec: Any, dims: int, where: str) -> tuple[ActionCoding, tuple[int, ...], int]:
    """The action's coding, the shape the env takes it in, and (one-hot specs) the number of
    values to one-hot-encode the index into (0: no encoding)."""
    shape = tuple(int(s) for s in spec.shape)
    own = shape[dims:]  # per env
    inf = float("inf")
    if isinstance(spec, MultiOneHot):
        raise TypeError(
            f"{where}: the action spec is MultiOneHot; rlexp takes Bounded, Unbounded, Categorical, "
            "OneHot, MultiCategorical and Binary actions"
        )
    if isinstance(spec, Binary):
        k = int(own[-1]) if own else 1
        return ActionCoding("multi_binary", own, k, (2,) * k, (0,) * k, dtype="int64"), shape, 0
    if isinstance(spec, MultiCategorical):
        k = int(own[-1])
        nvec = tuple(int(v) for v in spec.nvec.reshape(-1, k)[0].tolist())
        return ActionCoding("multi_discrete", own, k, nvec, (0,) * k, dtype="int64"), shape, 0
    if isinstance(spec, Categorical):
        count = int(spec.space.n)
        return ActionCoding("discrete", (), 1, (count,), (0,), dtype="int64"), shape, 0
    if isinstance(spec, OneHot):
        count = int(spec.space.n)
        coding = ActionCoding("discrete", (), 1, (count,), (0,), dtype="int64")
        return coding, shape, count
    if isinstance(spec, Bounded | Unbounded) and spec.domain == "continuous":
        size = 1
        for s in own:
            size *= s
        if isinstance(spec, Bounded):
            low = tuple(float(v) for v in spec.space.low.reshape(-1, size)[0].tolist())
            high = tuple(float(v) for v in spec.space.high.reshape(-1, size)[0].tolist())
        else:
            low, high = (-inf,) * size, (inf,) * size
        dtype = str(spec.dtype).replace("torch.", "")
        return ActionCoding("box", own, size, low=low, high=high, dtype=dtype), shape, 0
    raise TypeError(
        f"{where}: the action spec is {type(spec).__name__}; rlexp takes Bounded, Unbounded, "
        "Categorical, OneHot, MultiCategorical and Binary actions"
    )
