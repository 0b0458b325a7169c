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

glibc's ``malloc`` gives freed memory back to the kernel (blocks above its mmap threshold, and the
heap's top beyond its trim threshold), and the next allocation of that size faults every page in
again, zeroed by the kernel. A PPO update of an image policy allocates and frees tens of MB per
minibatch (the float images, the convolutions' activations and gradients): 1.8 million page
faults and 3.2 s of kernel time in a 16-update Pong run. ``keep_freed_memory`` makes the process
keep it (``mallopt``: blocks up to 32 MB from the heap, the heap's top given back only beyond
1 GiB), so those allocations reuse pages already faulted in (an 8-update run: 1.5 million -> 0.2
million faults, 2.8 s -> 0.7 s of kernel time; peak RSS +2%). Not where the user tuned glibc's
malloc (``GLIBC_TUNABLES``, ``MALLOC_*_``), nor with another C library.
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import gc
import importlib
import importlib.util
import os
import sys
import types
from collections.abc import Iterator

_applied = False
#: glibc's ``mallopt`` parameters (malloc.h) and the values ``keep_freed_memory`` gives them: the
#: mmap threshold at glibc's own ceiling for it (64-bit), the trim threshold at 1 GiB
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
KEPT_MALLOC = {M_MMAP_THRESHOLD: 32 * 2**20, M_TRIM_THRESHOLD: 2**30}


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
    keep_freed_memory()
    _applied = True


def keep_freed_memory() -> bool:
    """glibc's malloc keeps freed memory for the next allocations (module docstring); whether it
    was set (False: not glibc, or the user's own malloc settings in the environment)."""
    if not sys.platform.startswith("linux") or "glibc" not in _libc():
        return False
    if "malloc" in os.environ.get("GLIBC_TUNABLES", "") or any(
        k.startswith("MALLOC_") and k.endswith("_") for k in os.environ
    ):
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    return all([mallopt(param, value) == 1 for param, value in KEPT_MALLOC.items()])


def _libc() -> str:
    """The C library's name and version (``glibc 2.36``), or "" where it is unknown."""
    try:
        return os.confstr("CS_GNU_LIBC_VERSION") or ""
    except (ValueError, OSError, AttributeError):
        return ""


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
