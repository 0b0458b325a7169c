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
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

log = logging.getLogger(__name__)

FLAG = "--distributed"


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


def _join(how_to_launch: str) -> None:
    """Join the process group from the launcher's environment (gloo on CPU, nccl on CUDA)."""
    import torch
    import torch.distributed as dist

    global _INFO
    _env_from_submitit()
    missing = [
        k for k in ("RANK", "WORLD_SIZE", "MASTER_ADDR", "MASTER_PORT") if k not in os.environ
    ]
    if missing:
        raise RuntimeError(f"{how_to_launch}; {missing} are not set")
    backend = "nccl" if torch.cuda.is_available() else "gloo"
    dist.init_process_group(backend=backend)
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
        "`torchrun --nproc_per_node=N train.py --distributed ...` (or under SLURM, docs/distributed.md)"
    )
    stamp = [time.strftime("%Y-%m-%d/%H-%M-%S")] if _INFO.is_main else [None]
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
        "(hydra/launcher=slurm hydra.launcher.tasks_per_node=N)"
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
    dist.all_reduce(flat)
    flat /= _INFO.world_size
    for t, synced in zip(tensors, _unflatten_dense_tensors(flat, tensors), strict=True):
        t.copy_(synced)


def all_reduce_sum(tensor: Any) -> Any:
    """The sum of ``tensor`` over ranks (a new tensor)."""
    import torch.distributed as dist

    out = tensor.clone()
    dist.all_reduce(out)
    return out


def broadcast_(tensors: list[Any]) -> None:
    """Overwrite ``tensors`` with rank 0's values."""
    import torch.distributed as dist

    for t in tensors:
        dist.broadcast(t, src=0)


def all_gather_object(obj: Any) -> list[Any]:
    import torch.distributed as dist

    out: list[Any] = [None] * _INFO.world_size
    dist.all_gather_object(out, obj)
    return out
