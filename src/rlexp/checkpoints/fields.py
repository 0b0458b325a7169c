"""Every field of a loaded checkpoint that rlexp uses, checked for type and range before use.

A checkpoint that fails here is treated as a corrupt one (issue #29, item 8): a resume falls back to
the previous good checkpoint naming it, ``rlexp eval`` / ``export`` exit 2 with one line. Without
these checks a ``global_step`` of 2**70 or a config without its ``policy`` section ended in a
traceback or, worse, in a run that went on from garbage (a negative normaliser count, a float16
weight cast silently to float32). ``check_fields`` needs only the checkpoint;
``check_tensors_fit`` compares its tensors with the model they are loaded into.
"""

from __future__ import annotations

import math
import random
from collections.abc import Mapping
from typing import Any, Literal

import numpy as np
import torch

#: The sections of the stored config that rebuilding the run needs.
CONFIG_SECTIONS = ("env", "policy", "algorithm", "trainer")
#: A ``global_step`` beyond this many times the run's budget is not one a run of it reached.
STEP_SLACK = 1000
#: numpy bit generators an event manager's RNG may use.
BIT_GENERATORS = ("PCG64", "PCG64DXSM", "MT19937", "Philox", "SFC64")


#: What the loaded checkpoint is for: its contents only; rebuilding its run from the stored config
#: (eval, export); or continuing its run (which reads every section).
Use = Literal["read", "rebuild", "resume"]


class FieldError(ValueError):
    """A field of the wrong type or out of its range; the message names the field and value."""


def _shown(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _int_in(value: Any, field: str, low: int, high: int) -> int:
    if not _is_int(value) or not low <= value <= high:
        raise FieldError(f"{field}={_shown(value)}; expected an int in [{low}, {high}]")
    return value


def _mapping(value: Any, field: str) -> Mapping[str, Any]:
    if not isinstance(value, Mapping):
        raise FieldError(f"{field} is {type(value).__name__}, not a dict")
    return value


def _tensor(
    value: Any, field: str, dtypes: tuple[torch.dtype, ...], ndim: int | None
) -> torch.Tensor:
    if not isinstance(value, torch.Tensor):
        raise FieldError(f"{field} is {type(value).__name__}, not a tensor")
    if value.dtype not in dtypes:
        raise FieldError(f"{field} is {value.dtype}, expected {' or '.join(map(str, dtypes))}")
    if ndim is not None and value.dim() != ndim:
        raise FieldError(f"{field} has shape {tuple(value.shape)}; expected {ndim} dimensions")
    return value


def max_step(config: Mapping[str, Any]) -> int:
    """The largest ``global_step`` a run of ``config`` can have written: ``STEP_SLACK`` times its
    budget plus a batch (distributed runs count every rank's frames; a resumed run may have been
    given a smaller budget later), at most 2**53."""
    t = config.get("trainer") or {}
    batch = t.get("frames_per_batch") if _is_int(t.get("frames_per_batch")) else 0
    budget = t.get("total_frames") if _is_int(t.get("total_frames")) else 0
    if _is_int(t.get("iterations")):
        budget = max(budget, t["iterations"] * max(batch, 1))
    if budget <= 0:
        return 2**53
    return min(2**53, STEP_SLACK * (budget + max(batch, 1)))


def check_fields(ckpt: Mapping[str, Any], file_step: int | None, use: Use) -> None:
    """``FieldError`` naming the first field of the wrong type or range. ``file_step``: the step the
    file's name says (``*_step_N.pt``); ``use``: which sections must be there (``Use``)."""
    config = _mapping(ckpt.get("config"), "config")
    for key in CONFIG_SECTIONS if use != "read" else ():
        if not isinstance(config.get(key), Mapping):
            found = "missing" if key not in config else type(config[key]).__name__
            raise FieldError(
                f"config.{key} is {found}: the stored config lacks its {key!r} section, which "
                "rebuilding the run needs"
            )
    step = _int_in(ckpt.get("global_step"), "global_step", 0, max_step(config))
    if file_step is not None and step != file_step:
        raise FieldError(f"global_step={step}, but the file's name says step {file_step}")
    check_state(ckpt, step, resume=use == "resume")
    flight = ckpt.get("eval_in_flight")
    if flight is not None:
        flight = _mapping(flight, "eval_in_flight")
        at = _int_in(flight.get("step"), "eval_in_flight.step", 0, step)
        if not isinstance(flight.get("save", False), bool):
            raise FieldError(f"eval_in_flight.save={_shown(flight.get('save'))}; expected a bool")
        state = _mapping(flight.get("state"), "eval_in_flight.state")
        try:
            _mapping(state.get("policy"), "policy")
            check_state(state, at, resume=False)
        except FieldError as exc:
            raise FieldError(f"eval_in_flight.state.{exc}") from None


def check_state(sd: Mapping[str, Any], step: int, resume: bool) -> None:
    """The trainer state's fields (a checkpoint's, or the snapshot of an eval round in flight)."""
    _check_policy(_mapping(sd.get("policy"), "policy"))
    _check_algorithm(_mapping(sd.get("algorithm"), "algorithm"), step)
    required = ("windows", "events", "rng") if resume else ()
    for key in required:
        if key not in sd:
            raise FieldError(f"{key} is missing: a resume needs it")
    if "windows" in sd:
        _check_windows(_mapping(sd["windows"], "windows"))
    if "events" in sd:
        _check_events(_mapping(sd["events"], "events"), resume)
    if "rng" in sd:
        _check_rng(_mapping(sd["rng"], "rng"))
    if sd.get("envs") is not None:
        envs = _mapping(sd["envs"], "envs")
        if "train" in envs:
            _mapping(envs["train"], "envs.train")
    for key in ("observation_layout", "hooks", "versions"):
        if sd.get(key) is not None:
            _mapping(sd[key], key)
    for name, value in _mapping(sd.get("last_eval") or {}, "last_eval").items():
        if not isinstance(name, str) or not _is_number(value):
            raise FieldError(f"last_eval[{_shown(name)}]={_shown(value)}; expected a number")
    best = sd.get("best_metric", -math.inf)
    if not _is_number(best) or math.isnan(best):
        raise FieldError(f"best_metric={_shown(best)}; expected a number (-inf: none yet)")
    _check_pending_observation(sd.get("pending_observation"))
    if sd.get("pending_rollout") is not None:
        _check_pending_rollout(_mapping(sd["pending_rollout"], "pending_rollout"))


def _check_pending_observation(pending: Any) -> None:
    """A float tensor, or (images) a mapping of a float ``vector`` and uint8 image tensors."""
    if pending is None or (isinstance(pending, torch.Tensor) and pending.is_floating_point()):
        return
    if isinstance(pending, Mapping) and pending:
        for key, value in pending.items():
            image = isinstance(value, torch.Tensor) and value.dtype == torch.uint8
            floats = isinstance(value, torch.Tensor) and value.is_floating_point()
            mask = isinstance(value, torch.Tensor) and value.dtype == torch.bool
            want = {"vector": floats, "action_mask": mask}.get(key, image)
            if not (isinstance(key, str) and want):
                raise FieldError(
                    f"pending_observation[{_shown(key)}] is {_shown(value)[:40]}; expected a float "
                    "'vector', uint8 images or a bool 'action_mask'"
                )
        return
    raise FieldError(f"pending_observation is {_shown(pending)[:40]}, not a float tensor")


#: What the update reads of a rollout (``algorithm.overlap``'s pending one: rlexp/training/overlap.py).
ROLLOUT_KEYS = {"": ("observation", "action", "action_log_prob"), "next": ("reward", "done")}


def _check_pending_rollout(rollout: Mapping[str, Any]) -> None:
    """[envs, steps] as its batch size; what the update reads present; every tensor of that
    leading shape."""
    size = rollout.get("batch_size")
    if not (
        isinstance(size, list)
        and len(size) == 2
        and all(isinstance(n, int) and not isinstance(n, bool) and 0 < n <= 10**8 for n in size)
    ):
        raise FieldError(f"pending_rollout.batch_size={_shown(size)}; expected [envs, steps]")

    def walk(data: Any, inner: str) -> None:
        path = f"pending_rollout.data{inner}"
        data = _mapping(data, path)
        for key in ROLLOUT_KEYS.get(inner.lstrip("."), ()):
            if key not in data:
                raise FieldError(f"{path}.{key} is missing: the update reads it")
        for key, value in data.items():
            if isinstance(value, Mapping):
                walk(value, f"{inner}.{key}")
            elif not isinstance(value, torch.Tensor) or list(value.shape[:2]) != size:
                raise FieldError(
                    f"{path}.{key} is {_shown(value)[:40]}; expected a tensor of {size} x ..."
                )

    walk(rollout.get("data"), "")


def _check_policy(policy: Mapping[str, Any]) -> None:
    """Tensors only; the observation normaliser's count and variance not negative (shapes and
    dtypes are compared with the model's in ``check_tensors_fit``)."""
    for key, value in policy.items():
        if not isinstance(key, str) or not isinstance(value, torch.Tensor):
            raise FieldError(f"policy[{_shown(key)}] is {type(value).__name__}, not a tensor")
        leaf = key.rsplit(".", 2)[-2:]
        if leaf[:1] == ["normalizer"] and leaf[-1] in ("count", "var") and value.numel():
            if not value.is_floating_point() or not bool((value >= 0).all()):
                raise FieldError(f"policy.{key} holds negative values; a count or variance can't")


def _check_algorithm(algorithm: Mapping[str, Any], step: int) -> None:
    iteration = algorithm.get("iteration")
    if not _is_int(iteration) or iteration < 0:
        raise FieldError(f"algorithm.iteration={_shown(iteration)}; expected an int >= 0")
    _int_in(iteration, "algorithm.iteration", 0, step)
    opt = algorithm.get("optimizer")
    if opt is not None:
        _check_optimizer(_mapping(opt, "algorithm.optimizer"))
    for name, value in _mapping(algorithm.get("hyperparameters") or {}, "hyperparameters").items():
        if not _is_number(value) or not math.isfinite(value):
            raise FieldError(f"algorithm.hyperparameters.{name}={_shown(value)}; expected a number")
    if algorithm.get("reward_normalizer") is not None:
        from rlexp.algorithms.normalize import check_state as check_normalizer

        try:
            check_normalizer(_mapping(algorithm["reward_normalizer"], "reward_normalizer"))
        except ValueError as exc:
            raise FieldError(f"algorithm.reward_normalizer.{exc}") from None
    if algorithm.get("reference") is not None:
        for key, value in _mapping(algorithm["reference"], "algorithm.reference").items():
            _tensor(value, f"algorithm.reference.{key}", (torch.float32, torch.float64), None)


def _check_optimizer(opt: Mapping[str, Any]) -> None:
    groups = opt.get("param_groups")
    if not isinstance(groups, list) or not all(isinstance(g, Mapping) for g in groups):
        raise FieldError("algorithm.optimizer.param_groups is not a list of dicts")
    for i, group in enumerate(groups):
        params = group.get("params")
        if not isinstance(params, list) or not all(_is_int(p) for p in params):
            raise FieldError(f"algorithm.optimizer.param_groups[{i}].params is not a list of ints")
        for key in ("lr", "eps", "weight_decay"):
            value = group.get(key, 0.0)
            if not _is_number(value) or not 0 <= value < math.inf:
                raise FieldError(
                    f"algorithm.optimizer.param_groups[{i}].{key}={_shown(value)}; expected a "
                    "finite number >= 0"
                )
    for index, state in _mapping(opt.get("state") or {}, "algorithm.optimizer.state").items():
        where = f"algorithm.optimizer.state[{_shown(index)}]"
        for key, value in _mapping(state, where).items():
            if key == "step":
                ok = _is_int(value) or (isinstance(value, torch.Tensor) and value.numel() == 1)
                if not ok or not 0 <= float(value) < 2**53:
                    raise FieldError(f"{where}.step={_shown(value)}; expected a count >= 0")
            elif isinstance(value, torch.Tensor) and key == "exp_avg_sq":
                if not value.is_floating_point() or not bool((value >= 0).all()):
                    raise FieldError(f"{where}.exp_avg_sq holds negative values")


def _check_windows(windows: Mapping[str, Any]) -> None:
    returns, lengths = windows.get("returns", []), windows.get("lengths", [])
    if not isinstance(returns, list) or not all(
        _is_number(r) and math.isfinite(r) for r in returns
    ):
        raise FieldError("windows.returns is not a list of finite numbers")
    if not isinstance(lengths, list) or not all(_is_int(n) and n >= 0 for n in lengths):
        raise FieldError("windows.lengths is not a list of ints >= 0")
    if "running_return" in windows or "running_length" in windows:
        ret = _tensor(windows.get("running_return"), "windows.running_return", _FLOATS, 1)
        n = _tensor(windows.get("running_length"), "windows.running_length", (torch.int64,), 1)
        if ret.shape != n.shape or bool((n < 0).any()):
            raise FieldError("windows.running_length does not match running_return, or is < 0")


_FLOATS = (torch.float32, torch.float64)


def _check_events(events: Mapping[str, Any], resume: bool) -> None:
    for where in ("train", "eval"):
        if where not in events:
            if resume:
                raise FieldError(f"events.{where} is missing: a resume needs it")
            continue
        sd = _mapping(events[where], f"events.{where}")
        for name, count in _mapping(sd.get("counters") or {}, f"events.{where}.counters").items():
            if not _is_int(count) or count < 0:
                raise FieldError(f"events.{where}.counters.{name}={_shown(count)}; expected >= 0")
        if "rng" in sd:
            _check_bit_generator(sd["rng"], f"events.{where}.rng")
        _mapping(sd.get("events") or {}, f"events.{where}.events")


def _check_bit_generator(state: Any, field: str) -> None:
    """The state a numpy ``Generator``'s bit generator accepts (set on a throw-away one)."""
    name = state.get("bit_generator") if isinstance(state, Mapping) else None
    if name not in BIT_GENERATORS:
        raise FieldError(f"{field} is not a numpy bit generator state ({_shown(name)})")
    try:
        getattr(np.random, name)().state = dict(state)
    except (TypeError, ValueError, KeyError, OverflowError) as exc:
        raise FieldError(f"{field} is not a valid {name} state ({str(exc)[:80]})") from None


def _check_rng(rng: Mapping[str, Any]) -> None:
    """Each RNG state as its library takes it, set on a throw-away generator (a bad one would
    otherwise fail only when training starts, after the run dir was written)."""
    checks = {
        "python": lambda s: random.Random().setstate(s),
        "numpy": _set_numpy,
        "torch": lambda s: torch.Generator().set_state(_tensor(s, "rng.torch", (torch.uint8,), 1)),
    }
    for key, check in checks.items():
        if key not in rng:
            continue
        try:
            check(rng[key])
        except FieldError:
            raise
        except (TypeError, ValueError, KeyError, RuntimeError, OverflowError) as exc:
            raise FieldError(f"rng.{key} is not a valid state ({str(exc)[:80]})") from None
    cuda = rng.get("cuda", [])
    if not isinstance(cuda, list) or not all(
        isinstance(t, torch.Tensor) and t.dtype == torch.uint8 for t in cuda
    ):
        raise FieldError("rng.cuda is not a list of uint8 tensors")


def _set_numpy(state: Any) -> None:
    state = _mapping(state, "rng.numpy")
    key = _tensor(state.get("key"), "rng.numpy.key", (torch.int64,), 1)
    if key.numel() != 624 or bool(((key < 0) | (key >= 2**32)).any()):
        raise FieldError("rng.numpy.key is not 624 values in [0, 2**32)")
    pos = _int_in(state.get("pos"), "rng.numpy.pos", 0, 624)
    gauss = _int_in(state.get("has_gauss"), "rng.numpy.has_gauss", 0, 1)
    cached = state.get("cached_gaussian")
    if not _is_number(cached) or not math.isfinite(cached):
        raise FieldError(f"rng.numpy.cached_gaussian={_shown(cached)}; expected a number")
    np.random.RandomState().set_state(
        ("MT19937", key.numpy().astype(np.uint32), pos, gauss, float(cached))
    )


def check_tensors_fit(ckpt: Mapping[str, Any], policy: torch.nn.Module) -> None:
    """``FieldError`` when a policy tensor (the checkpoint's, an eval round's snapshot's, GRPO's
    reference) has another dtype or shape than the model's: ``load_state_dict`` would cast it
    silently, and the evaluation of a float16 copy would be reported as the run's result."""
    where = f"checkpoint {str(ckpt.get('path'))!r}"
    own = policy.state_dict()
    states = [("policy", ckpt["policy"], own)]
    flight = ckpt.get("eval_in_flight")
    if isinstance(flight, Mapping) and isinstance(flight.get("state"), Mapping):
        states.append(("eval_in_flight.state.policy", flight["state"]["policy"], own))
    reference = (ckpt.get("algorithm") or {}).get("reference")
    actor = getattr(policy, "actor", None)
    if isinstance(reference, Mapping) and isinstance(actor, torch.nn.Module):
        states.append(("algorithm.reference", reference, actor.state_dict()))
    for section, theirs, mine in states:
        for key, value in theirs.items():
            expected = mine.get(key)
            if expected is None:
                continue  # load_state_dict names unexpected keys
            if value.dtype != expected.dtype:
                raise FieldError(
                    f"{where}: {section}.{key} is {value.dtype}, this config's policy has "
                    f"{expected.dtype} (rlexp does not cast weights: the numbers would not be the "
                    "trained ones)"
                )
            if value.shape != expected.shape:
                raise FieldError(
                    f"the checkpoint's policy does not fit this config's policy (size mismatch "
                    f"for {section}.{key}: shape {tuple(value.shape)} in {where}, "
                    f"{tuple(expected.shape)} in this config's policy)"
                )
