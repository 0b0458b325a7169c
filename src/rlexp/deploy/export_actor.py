"""The module ``rlexp export`` writes: the deterministic actor on the actor's own inputs only
(docs/export.md, "Grouped and image policies").

A policy's actor reads a selection of the env's observation (``policy.actor.observations``,
DESIGN #47): some of the flat vector's parts and some uint8 images. The exported file takes exactly
those, never what only the critic reads:

- ``observation``: float32 [batch, n], the actor's vector parts in layout order (absent when the
  actor reads no vector part); the normaliser's statistics are gathered to those columns (the
  policy normalises the whole vector per dimension, then gathers: the same numbers);
- one uint8 [batch, C, H, W] input per image the actor reads, in layout order, /255 inside.

A recurrent actor (``policy.memory.type`` lstm / gru) also takes its state and returns the next one:
``actor_h`` (and ``actor_c`` for an LSTM) float32 [batch, num_layers, hidden_size] after the
observation inputs, ``actor_h_out`` (``actor_c_out``) after the action (``RecurrentStep``; the
critic's memory is never exported).

A policy without images or memory exports this module itself (``forward(observation)``, as before
groups existed); otherwise a thin wrapper whose ``forward`` names one argument per input is made from
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
        "reads_vector", "recurrent",
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
        # a recurrent actor: its LSTM / GRU between the features and the MLP (one step per call)
        core = recurrent_step(policy)
        self.recurrent = core is not None
        self.core = core if core is not None else nn.Identity()

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        return self.act(observation, [])

    def act(self, observation: torch.Tensor, images: list[torch.Tensor]) -> torch.Tensor:
        """The action for the actor's vector (ignored when it reads none) and its uint8 images."""
        return self.head(self.features(observation, images))

    def act_recurrent(
        self,
        observation: torch.Tensor,
        images: list[torch.Tensor],
        h: torch.Tensor,
        c: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """A recurrent actor's step: the action and the next state (``c``: an LSTM's cell state;
        a GRU's is passed through unused)."""
        y, h, c = self.core(self.features(observation, images), h, c)
        return self.head(y), h, c

    def features(self, observation: torch.Tensor, images: list[torch.Tensor]) -> torch.Tensor:
        """The normalised vector and the encoded images, as the actor's MLP (or memory) reads them."""
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
        return features[0] if len(features) == 1 else torch.cat(features, -1)

    def head(self, x: torch.Tensor) -> torch.Tensor:
        """The MLP's output as the env's action (argmax, clip, rescale)."""
        out = self.mlp(x)
        if self.categorical:
            if self.uniform:
                index = out.reshape(-1, self.k, self.n).argmax(-1)
            else:
                index = torch.stack([b.argmax(-1) for b in torch.split(out, self.nvec, -1)], -1)
            return index + self.action_start
        if self.clamp_actions:
            out = torch.clamp(out, self.action_low, self.action_high)
        if self.rescale:
            out = (out + 1.0) * self.rescale_half + self.rescale_low
        return out


class LstmStep(nn.Module):
    """One step of the actor's ``nn.LSTM`` (a copy, float32, no gradients) with the state batch
    first, as the file takes it: x [B, F], h and c [B, num_layers, H] -> y [B, H], h, c."""

    def __init__(self, rnn: nn.LSTM) -> None:
        super().__init__()
        self.rnn = copy.deepcopy(rnn).float().requires_grad_(False).eval()

    def forward(
        self, x: torch.Tensor, h: torch.Tensor, c: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        state = (h.transpose(0, 1).contiguous(), c.transpose(0, 1).contiguous())
        y, (h, c) = self.rnn(x.unsqueeze(1), state)
        return y.squeeze(1), h.transpose(0, 1), c.transpose(0, 1)


class GruStep(nn.Module):
    """One step of the actor's ``nn.GRU`` as ``LstmStep`` (``c`` passed through: a GRU has none)."""

    def __init__(self, rnn: nn.GRU) -> None:
        super().__init__()
        self.rnn = copy.deepcopy(rnn).float().requires_grad_(False).eval()

    def forward(
        self, x: torch.Tensor, h: torch.Tensor, c: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        y, h = self.rnn(x.unsqueeze(1), h.transpose(0, 1).contiguous())
        return y.squeeze(1), h.transpose(0, 1), c


def recurrent_step(policy: nn.Module) -> LstmStep | GruStep | None:
    """The actor's memory as one step of the file (None: a feed-forward policy); a memory that is
    not one batch-first ``nn.LSTM`` / ``nn.GRU`` is a one-line ValueError."""
    if not getattr(policy, "recurrent", False):
        return None
    rnn = actor_rnn(policy)
    if isinstance(rnn, nn.LSTM):
        return LstmStep(rnn)
    if isinstance(rnn, nn.GRU):
        return GruStep(rnn)
    raise ValueError(
        f"the actor's memory is a {type(rnn).__name__}; rlexp export takes an LSTM or a GRU "
        "(policy.memory.type=lstm|gru)"
    )


def actor_rnn(policy: nn.Module) -> nn.Module:
    """The actor's own ``nn.LSTM`` / ``nn.GRU`` (``policy.memory.shared``: the one both heads
    read); never the critic's own."""
    rnn = getattr(getattr(policy, "actor_core", None), "rnn", None)
    if rnn is None or not getattr(rnn, "batch_first", False):
        raise ValueError(
            f"the recurrent policy {type(policy).__name__} has no batch-first actor_core.rnn; "
            "rlexp export takes the actor's LSTM / GRU from there"
        )
    return rnn


def state_names(actor: DeterministicActor) -> list[str]:
    """The file's state inputs (``actor_h``, and ``actor_c`` for an LSTM; [] without memory); the
    outputs are the same names plus ``_out``."""
    if isinstance(actor.core, LstmStep):
        return ["actor_h", "actor_c"]
    return ["actor_h"] if isinstance(actor.core, GruStep) else []


def state_shape(actor: DeterministicActor) -> list[int]:
    """[num_layers, hidden_size] of each state input (after the batch)."""
    rnn = actor.core.rnn
    return [int(rnn.num_layers), int(rnn.hidden_size)]


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
    taken = state_names(actor)  # (the state inputs come last, under their fixed names)
    for key in actor.image_keys:
        name = re.sub(r"\W", "_", key)
        if name[0].isdigit() or keyword.iskeyword(name) or name in ("self", "torch"):
            name = "image_" + name
        while name in names or name in taken:
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

    def forward(self, {args}) -> {returns}:
        {body}
"""
#: The wrapper's return type and body: feed-forward, LSTM (state h, c), GRU (state h).
_BODIES = {
    0: ("torch.Tensor", "return self.core.act({vector}, [{images}])"),
    2: (
        "tuple[torch.Tensor, torch.Tensor, torch.Tensor]",
        "return self.core.act_recurrent({vector}, [{images}], actor_h, actor_c)",
    ),
    1: (
        "tuple[torch.Tensor, torch.Tensor]",
        "action, h, _ = self.core.act_recurrent({vector}, [{images}], actor_h, actor_h)\n"
        "        return action, h",
    ),
}
_count = [0]


def exported_module(actor: DeterministicActor, torchscript: bool) -> nn.Module:
    """What the file holds: the actor itself without images or memory; otherwise a wrapper whose
    ``forward`` takes one named tensor per input (the state last) and returns the action (and the
    next state). ``torchscript``: encoders traced, all scripted."""
    states = state_names(actor)
    if not actor.image_keys and not states:
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
    returns, body = _BODIES[len(states)]
    source = _WRAPPER.format(
        args=", ".join(f"{n}: torch.Tensor" for n in [*names, *states]),
        returns=returns,
        body=body.format(vector=vector, images=", ".join(images)),
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
    for _ in state_names(actor):  # a state of about the size an LSTM / GRU keeps (|h| < 1)
        out.append(torch.rand(batch, *state_shape(actor), generator=gen) * 1.6 - 0.8)
    return out


def call_actor(
    actor: DeterministicActor, inputs: list[torch.Tensor]
) -> torch.Tensor | tuple[torch.Tensor, ...]:
    """The actor on inputs in the file's order: the action (recurrent: and the next state)."""
    states = state_names(actor)
    if not actor.image_keys and not states:
        return actor(inputs[0])
    if states:
        inputs, state = inputs[: -len(states)], inputs[-len(states) :]
    vector = inputs[0] if actor.reads_vector else torch.zeros(0)
    images = list(inputs[1:] if actor.reads_vector else inputs)
    if not states:
        return actor.act(vector, images)
    action, h, c = actor.act_recurrent(vector, images, state[0], state[-1])
    return (action, h, c) if len(states) == 2 else (action, h)
