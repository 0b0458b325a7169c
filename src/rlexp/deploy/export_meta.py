"""An exported policy's metadata JSON is data: what ``rlexp eval FILE`` may take from it, checked
before anything is built from it (docs/export.md, docs/envs.md "Security: what a name may import").

A file people share must never be a route to code: every field has the type ``rlexp export``
writes, the env names in its config import nothing outside the allowlist (``module:EnvId`` and
``module:callable`` alike: an allowed module, or one a plugin already imported), and the action
space it was made for is the env's own, so the file's outputs mean the same actions.

Only the standard library is imported at module level (``rlexp.deploy.policy_eval`` loads this early).
"""

from __future__ import annotations

import re
import sys
from typing import Any

#: The action kinds an export writes (rlexp.envs.spaces.ActionCoding.kind).
ACTION_KINDS = ("box", "discrete", "multi_discrete", "multi_binary")


def _int(value: Any, low: int) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= low


def _ints(value: Any, low: int | None = None) -> bool:
    return isinstance(value, list) and all(
        isinstance(v, int) and not isinstance(v, bool) and (low is None or v >= low) for v in value
    )


def check_fields(meta: dict[str, Any], where: str) -> None:
    """A ValueError of one line naming the field when a field is not what an export writes."""

    def bad(key: str, want: str) -> ValueError:
        return ValueError(
            f"{where}: {key}={meta.get(key)!r} is not {want} (export metadata is data)"
        )

    if not _int(meta.get("global_step"), 0):
        raise bad("global_step", "a whole number >= 0")
    if not _int(meta.get("action_dim"), 1):
        raise bad("action_dim", "a whole number >= 1")
    # an env of images only has no vector (dim 0); one without inputs (older rlexp) has one
    if not _int(meta.get("observation_dim"), 0 if meta.get("inputs") is not None else 1):
        raise bad("observation_dim", "a whole number >= 1 (>= 0 with inputs)")
    if meta.get("inputs") is not None:
        check_inputs(meta["inputs"], where)
    if meta.get("memory") is not None:
        check_memory(meta, where)
    for key in ("actor_observations", "critic_observations"):
        value = meta.get(key)
        if value is not None and not (
            isinstance(value, list) and all(isinstance(v, str) for v in value)
        ):
            raise bad(key, "a list of observation keys or null")
    for key in ("input_name", "output_name"):
        if meta["format"] == "onnx" and not isinstance(meta.get(key), str):
            raise bad(key, "a string")
    if meta.get("source_checkpoint") is not None and not isinstance(meta["source_checkpoint"], str):
        raise bad("source_checkpoint", "a path or null")
    if meta.get("observation_layout") is not None and not isinstance(
        meta["observation_layout"], dict
    ):
        raise bad("observation_layout", "an object or null")
    space = meta.get("action_space")
    if space is None:
        return
    if not isinstance(space, dict) or space.get("kind") not in ACTION_KINDS:
        raise bad("action_space", f"an object whose kind is one of {list(ACTION_KINDS)}")
    if space["kind"] != "box":
        nvec, start = space.get("nvec"), space.get("start")
        if not (_ints(nvec, 1) and _ints(start) and len(nvec) == len(start) == meta["action_dim"]):
            raise bad("action_space", f"categorical with {meta['action_dim']} nvec and start ints")


#: An input's kind -> its dtype and the number of dims after the batch.
INPUT_KINDS = {"vector": ("float32", 1), "image": ("uint8", 3)}
#: How an env may give an image (envs/images.py image_layout), as the helper converts it.
SOURCE_LAYOUTS = ("hw", "hwc", "chw", "stack_hwc", "stack_chw")
_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*\Z")


def check_inputs(inputs: Any, where: str) -> None:
    """The metadata's ``inputs`` (what the file takes; export_actor.input_records) as an export
    writes them: a ValueError of one line naming the input and the field otherwise."""
    if not isinstance(inputs, list) or not inputs or not all(isinstance(i, dict) for i in inputs):
        raise ValueError(f"{where}: inputs={inputs!r} is not a list of input objects (export "
                         "metadata is data)")  # fmt: skip
    names: list[str] = []
    for n, spec in enumerate(inputs):

        def bad(key: str, want: str, n: int = n, spec: dict = spec) -> ValueError:
            return ValueError(
                f"{where}: inputs[{n}].{key}={spec.get(key)!r} is not {want} (export metadata is "
                "data)"
            )

        name, kind = spec.get("name"), spec.get("kind")
        if not isinstance(name, str) or not _NAME.match(name) or name in names:
            raise bad("name", "a new identifier")
        names.append(name)
        if kind not in INPUT_KINDS:
            raise bad("kind", f"one of {list(INPUT_KINDS)}")
        dtype, rank = INPUT_KINDS[kind]
        if spec.get("dtype") != dtype:
            raise bad("dtype", repr(dtype))
        shape = spec.get("shape")
        if not (isinstance(shape, list) and len(shape) == rank + 1 and shape[0] == "batch"
                and _ints(shape[1:], 1)):  # fmt: skip
            raise bad("shape", f'["batch", {rank} whole numbers >= 1]')
        if not isinstance(spec.get("key"), str) or not spec["key"]:
            raise bad("key", "an observation key")
        groups = spec.get("groups")
        if not (isinstance(groups, list) and groups and all(isinstance(g, str) for g in groups)):
            raise bad("groups", "a list of group names")
        parts = spec.get("parts")
        if not (isinstance(parts, list) and parts and all(_part(p) for p in parts)):
            raise bad("parts", "a list of observation parts (key, kind, shape, offset, size)")
        if kind == "vector" and sum(p["size"] for p in parts) != shape[1]:
            raise bad("parts", f"parts whose sizes add up to the input's {shape[1]}")
        if kind == "image" and (len(parts) != 1 or parts[0]["kind"] != "image"
                                or parts[0]["shape"] != shape[1:]):  # fmt: skip
            raise bad("parts", f"one image part of shape {shape[1:]}")


#: A recurrent export's memory type -> its state inputs (outputs: each name + ``_out``).
MEMORY_STATES = {"lstm": ["actor_h", "actor_c"], "gru": ["actor_h"]}
#: The one reset rule an export writes (export.memory_record).
MEMORY_RESET = "zeros at episode start"


def check_memory(meta: dict[str, Any], where: str) -> None:
    """A recurrent export's ``memory`` (and ``output_names``) as ``rlexp export`` writes them
    (export.memory_record): a ValueError of one line naming the field otherwise."""
    memory = meta["memory"]

    def bad(key: str, want: str) -> ValueError:
        value = memory.get(key) if isinstance(memory, dict) else memory
        return ValueError(
            f"{where}: memory.{key}={value!r} is not {want} (export metadata is data)"
        )

    if not isinstance(memory, dict) or memory.get("type") not in MEMORY_STATES:
        raise bad("type", f"one of {list(MEMORY_STATES)}")
    for key in ("num_layers", "hidden_size"):
        if not _int(memory.get(key), 1):
            raise bad(key, "a whole number >= 1")
    if not isinstance(memory.get("shared", False), bool):
        raise bad("shared", "true or false")
    if memory.get("reset") != MEMORY_RESET:
        raise bad("reset", repr(MEMORY_RESET))
    names = MEMORY_STATES[memory["type"]]
    shape = ["batch", memory["num_layers"], memory["hidden_size"]]
    want = [{"name": n, "output": f"{n}_out", "dtype": "float32", "shape": shape} for n in names]
    if memory.get("state") != want:
        raise bad("state", f"{want}")
    taken = {i.get("name") for i in meta.get("inputs") or [] if isinstance(i, dict)}
    if taken & set(names):
        raise bad("state", f"names apart from the inputs' {sorted(taken)}")
    outputs = ["action", *(f"{n}_out" for n in names)]
    if meta.get("output_names", outputs) != outputs:
        raise ValueError(f"{where}: output_names={meta['output_names']!r} is not {outputs} "
                         "(export metadata is data)")  # fmt: skip


def _part(p: Any) -> bool:
    """An observation part record (envs.spaces.ObsPart.record) with the types it is written with."""
    return (
        isinstance(p, dict)
        and isinstance(p.get("key"), str)
        and isinstance(p.get("kind"), str)
        and _ints(p.get("shape"), 0)
        and _int(p.get("offset"), -1)
        and _int(p.get("size"), 0)
        and all(_ints(p[k]) for k in ("nvec", "start") if k in p)
        and all(isinstance(p[k], str) for k in ("group", "image_key", "source_layout") if k in p)
        and (p["kind"] != "image" or p.get("source_layout") in SOURCE_LAYOUTS)
    )


def check_env_names(env: Any, where: str) -> None:
    """The data rule: ``env.name`` and every string in ``env.kwargs`` that names a module (``a:B``)
    import nothing: the module is under the env allowlist (rlexp.envs.batched.allowed_modules: rlexp's,
    a plugin's, the shell's ``RLEXP_ENV_MODULES``) or already imported (a plugin's). The callable
    of a batched backend is checked again when the env is built (rlexp.common.registry.reach)."""
    from rlexp.common.registry import check_module_name, module_of, strings_in, under
    from rlexp.envs.batched import ENV_MODULES_VAR, allowed_modules

    if env.backend in ("vecenv", "torchrl"):  # the callable: through the gate, nothing called
        from rlexp.envs.batched import resolve_env_factory

        try:
            resolve_env_factory(env.name, env.backend)
        except ValueError as exc:
            raise ValueError(f"{where}: {exc}") from None
    named = [("env.name", env.name)]
    named += [(f"env.kwargs.{k}", v) for k, v in strings_in(env.kwargs or {})]
    for key, value in named:
        module = module_of(value)
        if module is None:
            continue
        line = f"{where}: {key}={value!r}"
        check_module_name(module, line, None)
        if under(module, allowed_modules()) or module in sys.modules:
            continue
        raise ValueError(
            f"{line} would import module {module!r}, which is not allowed: an exported file's "
            f"metadata never imports code; if you trust it, allow the module from the shell "
            f"({ENV_MODULES_VAR}={module.split('.')[0]}) or install the plugin that registers the env"
        )


def check_action_space(meta: dict[str, Any], env: Any, where: str) -> None:
    """A ValueError of one line when the env's actions are not the ones the file was made for
    (another ``start``, ``nvec``, kind or bounds): its outputs would be other actions."""
    dim = int(env.action_spec.shape[-1])
    if dim != meta["action_dim"]:
        raise ValueError(
            f"{where} outputs {meta['action_dim']} action values; the env of its config takes {dim}"
        )
    base = env
    while hasattr(base, "base_env"):  # under TorchRL transforms
        base = base.base_env
    coding = getattr(base, "action_coding", None)
    if coding is None:
        return
    now, saved = json_safe(coding.record()), meta.get("action_space")
    if saved != now:
        diff = sorted(k for k in {*now, *(saved or {})} if (saved or {}).get(k) != now.get(k))
        said = {k: (saved or {}).get(k) for k in diff}
        raise ValueError(
            f"{where} was made for another action space: its metadata says {said}, the env has "
            f"{ {k: now.get(k) for k in diff} }; re-export the policy from its checkpoint"
        )


def json_safe(record: dict[str, Any]) -> dict[str, Any]:
    """An action coding's record with unbounded sides (+-inf: a batched torch env's Box) as null,
    as the metadata holds it."""
    return {
        k: [None if isinstance(x, float) and x in (float("inf"), float("-inf")) else x for x in v]
        if k in ("low", "high") else v
        for k, v in record.items()
    }  # fmt: skip
