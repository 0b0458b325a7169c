"""Multi-process training (``torchrun --nproc_per_node=N train.py --distributed ...``).

Each rank runs its own envs (seeded ``seed + rank``), collects its share of every batch and takes
part in every optimiser step: gradients are all-reduced (averaged) explicitly after each backward
pass, so the synchronisation cannot be bypassed by calling a module directly (the bug of the system
our users come from). Parameters are broadcast from rank 0 at start; observation-normaliser
statistics are reduced across ranks; rank 0 alone logs, evaluates and saves. All ranks share one run
dir: rank 0 picks the timestamp before Hydra starts and broadcasts it.

Backend: gloo on CPU, nccl when CUDA is available (each rank on ``cuda:<local_rank>``). Under SLURM,
``hydra/launcher=slurm`` with ``tasks_per_node=N`` starts the ranks; submitit's environment sets
RANK / WORLD_SIZE / LOCAL_RANK / MASTER_ADDR / MASTER_PORT (docs/distributed.md).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import timedelta
from typing import Any

log = logging.getLogger(__name__)

FLAG = "--distributed"
TIMEOUT_KEY = "trainer.stall_timeout_s"


class CollectiveTimeout(RuntimeError):
    """Another rank did not join a collective within ``trainer.stall_timeout_s``."""


@dataclass
class DistInfo:
    """This process's place in the job (a single process: rank 0 of 1)."""

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0
    backend: str | None = None

    @property
    def enabled(self) -> bool:
        return self.backend is not None

    @property
    def is_main(self) -> bool:
        return self.rank == 0


_INFO = DistInfo()
#: How long a collective waits for the other ranks (gloo's own default is 30 minutes).
_TIMEOUT_S: float | None = None


def info() -> DistInfo:
    return _INFO


def split_flag(argv: Sequence[str]) -> tuple[bool, list[str]]:
    """(whether ``--distributed`` was given, the other arguments)."""
    rest = [a for a in argv if a != FLAG]
    return len(rest) != len(argv), rest


def _env_from_submitit() -> None:
    """Under SLURM without torchrun, take the ranks from submitit's / SLURM's environment."""
    if "RANK" in os.environ or "SLURM_PROCID" not in os.environ:
        return
    try:
        import submitit

        env = submitit.helpers.TorchDistributedEnvironment().export()
        log.info("distributed from SLURM: rank %d of %d", env.rank, env.world_size)
    except Exception as exc:  # not inside a submitit job
        raise RuntimeError(
            f"--distributed under SLURM needs submitit's environment: {exc}"
        ) from exc


def command_line_timeout(argv: Sequence[str]) -> float:
    """``trainer.stall_timeout_s`` as the command line sets it, else its default: the bound of the
    collectives until the config is composed (``set_timeout`` then applies the config's value)."""
    from rlexp.config.schema import TrainerConfig

    value: float = TrainerConfig.stall_timeout_s
    for arg in argv:
        key, _, text = arg.partition("=")
        if key.lstrip("+") == TIMEOUT_KEY:
            try:
                value = float(text)
            except ValueError:
                pass  # the config check names the bad value
    return value if value > 0 else TrainerConfig.stall_timeout_s


def set_timeout(seconds: float) -> None:
    """Bound every later collective of this process group by ``seconds`` (the config's
    ``trainer.stall_timeout_s``): a rank that stops makes the others fail within it."""
    import torch.distributed as dist

    global _TIMEOUT_S
    if not (_INFO.enabled and dist.is_initialized()) or seconds == _TIMEOUT_S:
        return
    set_pg_timeout = getattr(dist.distributed_c10d, "_set_pg_timeout", None)
    if set_pg_timeout is None:  # an older torch: the bound given at init stays
        log.warning("this torch cannot change the collective timeout; it stays %s s", _TIMEOUT_S)
        return
    set_pg_timeout(timedelta(seconds=seconds))
    _TIMEOUT_S = seconds


@contextmanager
def _bounded(op: str) -> Iterator[None]:
    """A collective that timed out waiting for another rank, as one line naming the bound."""
    try:
        yield
    except RuntimeError as exc:
        text = str(exc).lower()
        if "timed out" not in text and "timeout" not in text:
            raise
        raise CollectiveTimeout(
            f"rank {_INFO.rank}: {op} waited more than {TIMEOUT_KEY}={_TIMEOUT_S:g} s for the "
            "other ranks (one of them stopped, or is stuck in its env or an eval round)"
        ) from None


def _join(how_to_launch: str, timeout_s: float) -> None:
    """Join the process group from the launcher's environment (gloo on CPU, nccl on CUDA);
    collectives wait at most ``timeout_s`` for the other ranks."""
    import torch
    import torch.distributed as dist

    global _INFO, _TIMEOUT_S
    _env_from_submitit()
    missing = [
        k for k in ("RANK", "WORLD_SIZE", "MASTER_ADDR", "MASTER_PORT") if k not in os.environ
    ]
    if missing:
        raise RuntimeError(f"{how_to_launch}; {missing} are not set")
    backend = "nccl" if torch.cuda.is_available() else "gloo"
    dist.init_process_group(backend=backend, timeout=timedelta(seconds=timeout_s))
    _TIMEOUT_S = timeout_s
    _INFO = DistInfo(
        dist.get_rank(), dist.get_world_size(), int(os.environ.get("LOCAL_RANK", 0)), backend
    )
    if backend == "nccl":
        torch.cuda.set_device(_INFO.local_rank)


def init(argv: Sequence[str]) -> list[str]:
    """Before Hydra: join the process group and agree on one run dir. Returns Hydra's arguments."""
    import torch.distributed as dist

    _join(
        "--distributed needs a launcher that sets the ranks: run it with "
        "`torchrun --nproc_per_node=N train.py --distributed ...` (or under SLURM, docs/distributed.md)",
        command_line_timeout(argv),
    )
    from rlexp.config.schema import launch_time

    stamp = [launch_time("%Y-%m-%d/%H-%M-%S.%f")] if _INFO.is_main else [None]
    with _bounded("the start (agreeing on the run dir)"):
        dist.broadcast_object_list(stamp, src=0)
    args = list(argv)
    if not any(a.startswith("hydra.run.dir=") for a in args):
        args.append(f"hydra.run.dir=outputs/{stamp[0]}")
    if (
        not _INFO.is_main
    ):  # one run dir: only rank 0 writes Hydra's files; each rank logs to its own file
        args += ["hydra.output_subdir=null", f"hydra.job.name=train_rank{_INFO.rank}"]
    log.info("distributed: rank %d of %d (%s)", _INFO.rank, _INFO.world_size, _INFO.backend)
    return args


def init_in_job() -> None:
    """Inside a launcher's job (SLURM via submitit, ``tasks_per_node=N``): join the process group.
    The Hydra job dir is already shared by the job's tasks; rank 0 alone writes into it."""
    _join(
        "--distributed with -m needs a launcher that starts several tasks per job "
        "(hydra/launcher=slurm hydra.launcher.tasks_per_node=N)",
        command_line_timeout([]),  # the job's config sets its own bound (set_timeout)
    )


def shutdown() -> None:
    import torch.distributed as dist

    if dist.is_available() and dist.is_initialized():
        dist.destroy_process_group()


# -- collectives used by the trainer --------------------------------------------------------------
def all_reduce_mean_(tensors: list[Any]) -> None:
    """Average ``tensors`` in place across ranks (one coalesced all-reduce)."""
    import torch.distributed as dist
    from torch._utils import _flatten_dense_tensors, _unflatten_dense_tensors

    flat = _flatten_dense_tensors(tensors)
    with _bounded("the gradient all-reduce"):
        dist.all_reduce(flat)
    flat /= _INFO.world_size
    for t, synced in zip(tensors, _unflatten_dense_tensors(flat, tensors), strict=True):
        t.copy_(synced)


def all_reduce_sum(tensor: Any) -> Any:
    """The sum of ``tensor`` over ranks (a new tensor)."""
    import torch.distributed as dist

    out = tensor.clone()
    with _bounded("an all-reduce"):
        dist.all_reduce(out)
    return out


def broadcast_(tensors: list[Any]) -> None:
    """Overwrite ``tensors`` with rank 0's values."""
    import torch.distributed as dist

    with _bounded("a broadcast from rank 0"):
        for t in tensors:
            dist.broadcast(t, src=0)


def all_gather_object(obj: Any) -> list[Any]:
    import torch.distributed as dist

    out: list[Any] = [None] * _INFO.world_size
    with _bounded("an all-gather"):
        dist.all_gather_object(out, obj)
    return out
