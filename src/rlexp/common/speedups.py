"""Scoped work-arounds for per-call overhead in the libraries we build on.

``tensordict`` looks up ``importlib.util.find_spec("pandas")`` inside ``TensorDict.from_any``, which
every ``TensorDictModule`` output write goes through: three file-system searches per PPO minibatch
and two per collected env step (~8% of a profile here). We give ``tensordict.base`` alone a cached
``find_spec``; nothing else in the process is affected.

Python's cyclic garbage collector, for the same reason: a training process holds ~400k objects from
its imports alone (torch, its dynamo and sympy, TorchRL, Hydra), and each full collection walks all
of them, ~0.2 s here. The imports trigger dozens (``import torchrl``: 2.9 s with the collector on,
2.2 s with it off) and the training loop one every few iterations (a HalfCheetah rollout's 2048
TensorDicts are enough). So the collector is off while a run starts (``startup_gc``), and when the
run has been built everything that exists is moved out of its reach (``gc.freeze``) and the
collector turned back on (``training_gc``): it then walks only what training itself creates. A
later run in the same process (a sweep's jobs one after another, tests) unfreezes and collects
first (``release_frozen``), so nothing of an earlier run is kept for good.
"""

from __future__ import annotations

import contextlib
import functools
import gc
import importlib
import importlib.util
import types
from collections.abc import Iterator

_applied = False


def apply() -> None:
    """Install the work-arounds once (idempotent)."""
    global _applied
    if _applied:
        return
    import tensordict.base as td_base

    cached = functools.lru_cache(maxsize=None)(importlib.util.find_spec)
    td_base.importlib = types.SimpleNamespace(
        util=types.SimpleNamespace(find_spec=cached),
        import_module=importlib.import_module,
    )
    _applied = True


@contextlib.contextmanager
def startup_gc() -> Iterator[None]:
    """The cyclic GC off inside (imports, config, build), its previous state restored after."""
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            gc.enable()
        else:
            gc.disable()


def training_gc() -> None:
    """Before the training loop: what the start-up built stays for good (``gc.freeze``), and the GC
    is on for what the loop creates."""
    gc.freeze()
    gc.enable()


def release_frozen() -> None:
    """At a run's start: what an earlier run in this process froze becomes collectable, and is."""
    if gc.get_freeze_count():
        gc.unfreeze()
        gc.collect()


def sweep_gc() -> None:
    """A sweep's own loop (sweeper, launcher, SLURM polling for hours) runs with the GC; each of its
    jobs builds without it (``rlexp.app.train``)."""
    gc.enable()
