"""Small helpers of the training loop: one torch thread while envs step, crossing a multiple of a
step count, the base env under transforms, the collector's sampling policy, a digest of a module's
parameters (ranks in sync), the NaN guard's check of a rollout, and the training envs put back from
a checkpoint."""

from __future__ import annotations

import logging
from collections.abc import Iterator
from contextlib import AbstractContextManager, contextmanager, nullcontext
from typing import Any

import torch
from tensordict import TensorDictBase
from torchrl.envs import EnvBase

from rlexp.algorithms.base import NonFiniteError
from rlexp.common.observations import all_finite
from rlexp.runtime.distributed import DistInfo, all_gather_object, all_reduce_sum
from rlexp.runtime.user_code import describe, user_code_exits

log = logging.getLogger(__name__)


def base_env(env: EnvBase | None) -> EnvBase | None:
    while env is not None and hasattr(env, "base_env"):
        env = env.base_env
    return env


def collection_policy(policy, algorithm, overlap: bool):
    """The training collector's sampling policy: with the critic's values (``state_value``) where
    the algorithm's GAE takes them from the rollout (PPO) and the policy's collection computes them
    cheaply (``Policy.values_in_collection``: image policies sharing the encoder), unless
    ``algorithm.overlap`` collects the next rollout during an update (its values would be the
    critic's before that update: GAE computes them itself there)."""
    values = getattr(algorithm, "rollout_values", False) and not overlap
    return policy.sampling_policy(values=values)


def parameter_digest(module: torch.nn.Module) -> str:
    """sha256 of every parameter's bytes, in ``state_dict`` order."""
    import hashlib

    h = hashlib.sha256()
    for _, p in sorted(module.named_parameters()):
        h.update(p.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()[:16]


@contextmanager
def one_torch_thread() -> Iterator[None]:
    """Env stepping runs the policy on a few observations at a time: more torch threads only slow it
    down, and the cores belong to the physics (the native envs' thread pool). ``trainer.torch_threads``
    is for the update; collection and evaluation run with one (PushCube x64, torch_threads=2: 7,960
    -> 9,581 env-steps/s, docs/performance.md)."""
    threads = torch.get_num_threads()
    if threads == 1:
        yield
        return
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


def collection_threads(policy: torch.nn.Module) -> AbstractContextManager[None]:
    """The torch threads a rollout's policy steps run with: one (``one_torch_thread``), except for
    a policy whose actor reads images (``Policy.acts_on_images``): its step is a CNN forward over
    every env's frames, compute-bound work that ``trainer.torch_threads`` speeds up as it does the
    update (Pong, a Nature CNN's forward on 8 frames: 1.8 ms at one thread, 1.2 ms at two;
    docs/performance.md "CNN PPO"). Evaluation keeps one thread
    everywhere (in-process rounds, the eval worker, ``rlexp eval``: the same kernels, the same
    numbers)."""
    if getattr(policy, "acts_on_images", False):
        return nullcontext()
    return one_torch_thread()


def crossed(before: int, after: int, every: int) -> bool:
    """True when the step count went past a multiple of ``every`` (not only on exact equality)."""
    return every > 0 and after // every > before // every


def check_rollout_finite(
    batch: TensorDictBase, dist: DistInfo, device: torch.device, step: int
) -> None:
    """``NonFiniteError`` naming the key (and, distributed, the ranks) when a rollout's next
    observations or rewards hold a NaN or Inf. Distributed, every rank must call it: the flags are
    summed over ranks so that all raise together (one alone would block the others)."""
    keys = (("next", "observation"), ("next", "reward"))
    bad = [(dist.rank, k) for k in keys if not all_finite(batch[k])]  # (a TensorDict's floats)
    if dist.enabled:
        flags = torch.zeros(dist.world_size, len(keys), device=device)
        for rank, k in bad:
            flags[rank, keys.index(k)] = 1.0
        bad = [(r, keys[i]) for r, i in all_reduce_sum(flags).nonzero().tolist()]
    if not bad:
        return
    key = bad[0][1]
    where = ""
    if dist.enabled:
        ranks = [str(r) for r, k in bad if k == key]
        where = f" on rank{'s' if len(ranks) > 1 else ''} {', '.join(ranks)}"
    raise NonFiniteError(f"non-finite {'/'.join(key)} from the env{where} at step {step}")


def envs_state(env: EnvBase | None) -> dict:
    """The checkpoint's ``envs`` (the training envs mid-episode; eval rounds start from fresh
    resets) and ``observation_layout`` (how a Gymnasium env's observations were flattened)."""
    base = base_env(env)
    envs = {"train": base.env_state()} if hasattr(base, "env_state") else {}
    layout = getattr(base, "obs_layout", None)
    return {"envs": envs, "observation_layout": None if layout is None else layout.record()}


class EnvRestoreError(RuntimeError):
    """The env's ``set_state`` raised on resume (the message is the one line to show)."""


def restore_envs(env: EnvBase | None, sd: dict, is_main: bool) -> str | None:
    """Put the training envs back as checkpoint ``sd`` holds them (rank 0's; other ranks continue
    with fresh episodes): what happened (restored, or new episodes, and why), or None. ValueError
    when the checkpoint's observations were flattened otherwise than this env's."""
    from rlexp.envs.layout_check import check_layout

    check_layout(sd.get("observation_layout"), env, f"checkpoint {sd.get('path')!r}")
    base = base_env(env)
    if not (is_main and "train" in sd.get("envs", {}) and hasattr(base, "load_env_state")):
        return None
    try:
        with user_code_exits("set_state"):
            base.load_env_state(sd["envs"]["train"])
    except Exception as exc:  # the env's own set_state (or its restore) failed: one line, exit 2
        name = getattr(base, "env_id", type(base).__name__)
        part = (
            "its set_state()"
            if getattr(base, "state_kind", "state") == "state"
            else (f"restoring its {getattr(base, 'state_kind', '')} state")
        )
        raise EnvRestoreError(
            f"env.name={name!r}: {part} raised while resuming from checkpoint "
            f"{sd.get('path')}: {describe(exc)}; fix the env's set_state(), or start the run in a "
            "new hydra.run.dir"
        ) from None
    mode = getattr(base, "resume_mode", None) or "restored"
    log.info("[resume] training envs: %s", mode)
    return mode


def restart_returns(algorithm: object) -> None:
    """The envs start new episodes: a reward normaliser's running returns start again from 0."""
    normalizer = getattr(algorithm, "reward_normalizer", None)
    if normalizer is not None:
        normalizer.returns = None  # zeros at the next rollout


def stop_requested_elsewhere(policy: torch.nn.Module, stop_reason: str | None) -> bool:
    """Distributed: a signal may reach one rank only; True where another rank was asked to stop."""
    device = next(policy.parameters()).device  # nccl reduces GPU tensors only
    requested = torch.tensor([float(stop_reason is not None)], device=device)
    return all_reduce_sum(requested).item() > 0 and stop_reason is None


def check_ranks_in_sync(policy: torch.nn.Module, world_size: int) -> None:
    """Distributed: every rank must hold the same parameters (gradients were averaged)."""
    digest = parameter_digest(policy)
    digests = all_gather_object(digest)
    if len(set(digests)) != 1:
        raise RuntimeError(f"ranks diverged: parameter digests {digests}")
    log.info("[dist] parameters identical on all %d ranks (sha256 %s)", world_size, digest)


def carried_state(collector: Any, resumed: dict[str, Any] | None) -> dict[str, Any] | None:
    """The checkpoint's ``recurrent_carry``: the collector's (a recurrent policy's hidden state and
    episode starts between steps), or what a resumed run has not handed to its collector yet."""
    carried = getattr(collector, "carried_state", None)  # (overlap: the child's, after a rollout)
    return resumed if carried is None else carried()
