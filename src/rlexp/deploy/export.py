"""``rlexp export``: a checkpoint's deterministic policy as one self-contained file, TorchScript or
ONNX, and a metadata JSON beside it (``<file>.json``; docs/export.md).

The file maps a float32 ``observation`` [batch, obs_dim] (the env's observation flattened as the
metadata's ``observation_layout`` says) to the ``action`` [batch, act_dim] that ``rlexp eval``
applies to the env: for Box actions the Gaussian's mean, i.e. the actor MLP on the normalised
observation; for categorical actions (Discrete, MultiDiscrete, MultiBinary) the most likely value of
each component as an int64 in the env's own range (``start`` added; metadata ``action_space``).
Folded in:

- the observation normaliser. rlexp normalises inside the policy (``ObservationNormalizer``, whose
  statistics are checkpointed), not with a TorchRL transform on the env: ``(x - mean) / sqrt(var +
  eps)`` as the ``_scale`` / ``_shift`` buffers hold it, clipped to +-``env.clip_observations``;
  with ``env.normalize_observations=false`` it is the identity (and nothing is clipped);
- the clipping of the action to the action bounds, which rlexp's envs (gymnasium, native, the
  batched torch envs: vecenv, torchrl) apply before acting; ``env.backend=torchrl_gym`` hands
  actions on unclipped, and so does its export. An unbounded side (a batched env's Box without
  bounds) clips nothing; the metadata writes it as null.

Only the actor is exported (PPO's critic is not); actor-critic and actor-only policies alike. A
policy whose actor reads a selection of the observation (groups, an asymmetric critic) or images
takes the actor's inputs only: its vector parts and uint8 [batch, C, H, W] images, listed in the
metadata's ``inputs`` (``export_actor.py``; docs/export.md "Grouped and image policies").

A recurrent policy's file (``policy.memory.type`` lstm / gru) also takes the actor's state after
those inputs (``actor_h``, and ``actor_c`` for an LSTM: float32 [batch, num_layers, hidden_size])
and returns the next one after the action (``actor_h_out``, ``actor_c_out``); the metadata's
``memory`` says so, and that the state is zeros at each episode's start (docs/export.md "Recurrent
policies").
"""

from __future__ import annotations

import json
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from rlexp.checkpoints.files import select_checkpoint
from rlexp.deploy.export_actor import (
    DeterministicActor,
    actor_columns,
    call_actor,
    exported_module,
    input_names,
    input_records,
    probe_inputs,
    state_names,
    state_shape,
)
from rlexp.deploy.export_meta import json_safe
from rlexp.deploy.policy_eval import (
    EXPORT_SCHEMA,
    EXPORT_SUFFIXES,
    check_policy_finite,
    load_exported,
    metadata_path,
    quiet,
    typed_config,
)
from rlexp.files.fsutil import atomic_write, atomic_write_text, temp_path

#: The exported file's input and output names (ONNX graph names; the metadata states them).
INPUT_NAME, OUTPUT_NAME = "observation", "action"  # (images: export_actor.input_names)
#: Backends whose envs clip actions to the action bounds before applying them.
CLIPPING_BACKENDS = ("gymnasium", "gymnasium_async", "envpool", "native", "vecenv", "torchrl")


@dataclass
class Exported:
    """What ``export_policy`` wrote and from which checkpoint."""

    path: Path
    metadata: Path
    checkpoint: str
    chosen: str  # why this checkpoint: given, best.pt, the newest step checkpoint
    global_step: int
    #: the observation helper (export_obs.py) where the env's observation is not a flat Box
    helper: Path | None = None
    #: a recurrent policy's state, in words (None: none): what the caller carries and resets
    state: str | None = None


def out_path(out: str | Path | None, checkpoint: str | Path, fmt: str) -> Path:
    """Where to write: ``out`` (a file; a folder gets the default name; the format's suffix is
    added when missing), by default ``<run_dir>/exported/<checkpoint stem>.pt|.onnx``."""
    suffix = EXPORT_SUFFIXES[fmt]
    ckpt = Path(checkpoint)
    name = ckpt.stem + suffix
    if out is None:
        home = ckpt.parent.parent if ckpt.parent.name == "checkpoints" else ckpt.parent
        return home / "exported" / name
    p = Path(out)
    if p.is_dir():
        return p / name
    if not p.suffix:
        return p.with_suffix(suffix)
    if p.suffix != suffix:
        raise ValueError(f"--out {str(p)!r}: a {fmt} file ends in {suffix}, not {p.suffix}")
    return p


def export_policy(
    path: str | Path, fmt: str, out: str | Path | None = None, which: str | None = None
) -> Exported:
    """Export the deterministic actor of the checkpoint at ``path`` (a file or a run dir) as
    ``fmt`` (torchscript | onnx), with its metadata JSON; the file is checked against the policy."""
    if fmt not in EXPORT_SUFFIXES:
        raise ValueError(f"--format {fmt!r}; choose from {list(EXPORT_SUFFIXES)}")
    if fmt == "onnx":
        from rlexp.extras import require

        require("export", "rlexp export --format onnx", ("onnx", "onnxscript", "onnxruntime"))
    ckpt, chosen = select_checkpoint(path, which)  # rlexp eval's rule too
    check_policy_finite(ckpt)
    target = out_path(out, ckpt["path"], fmt)
    if target.exists() and not metadata_path(target).is_file():  # a checkpoint, someone's file
        raise ValueError(
            f"--out {str(target)!r} exists and is not an rlexp export (no "
            f"{metadata_path(target).name!r} beside it); rlexp export does not overwrite it"
        )
    _check_writable(target)  # a read-only run dir fails now, naming the path
    actor, config, info, samples = _actor_of(ckpt)
    if not target.parent.is_dir():
        target.parent.mkdir(parents=True)
    helper = _write_helper(target, config, info, samples)  # numpy-only flattening, beside the file
    try:
        # the exporters choose the format by the suffix: the temporary file keeps it
        atomic_write(target, lambda tmp: _WRITERS[fmt](actor, tmp), keep_suffix=True)
    except (RuntimeError, TypeError, ValueError, ImportError) as exc:  # the exporters' own kinds
        text = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        raise ValueError(f"writing the {fmt} file {str(target)!r} failed: {text}") from exc
    meta = {
        "schema": EXPORT_SCHEMA,
        "format": fmt,
        "file": target.name,
        **_io_fields(info),
        **info,
        # the env's own observation in, its own action out, with numpy only (export_obs.py)
        "observation_helper": helper,
        **_source_fields(ckpt, chosen, config),
    }
    try:
        _check_file(target, meta, actor)
    except ValueError:
        target.unlink()  # a file that does not act as the policy is worse than none
        raise
    meta_file = metadata_path(target)
    atomic_write_text(meta_file, json.dumps(meta, indent=2) + "\n")
    plain = (info["observation_layout"] or {}).get("space") == "Box" and len(
        info["observation_layout"]["parts"][0]["shape"]
    ) == 1  # the observation is the input vector already: the helper is there, not worth a line
    shown = None if helper is None or plain else target.parent / helper
    state = None
    if meta["memory"] is not None:
        m = meta["memory"]
        state = (
            f"{', '.join(x['name'] for x in m['state'])} float32 {m['state'][0]['shape']} in, "
            f"{', '.join(x['output'] for x in m['state'])} out; zeros at each episode's start"
        )
    return Exported(target, meta_file, ckpt["path"], chosen, int(ckpt["global_step"]), shown, state)


def _actor_of(
    ckpt: dict[str, Any],
) -> tuple[DeterministicActor, Any, dict[str, Any], list[tuple[Any, Any]]]:
    """The checkpoint's policy rebuilt on one copy of its env (as ``rlexp eval`` builds it) -> the
    deterministic actor, the typed config, what the metadata says about the env, and a few
    observations of its space (Gymnasium envs; they check the observation helper)."""
    from rlexp.checkpoints.files import check_checkpoint_fits, check_policy_before_building
    from rlexp.envs.factory import make_env
    from rlexp.policies.actor_critic import policy_for_env
    from rlexp.runtime.env_source import ensure_env_importable, env_name_in, run_dir_of

    name = env_name_in(ckpt["config"])
    ensure_env_importable(name, run_dir_of(ckpt["path"]))
    config = typed_config(ckpt["config"], f"checkpoint {ckpt['path']!r}")
    e = config.env
    try:
        env = make_env(e, 1, config.seed)
    except KeyError as exc:  # check_gym_id: the id, or its module's own failure, in one line
        raise ValueError(exc.args[0] if exc.args else str(exc)) from None
    try:
        check_policy_before_building(ckpt, lambda: policy_for_env(config.policy, e, env))
        policy = policy_for_env(config.policy, e, env)
        obs_dim = int(policy.obs_layout.dim)  # the env's whole vector (every group's parts)
        act_dim = int(env.action_spec.shape[-1])
        from rlexp.envs.layout_check import check_layout

        check_layout(ckpt.get("observation_layout"), env, f"checkpoint {ckpt.get('path')!r}")
        check_checkpoint_fits(ckpt, config, policy)  # loads the weights; ValueError if they don't
        base = env
        while hasattr(base, "base_env"):  # under TorchRL transforms
            base = base.base_env
        coding = getattr(base, "action_coding", None)  # rlexp's Gymnasium adapter
        layout = getattr(base, "obs_layout", None)
        if policy.categorical:
            low = high = torch.zeros(act_dim)
            start = list(coding.start) if coding is not None else [0] * act_dim
            actor = DeterministicActor(policy, low, high, False, start).eval()
        else:
            space = env.action_spec.space
            low = space.low.reshape(-1, act_dim)[0]
            high = space.high.reshape(-1, act_dim)[0]
            clamp = e.backend in CLIPPING_BACKENDS
            scaled = getattr(base, "_rescale", None)  # env.rescale_actions: the env's own bounds
            rescale = None if scaled is None else tuple(torch.as_tensor(v) for v in scaled)
            actor = DeterministicActor(policy, low, high, clamp, rescale=rescale).eval()
            if scaled is not None:  # the file's output lies in the env's bounds
                low = torch.as_tensor(coding.low, dtype=torch.float64)
                high = torch.as_tensor(coding.high, dtype=torch.float64)
        samples = _sample_observations(base) if layout is not None else []
        info = {
            "observation_dim": obs_dim,
            "action_dim": act_dim,
            # the file's inputs: the actor's vector parts and images only (docs/export.md)
            "inputs": input_records(actor, policy),
            # the parts each network read in training, by key: a deployment needs the actor's only
            "actor_observations": _keys(policy.actor_input_parts),
            "critic_observations": _keys(policy.critic_input_parts)
            if policy.critic_net is not None
            else None,
            **_names(env, config, actor_columns(policy.actor_net.inputs, obs_dim)),
            # how the env's observation became the input vector (Dict / Tuple / Discrete parts)
            "observation_layout": layout.record() if layout is not None else None,
            # what the output is and how it becomes the env's action (docs/export.md)
            "action_space": json_safe(coding.record()) if coding is not None else None,
            "action_dtype": "int64" if policy.categorical else "float32",
            "action_low": None if policy.categorical else _finite_or_none(low),
            "action_high": None if policy.categorical else _finite_or_none(high),
            "actions_clamped": actor.clamp_actions,
            # env.rescale_actions: the policy acted in [-1, 1]; the file maps it onto the bounds
            "actions_rescaled": actor.rescale,
            "observation_normalizer": {
                "enabled": actor.normalize,
                "clip": actor.clip if actor.normalize else None,
                "count": float(policy.normalizer.count),
            },
            # a recurrent actor's state: inputs after the observation, outputs after the action
            "memory": memory_record(actor, config.policy),
        }
    finally:
        env.close()
    return actor, config, info, samples


def memory_record(actor: DeterministicActor, policy_cfg: Any) -> dict[str, Any] | None:
    """The metadata's ``memory`` (None: a feed-forward policy): the actor's LSTM / GRU, its state
    inputs and outputs (the critic's memory is not in the file) and how to reset them."""
    names = state_names(actor)
    if not names:
        return None
    layers, hidden = state_shape(actor)
    return {
        "type": "lstm" if len(names) == 2 else "gru",
        "num_layers": layers,
        "hidden_size": hidden,
        "shared": bool(getattr(getattr(policy_cfg, "memory", None), "shared", False)),
        "state": [
            {
                "name": n,
                "output": f"{n}_out",
                "dtype": "float32",
                "shape": ["batch", layers, hidden],
            }
            for n in names
        ],
        "reset": "zeros at episode start",
    }


def _sample_observations(base: Any, n: int = 8) -> list[tuple[Any, Any]]:
    """``n`` observations drawn from the Gymnasium observation space of ``base`` (seeded: every
    export draws the same), each with what rlexp's env emits for it (``ObsLayout.encode``); []
    where the backend does not show the space."""
    space = None
    if getattr(base, "_envs", None):
        space = base._envs[0].observation_space
    elif getattr(base, "_vec", None) is not None:
        space = base._vec.single_observation_space
    if space is None:
        return []
    space.seed(0)
    samples = [space.sample() for _ in range(n)]
    mask = base.obs_layout.mask
    if mask is None:
        return [(obs, base.obs_layout.encode(obs)) for obs in samples]
    # an action mask: a sampled one may allow no value of a component; the samples' is drawn
    # here (valid), in the observation's key or the info the helper is then given
    rng = np.random.default_rng(0)
    out = []
    for obs in samples:
        values = np.concatenate([_one_valid(rng, k) for k in mask.nvec]).astype(np.int8)
        info = {mask.key: values}
        if mask.source == "observation":
            obs = {**obs, mask.key: values}
        out.append((obs, base.obs_layout.encode(obs, info), info))
    return out


def _one_valid(rng: np.random.Generator, n: int) -> np.ndarray:
    values = rng.random(n) < 0.5
    values[rng.integers(n)] = True
    return values


def _write_helper(
    target: Path, config: Any, info: dict[str, Any], samples: list[tuple[Any, Any]]
) -> str | None:
    """Write the observation helper beside ``target`` (Gymnasium envs: those with an observation
    layout), checked against rlexp's own flattening; its file name, or None."""
    layout, action = info["observation_layout"], info["action_space"]
    if layout is None or action is None:
        return None
    from rlexp.deploy.export_obs import check_helper, helper_name, helper_source, rlexp_inputs

    path = target.parent / helper_name(target)
    inputs = info["inputs"]
    text = helper_source(target, config.env.name, layout, action, inputs, info["memory"])
    atomic_write_text(path, text)
    if samples:
        try:
            pairs = [(s[0], rlexp_inputs(s[1], inputs)) for s in samples]
            infos = [s[2] for s in samples] if len(samples[0]) > 2 else None
            check_helper(path, pairs, infos)
        except ValueError:
            path.unlink()
            raise
    return path.name


def _names(env: Any, config: Any, columns: list[int]) -> dict[str, Any]:
    """Observation and action names where the env knows them (native tasks: term names, one per
    element of the file's ``observation`` input, i.e. of the actor's ``columns``, and each
    observation term's slice of the env's whole vector); null for Gymnasium tasks."""
    base = env
    while hasattr(base, "base_env"):  # under TorchRL transforms
        base = base.base_env
    layout = getattr(base, "observation_layout", None)
    terms = getattr(base, "_action_terms", None)
    native = config.env.native
    if layout is None or terms is None or native is None:
        return {"observation_names": None, "observation_terms": None, "action_names": None}
    obs_names = [
        _element(n, i, stop - start) for n, start, stop, _ in layout for i in range(stop - start)
    ]
    # the actor's elements only (not a critic group's)
    obs_names = [obs_names[i] for i in columns if i < len(obs_names)]
    action_names = [
        _element(key, i, part.stop - part.start)
        for key, (part, _) in zip(native.actions, terms, strict=True)
        for i in range(part.stop - part.start)
    ]
    return {
        "observation_names": obs_names,
        "observation_terms": [
            {"name": n, "start": start, "stop": stop, "shape": list(shape)}
            for n, start, stop, shape in layout
        ],
        "action_names": action_names,
    }


def _element(name: str, i: int, size: int) -> str:
    return name if size == 1 else f"{name}[{i}]"


def _finite_or_none(values: torch.Tensor) -> list[float | None]:
    """Bounds as JSON numbers; an unbounded side (+-inf, which JSON cannot hold) as null."""
    return [float(v) if torch.isfinite(v) else None for v in values]


def _keys(records: list[dict[str, Any]]) -> list[str]:
    """A network's parts by key (an image at the root: its TensorDict key; the root: "")."""
    return [r.get("image_key") or r["key"] if r["kind"] == "image" else r["key"] for r in records]


def _io_fields(info: dict[str, Any]) -> dict[str, Any]:
    """The first input's name, shape and dtype (every input: ``inputs``) and the output's."""
    first = info["inputs"][0]
    states = [s["output"] for s in (info["memory"] or {}).get("state", [])]
    return {
        "input_name": first["name"],
        "output_name": OUTPUT_NAME,
        "output_names": [OUTPUT_NAME, *states],  # the action, then a recurrent policy's state
        "input_shape": first["shape"],
        "output_shape": ["batch", info["action_dim"]],
        "dtype": first["dtype"],  # the first input's; the output's is action_dtype
    }


def _source_fields(ckpt: dict[str, Any], chosen: str, config: Any) -> dict[str, Any]:
    from rlexp import __version__

    return {
        "env_id": config.env.name,
        "env_backend": config.env.backend,
        "native_task": config.env.native.task if config.env.native is not None else None,
        "algorithm": config.algorithm.name,
        "policy": config.policy.name,
        "source_checkpoint": str(Path(ckpt["path"]).resolve()),
        "checkpoint_choice": chosen,
        "global_step": int(ckpt["global_step"]),
        "rlexp_version": __version__,
        "torch_version": torch.__version__,
        "config": ckpt["config"],  # the run's config: `rlexp eval FILE` rebuilds its env from it
    }


def _check_writable(target: Path) -> None:
    """``ValueError`` (one line: the path, why, the fix) when the exported file's folder cannot be
    created or written: before the policy is built, not halfway through the export."""
    from rlexp.run.writable import probe_dir

    longest = len(temp_path(target, keep_suffix=True).name)  # what atomic_write writes through
    try:
        probe_dir(target.parent, longest)  # and removes the folders it made
    except OSError as exc:
        from rlexp.runtime.entry import os_error_line

        raise ValueError(
            f"cannot write {str(target)!r}: {os_error_line(exc)}; give --out a path in a "
            "writable folder"
        ) from None


def _write_torchscript(actor: DeterministicActor, path: Path) -> None:
    with warnings.catch_warnings():  # torch.jit.script is deprecated in favour of torch.export
        warnings.simplefilter("ignore", DeprecationWarning)
        torch.jit.save(exported_module(actor, torchscript=True), str(path))


def _write_onnx(actor: DeterministicActor, path: Path) -> None:
    """torch.export-based exporter (torch's default and future; the TorchScript-based one is
    deprecated), a dynamic batch axis on every input, weights inside the file (no ``.data``)."""
    states = state_names(actor)
    names = [*input_names(actor), *states]
    batch = torch.export.Dim("batch")
    with warnings.catch_warnings(), quiet("torch.onnx"), quiet("torch.export"):
        warnings.simplefilter("ignore")
        torch.onnx.export(
            exported_module(actor, torchscript=False),
            tuple(probe_inputs(actor, 2)),
            str(path),
            dynamo=True,
            external_data=False,
            verbose=False,
            input_names=names,
            output_names=[OUTPUT_NAME, *(f"{n}_out" for n in states)],
            dynamic_shapes={name: {0: batch} for name in names},
        )


_WRITERS = {"torchscript": _write_torchscript, "onnx": _write_onnx}


def _check_file(path: Path, meta: dict[str, Any], actor: DeterministicActor) -> None:
    """Load the written file as a user would and compare it with the actor on a probe batch
    (vectors around the normaliser's mean, some far out so the clips act; random pixels)."""
    probe = probe_inputs(actor, 16)
    with torch.no_grad():
        want = call_actor(actor, probe)
        got = load_exported(path, meta)(*probe)
    # (a recurrent policy's file: the action and the next state, each compared)
    wants = list(want) if isinstance(want, tuple) else [want]
    gots = list(got) if isinstance(got, tuple | list) else [got]
    for g, w in zip(gots, wants, strict=False):
        same = len(gots) == len(wants) and g.shape == w.shape
        if not same or not torch.allclose(g.double(), w.double(), rtol=1e-5, atol=1e-5):
            diff = f"{float((g - w).abs().max()):.3g}" if same else "its outputs' shapes differ"
            raise ValueError(
                f"the exported {meta['format']} file {str(path)!r} does not reproduce the policy "
                f"(max difference {diff}); please report it"
            )
