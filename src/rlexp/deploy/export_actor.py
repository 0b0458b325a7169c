"""The module ``rlexp export`` writes: the deterministic actor on the actor's own inputs only
(docs/export.md, "Grouped and image policies").

A policy's actor reads a selection of the env's observation (``policy.actor.observations``,
DESIGN #47): some of the flat vector's parts and some uint8 images. The exported file takes exactly
those, never what only the critic reads:

- ``observation``: float32 [batch, n], the actor's vector parts in layout order (absent when the
  actor reads no vector part); the normaliser's statistics are gathered to those columns (the
  policy normalises the whole vector per dimension, then gathers: the same numbers);
- one uint8 [batch, C, H, W] input per image the actor reads, in layout order, /255 inside.

A policy without images exports this module itself (``forward(observation)``, as before groups
existed); with images a thin wrapper whose ``forward`` names one argument per input is made from
source (TorchScript needs a fixed signature). Image encoders are traced for TorchScript (their
reshapes over leading batch dims are not scriptable) and exported as they are for ONNX.
"""

from __future__ import annotations

import copy
import keyword
import linecache
import re
import warnings
from typing import Any

import torch
from torch import nn

#: The name of the vector input (the ONNX graph name; TorchScript's argument name).
VECTOR_INPUT = "observation"


class DeterministicActor(nn.Module):
    """The actor's inputs -> the deterministic action, the normaliser folded in.

    Box actions: the Gaussian's mean [batch, act_dim] float32, (``clamp_actions``) clipped to the
    action bounds as the env does. Categorical actions (``nvec``): the most likely value of each
    component, plus its ``start``: int64 [batch, K], the values of the env's own action space
    (``Discrete``: column 0; ``MultiDiscrete`` / ``MultiBinary``: reshape to the space's shape)."""

    # TorchScript: fixed branches
    __constants__ = [
        "normalize", "clip", "clamp_actions", "rescale", "categorical", "uniform", "k", "n",
        "reads_vector", "squash", "act_dim",
    ]  # fmt: skip

    def __init__(
        self,
        policy: nn.Module,
        low: torch.Tensor,
        high: torch.Tensor,
        clamp_actions: bool,
        start: list[int] | None = None,
        rescale: tuple[torch.Tensor, torch.Tensor] | None = None,
    ) -> None:
        super().__init__()
        net = policy.actor_net
        norm = net.normalizer
        self.normalize = bool(norm.enabled)
        self.clip = float(norm.clip)
        self.clamp_actions = clamp_actions
        inputs = getattr(net, "inputs", None)  # policies.inputs.ObsInput: what the actor reads
        columns = actor_columns(inputs, int(norm._scale.shape[0]))
        self.reads_vector = bool(columns)
        index = torch.tensor(columns, dtype=torch.long)
        # the same float32 buffers and ops as ObservationNormalizer.forward, at the actor's columns
        self.register_buffer("obs_scale", norm._scale.detach().float().index_select(0, index))
        self.register_buffer("obs_shift", norm._shift.detach().float().index_select(0, index))
        self.image_keys = tuple(inputs.image_keys) if inputs is not None else ()
        encoders = [inputs.encoders[k.replace(".", "/")] for k in self.image_keys]
        self.encoders = nn.ModuleList(
            copy.deepcopy(e).float().requires_grad_(False).eval() for e in encoders
        )
        self.image_shapes = [tuple(int(x) for x in e.in_shape) for e in encoders]
        self.mlp = copy.deepcopy(net.mlp).float().requires_grad_(False)
        # (an env on a GPU has its bounds there; the file runs on the CPU)
        self.register_buffer("action_low", low.detach().cpu().clone().float())
        self.register_buffer("action_high", high.detach().cpu().clone().float())
        self.categorical = policy.categorical
        nvec = list(policy.nvec) if policy.categorical else [1]
        self.nvec = nvec  # TorchScript infers List[int] from the value (no annotation: no warning)
        self.uniform = len(set(nvec)) == 1
        self.k, self.n = len(nvec), nvec[0]
        self.register_buffer("action_start", torch.tensor(start or [0] * self.k, dtype=torch.int64))
        # env.rescale_actions: [-1, 1] (the clamp's bounds) onto the env's (low, (high - low) / 2)
        self.rescale = rescale is not None
        low0, half = rescale if rescale is not None else (torch.zeros(1), torch.ones(1))
        self.register_buffer("rescale_low", low0.detach().cpu().clone().float())
        self.register_buffer("rescale_half", half.detach().cpu().clone().float())
        # SAC / TD3 (policies/offpolicy.py): tanh of the mean (SAC: the MLP's first half) mapped
        # onto the policy's bounds, as ``policy.deterministic_action``
        self.squash = getattr(policy, "kind", None) in ("sac", "td3")
        self.act_dim = int(low.shape[-1])
        bounds = (policy.action_low, policy.action_high) if self.squash else (low, high)
        self.register_buffer("squash_low", bounds[0].detach().cpu().clone().float())
        self.register_buffer("squash_high", bounds[1].detach().cpu().clone().float())

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        return self.act(observation, [])

    def act(self, observation: torch.Tensor, images: list[torch.Tensor]) -> torch.Tensor:
        """The action for the actor's vector (ignored when it reads none) and its uint8 images."""
        features: list[torch.Tensor] = []
        if self.reads_vector:
            x = observation
            if self.normalize:
                x = torch.clamp(
                    torch.addcmul(self.obs_shift, x, self.obs_scale), -self.clip, self.clip
                )
            features.append(x)
        i = 0
        for encoder in self.encoders:
            features.append(encoder(images[i]))
            i += 1
        x = features[0] if len(features) == 1 else torch.cat(features, -1)
        out = self.mlp(x)
        if self.categorical:
            if self.uniform:
                index = out.reshape(-1, self.k, self.n).argmax(-1)
            else:
                index = torch.stack([b.argmax(-1) for b in torch.split(out, self.nvec, -1)], -1)
            return index + self.action_start
        if self.squash:
            out = out[..., : self.act_dim]
            out = (
                self.squash_low
                + (self.squash_high - self.squash_low) * (torch.tanh(out) + 1.0) * 0.5
            )
        if self.clamp_actions:
            out = torch.clamp(out, self.action_low, self.action_high)
        if self.rescale:
            out = (out + 1.0) * self.rescale_half + self.rescale_low
        return out


def actor_columns(inputs: Any, dim: int) -> list[int]:
    """The flat vector's columns the actor reads (``inputs``: its ``ObsInput``; None: all)."""
    if inputs is None:
        return list(range(dim))
    return [
        i for p in inputs.parts if p.kind != "image" for i in range(p.offset, p.offset + p.size)
    ]


def input_names(actor: DeterministicActor) -> list[str]:
    """The file's input names: ``observation`` (when the actor reads a vector), then one per image
    (its TensorDict key as an identifier: ``cam.front`` -> ``cam_front``; unique)."""
    names = [VECTOR_INPUT] if actor.reads_vector else []
    for key in actor.image_keys:
        name = re.sub(r"\W", "_", key)
        if name[0].isdigit() or keyword.iskeyword(name) or name in ("self", "torch"):
            name = "image_" + name
        while name in names:
            name += "_"
        names.append(name)
    return names


def input_records(actor: DeterministicActor, policy: nn.Module) -> list[dict[str, Any]]:
    """The metadata's ``inputs``: per input its name, kind, key, dtype, shape, groups and the
    observation parts it is made of (the layout's records; a vector part's ``input_offset`` is
    where it starts in the input)."""
    inputs = getattr(policy.actor_net, "inputs", None)
    parts = list(inputs.parts) if inputs is not None else list(policy.obs_layout.parts)
    names = input_names(actor)
    out: list[dict[str, Any]] = []
    if actor.reads_vector:
        vector, at = [], 0
        for p in parts:
            if p.kind != "image":
                vector.append({**p.record(), "group": p.group, "input_offset": at})
                at += p.size
        out.append(
            {
                "name": names[0],
                "kind": "vector",
                "key": "vector",
                "dtype": "float32",
                "shape": ["batch", at],
                "groups": sorted({p["group"] for p in vector}),
                "parts": vector,
            }
        )
    images = [p for p in parts if p.kind == "image"]
    for name, p, shape in zip(names[len(out) :], images, actor.image_shapes, strict=True):
        out.append(
            {
                "name": name,
                "kind": "image",
                "key": p.image_key,
                "dtype": "uint8",
                "shape": ["batch", *shape],
                "groups": [p.group],
                "parts": [{**p.record(), "group": p.group}],
            }
        )
    return out


_WRAPPER = """
class ExportedActor(torch.nn.Module):
    def __init__(self, core):
        super().__init__()
        self.core = core

    def forward(self, {args}) -> torch.Tensor:
        return self.core.act({vector}, [{images}])
"""
_count = [0]


def exported_module(actor: DeterministicActor, torchscript: bool) -> nn.Module:
    """What the file holds: the actor itself without images; with images a wrapper whose
    ``forward`` takes one named tensor per input. ``torchscript``: encoders traced, all scripted."""
    if not actor.image_keys:
        return torch.jit.script(actor) if torchscript else actor
    core = actor
    if torchscript:
        core = copy.copy(actor)  # (nn.Module copy: the same buffers; only the encoders differ)
        core._modules = dict(actor._modules)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            core.encoders = nn.ModuleList(
                torch.jit.trace(e, torch.zeros(2, *shape, dtype=torch.uint8))
                for e, shape in zip(actor.encoders, actor.image_shapes, strict=True)
            )
    names = input_names(actor)
    vector = VECTOR_INPUT if actor.reads_vector else "torch.zeros(0)"
    images = names[1:] if actor.reads_vector else names
    source = _WRAPPER.format(
        args=", ".join(f"{n}: torch.Tensor" for n in names),
        vector=vector,
        images=", ".join(images),
    )
    # TorchScript reads a method's source: the generated text is registered with linecache
    _count[0] += 1
    filename = f"<rlexp-export-{_count[0]}>"
    linecache.cache[filename] = (len(source), None, source.splitlines(True), filename)
    scope: dict[str, Any] = {"torch": torch}
    exec(compile(source, filename, "exec"), scope)  # noqa: S102 (our own template, no user text)
    module = scope["ExportedActor"](core).eval()
    if not torchscript:
        return module
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        return torch.jit.script(module)


def probe_inputs(actor: DeterministicActor, batch: int, seed: int = 0) -> list[torch.Tensor]:
    """A batch of inputs to compare the file with the actor: the vector around the normaliser's
    mean (some far out so the clips act), images of random uint8 pixels."""
    gen = torch.Generator().manual_seed(seed)
    out = []
    if actor.reads_vector:
        probe = torch.randn(batch, actor.obs_scale.shape[0], generator=gen) * 3.0
        if actor.normalize:  # x = (probe - shift) / scale: normalised values of about +-3
            probe = (probe - actor.obs_shift) / actor.obs_scale
        out.append(probe)
    for shape in actor.image_shapes:
        out.append(torch.randint(0, 256, (batch, *shape), generator=gen, dtype=torch.uint8))
    return out


def call_actor(actor: DeterministicActor, inputs: list[torch.Tensor]) -> torch.Tensor:
    """The actor on inputs in the file's order."""
    if not actor.image_keys:
        return actor(inputs[0])
    vector = inputs[0] if actor.reads_vector else torch.zeros(0)
    return actor.act(vector, list(inputs[1:] if actor.reads_vector else inputs))
