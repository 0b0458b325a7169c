"""What each network reads of the observation (``policy.actor.observations``,
``policy.critic.observations``): the env's observation layout's parts, selected by key, key prefix
or group, turned into the network's input.

The env emits every group (envs/spaces.py ``ObsLayout``): a flat float32 vector of all non-image
parts, or, with images, a TensorDict of ``"vector"`` and one uint8 ``[..., C, H, W]`` entry per image.
One ``ObservationNormalizer`` covers the whole vector (per-dimension statistics, so each group is
normalised on its own); a network's ``ObsInput`` gathers its selected vector indices after it, runs
one encoder per selected image key (``encoders.py``), and concatenates: the selected normalised
vector first, then each image's features in layout order (SB3's ``CombinedExtractor``). A network
that reads the whole vector and no image gathers nothing: the observation's normalised vector is its
input, exactly as before groups existed (the numpy sampler and the fused step keep their paths).
"""

from __future__ import annotations

import difflib
from collections.abc import Callable, Sequence
from typing import Any

import torch
from tensordict import TensorDictBase
from torch import nn

from rlexp.envs.spaces import ObsLayout, ObsPart

#: The group an actor reads by default (rsl_rl's and Isaac Lab's name for the actor's observations).
POLICY_GROUP = "policy"


def plain_layout(dim: int) -> ObsLayout:
    """The layout of an env that records none (a batched torch env): one vector part at the root."""
    return ObsLayout("Box", (ObsPart("", "box", (dim,), 0, dim),), dim, plain=True)


def layout_of(env: Any) -> ObsLayout:
    """The observation layout of a built env: its base env's ``obs_layout``, else read from its
    observation spec (a flat vector: one part; a Composite: ``vector`` and uint8 image entries)."""
    base = env
    while hasattr(base, "base_env"):
        base = base.base_env
    layout = getattr(base, "obs_layout", None)
    spec = env.observation_spec["observation"]
    flat = not hasattr(spec, "keys")  # one tensor, not a Composite
    # a wrapper that changed the vector's width (none of rlexp's does) leaves the recorded layout
    if isinstance(layout, ObsLayout) and (not flat or int(spec.shape[-1]) == layout.dim):
        return layout
    if flat:
        return plain_layout(int(spec.shape[-1]))
    parts: list[ObsPart] = []
    dim = 0
    for key in spec.keys():
        entry = spec[key]
        if key == "vector":
            dim = int(entry.shape[-1])
            parts.insert(0, ObsPart("", "box", (dim,), 0, dim))
        elif entry.dtype == torch.uint8 and len(entry.shape) >= 3:
            chw = tuple(int(x) for x in entry.shape[-3:])
            parts.append(
                ObsPart(str(key), "image", chw, -1, 0, image_key=str(key), source_layout="chw")
            )
        else:
            raise TypeError(
                f"the env's observation entry {key!r} ({entry.dtype}, shape {list(entry.shape)}) is "
                "neither 'vector' nor a uint8 [C, H, W] image"
            )
    return ObsLayout("Composite", tuple(parts), dim)


def _matches(name: str, part: ObsPart) -> bool:
    """Whether ``name`` selects ``part``: its key, a prefix of its key at a "/" boundary, its
    group, or (an image) its TensorDict key."""
    return (
        name == part.key
        or (bool(name) and part.key.startswith(name + "/"))
        or name == part.group
        or (part.kind == "image" and name == part.image_key)
    )


def available(layout: ObsLayout) -> str:
    """The keys and groups of ``layout``, for messages."""
    keys = [
        p.image_key if p.kind == "image" and not p.key else (p.key or "(root)")
        for p in layout.parts
    ]
    groups = sorted({p.group for p in layout.parts})
    return f"keys {keys}, groups {groups}"


def select_parts(
    layout: ObsLayout, names: Sequence[str] | None, where: str, default_groups: Sequence[str] | None
) -> tuple[ObsPart, ...]:
    """The parts ``names`` selects, in layout order (``names`` None: the parts of
    ``default_groups``, every part for None). ``where``: the config key, for the one-line
    ValueError an unknown name or an empty selection raises."""
    parts = layout.parts
    if names is None:
        chosen = [p for p in parts if default_groups is None or p.group in default_groups]
        if not chosen:
            raise ValueError(
                f"{where}=null reads group {list(default_groups or [])}, which the env does not "
                f"have ({available(layout)}); name what the network reads, e.g. "
                f"{where}=[{parts[0].group}]"
            )
        return tuple(chosen)
    names = list(names)
    if not names:
        raise ValueError(
            f"{where}=[] selects no observation; name keys or groups ({available(layout)}), or "
            f"null for the default"
        )
    for name in names:
        if not any(_matches(name, p) for p in parts):
            # every key, each "/" prefix of one, every group and image key
            prefixes = {p.key.rsplit("/", i)[0] for p in parts for i in range(p.key.count("/") + 1)}
            candidates = sorted(
                (prefixes | {p.group for p in parts} | {p.image_key for p in parts}) - {""}
            )
            close = difflib.get_close_matches(str(name), candidates, n=1)
            hint = f"; did you mean {close[0]!r}?" if close else ""
            raise ValueError(
                f"{where}={names}: {name!r} names no observation of this env "
                f"({available(layout)}){hint}"
            )
    return tuple(p for p in parts if any(_matches(n, p) for n in names))


class ObsInput(nn.Module):
    """One network's input: the env's observation (a flat tensor or a TensorDict) -> the selected,
    normalised vector entries and the selected images' features, concatenated.

    The normaliser is shared by the networks and passed in at each call, so that its statistics are
    stored once per network as before (``actor_net.normalizer``), never under this module."""

    index: torch.Tensor | None

    def __init__(
        self,
        layout: ObsLayout,
        parts: Sequence[ObsPart],
        encoders: dict[str, nn.Module] | None = None,
    ) -> None:
        super().__init__()
        self.parts = tuple(parts)
        self.structured = layout.structured
        vector = [p for p in self.parts if p.kind != "image"]
        columns = [i for p in vector for i in range(p.offset, p.offset + p.size)]
        self.vector_dim = len(columns)
        self.reads_vector = bool(columns)
        everything = columns == list(range(layout.dim))
        # Not in the state_dict (made again from the layout): checkpoints keep their keys.
        self.register_buffer(
            "index", None if everything else torch.tensor(columns, dtype=torch.long), False
        )
        self.image_keys = tuple(p.image_key for p in self.parts if p.kind == "image")
        encoders = encoders or {}
        # (a module name cannot hold "."; a nested image's key "cam.front" is "cam/front" here)
        self.encoders = nn.ModuleDict({_module_name(k): encoders[k] for k in self.image_keys})
        self.out_dim = self.vector_dim + sum(int(e.features_dim) for e in self.encoders.values())

    @property
    def trivial(self) -> bool:
        """Reads the whole flat vector and no image: the normalised observation is the input."""
        return not self.structured and self.index is None

    def forward(
        self,
        obs: torch.Tensor | TensorDictBase,
        normalizer: nn.Module,
        cache: FeatureCache | None = None,
    ) -> torch.Tensor:
        """``cache`` (shared by the actor's and the critic's inputs for one minibatch): an image
        encoder's features on an image tensor computed once (``encode``)."""
        if not isinstance(obs, TensorDictBase):
            x = normalizer(obs)
            return x if self.index is None else x.index_select(-1, self.index)
        features = []
        if self.reads_vector:
            x = normalizer(obs.get("vector"))
            features.append(x if self.index is None else x.index_select(-1, self.index))
        for key in self.image_keys:
            features.append(encode(self.encoders[_module_name(key)], key, obs.get(key), cache))
        return features[0] if len(features) == 1 else torch.cat(features, -1)

    def function(self, normalizer: nn.Module) -> Callable[[Any], torch.Tensor]:
        """``obs -> input`` for a collection sampler: the normaliser itself where nothing is
        gathered (the path and numbers of a policy without groups)."""
        if self.trivial:
            return normalizer
        return lambda obs: self(obs, normalizer)

    def records(self) -> list[dict[str, Any]]:
        """The selected parts as the layout records them (export metadata, eval)."""
        return [p.record() for p in self.parts]


#: image key -> (the image tensor, its encoder, the encoder's features on it)
FeatureCache = dict[str, tuple[torch.Tensor, nn.Module, torch.Tensor]]


def encode(
    encoder: nn.Module, key: str, image: torch.Tensor, cache: FeatureCache | None
) -> torch.Tensor:
    """``encoder(image)``, or, with a ``cache``, the features it already holds for this very
    encoder on this very image tensor (identity, not equality: actor and critic read the same
    minibatch's tensor). With ``policy.share_encoder`` the actor's and the critic's encoder of an
    image key are one module, so the loss runs it once per minibatch and both heads read its
    features (SB3's and CleanRL's shared-features network): the same loss and, through autograd's
    sum over the two uses, the same gradients as two passes, to float rounding."""
    if cache is None:
        return encoder(image)
    hit = cache.get(key)
    if hit is not None and hit[0] is image and hit[1] is encoder:
        return hit[2]
    out = encoder(image)
    cache[key] = (image, encoder, out)
    return out


def _module_name(image_key: str) -> str:
    """An image key as a name ``nn.ModuleDict`` takes ("." is its path separator)."""
    return image_key.replace(".", "/")
