"""What SAC and TD3 share: the replay buffer, the update-to-data ratio, the optimisers and the
checkpointed state. ``sac.py`` and ``td3.py`` give the loss and one gradient step.

One ``update(batch)`` of the Trainer's loop (the rollout: ``algorithm.train_freq`` steps of every
env, ``frames = env.num_envs * train_freq`` transitions):

1. the rollout's transitions go into the replay buffer (``algorithms/replay.py``; both
   ``("next", "terminated")`` and ``("next", "truncated")`` are kept: the targets bootstrap
   through a truncation, never through a termination);
2. while fewer than ``learning_starts`` env steps have been seen, nothing is learnt and the next
   rollout is collected with uniform random actions (the policy's ``uniform_actions``);
3. then ``updates_per_step * frames`` gradient steps (the update-to-data ratio; a fraction carries
   over to the next update), each on ``batch_size`` transitions sampled uniformly from the
   buffer's own generator. SB3's ``train_freq=F, gradient_steps=G`` with ``n_envs=E`` is
   ``train_freq=F, updates_per_step=G / (F * E)``; CleanRL's one step per env step is
   ``updates_per_step=1``.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase
from torchrl.objectives import LossModule, SoftUpdate, ValueEstimators

from rlexp.algorithms.base import GradSync, MutableHyperparameters, NonFiniteError
from rlexp.algorithms.replay import Replay
from rlexp.algorithms.replay_keep import ChunkKeeper
from rlexp.config.schema_offpolicy import OffPolicyConfig

log = logging.getLogger(__name__)


class OffPolicy(MutableHyperparameters):
    """The off-policy learner's loop around ``_gradient_step`` (SAC, TD3)."""

    #: rollouts continue episodes (the Trainer never resets before a rollout)
    reset_each_rollout = False
    name = "off-policy"

    def __init__(
        self,
        cfg: OffPolicyConfig,
        policy: Any,
        total_iterations: int,
        nan_guard: bool = True,
        grad_sync: GradSync | None = None,
        run_dir: Path | None = None,
        seed: int = 0,
    ) -> None:
        from rlexp.config.validate import ConfigError

        if grad_sync is not None:
            from rlexp.config.offpolicy_checks import distributed_refusal

            raise ConfigError(distributed_refusal(cfg))
        if getattr(policy, "kind", None) != cfg.name:
            raise ValueError(f"algorithm={cfg.name} needs policy={cfg.name}")
        self.cfg = dataclasses.replace(cfg)  # its own copy: hooks may change its values
        self.policy = policy
        self.total_iterations = max(1, total_iterations)
        self.nan_guard = nan_guard
        self.iteration = 0
        self.frames = 0  # env steps seen (summed over envs)
        self.gradient_steps = 0
        self._owed = 0.0  # the fraction of a gradient step carried to the next update
        device = policy.action_low.device
        directory = None if run_dir is None else Path(run_dir) / "replay"
        self.replay = Replay(
            cfg.buffer_size,
            cfg.buffer_storage,
            directory,
            device,
            seed,
            n_step=cfg.n_step,
            gamma=cfg.gamma,
        )
        self._keeper = ChunkKeeper()  # which chunks the checkpoints on disk name
        qnets = [policy.make_q() for _ in range(policy.cfg.num_qvalue_nets)]
        self.loss = self._make_loss(qnets)
        self.loss.make_value_estimator(ValueEstimators.TD0, gamma=cfg.gamma)
        self.target_update = SoftUpdate(self.loss, tau=cfg.tau)
        self._soft_pairs = _soft_update_pairs(self.target_update)
        self.actor_params = [p for p in policy.actor_net.parameters() if p.requires_grad]
        self.q_params = list(self.loss.qvalue_network_params.values(True, True))
        self.actor_optimizer = self._adam(self.actor_params, cfg.lr)
        self.q_optimizer = self._adam(self.q_params, cfg.critic_lr)
        self._set_uniform()

    # -- what SAC / TD3 give ------------------------------------------------------------------------
    def _make_loss(self, qnets: list) -> LossModule:
        raise NotImplementedError

    def _gradient_step(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        """One gradient step on ``batch``; returns detached metrics (``loss/...``)."""
        raise NotImplementedError

    # -- the update ---------------------------------------------------------------------------------
    def update(self, batch: TensorDictBase) -> dict[str, float]:
        self.iteration += 1
        self.replay.extend(batch)
        self.frames += batch.numel()
        self._set_uniform()
        metrics: dict[str, float] = {"loss/buffer_size": float(len(self.replay))}
        if self.frames < self.cfg.learning_starts or len(self.replay) == 0:
            return metrics
        self._owed += self.cfg.updates_per_step * batch.numel()
        steps = int(math.floor(self._owed + 1e-9))
        self._owed -= steps
        self._set_lrs()
        sums: dict[str, torch.Tensor] = {}
        counts: dict[str, int] = {}
        for _ in range(steps):
            out = self._gradient_step(self.replay.sample(self.cfg.batch_size))
            self.gradient_steps += 1
            for k, v in out.items():
                sums[k] = sums[k] + v if k in sums else v  # (never changed in place)
                counts[k] = counts.get(k, 0) + 1
        metrics.update({k: float(v) / counts[k] for k, v in sums.items()})
        metrics["loss/gradient_steps"] = float(self.gradient_steps)
        return metrics

    def _set_uniform(self) -> None:
        self.policy.uniform_actions.fill_(self.frames < self.cfg.learning_starts)

    def _adam(self, params: list[torch.nn.Parameter], lr: float) -> torch.optim.Adam:
        fused = bool(params) and all(p.device.type in ("cpu", "cuda") for p in params)
        return torch.optim.Adam(params, lr=lr, eps=self.cfg.adam_eps, fused=fused or None)

    def _optimizers(self) -> dict[str, torch.optim.Optimizer]:
        return {"actor": self.actor_optimizer, "qvalue": self.q_optimizer}

    def _lr_of(self) -> dict[str, float]:
        """Each optimiser's learning rate now (``anneal_lr``: all scaled alike)."""
        scale = self.learning_rate() / self.cfg.lr if self.cfg.lr > 0 else 1.0
        return {"actor": self.learning_rate(), "qvalue": self.cfg.critic_lr * scale}

    def _set_lrs(self) -> None:
        lrs = self._lr_of()
        for name, opt in self._optimizers().items():
            for group in opt.param_groups:
                group["lr"] = lrs[name]

    def _step(
        self, optimizer: torch.optim.Optimizer, params: list, loss: torch.Tensor, what: str
    ) -> None:
        """zero_grad -> backward -> (NaN guard) -> (clip) -> step."""
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if self.nan_guard and not torch.isfinite(loss):
            raise NonFiniteError(f"non-finite loss ({what}) in algorithm={self.cfg.name}")
        if self.cfg.max_grad_norm > 0:
            torch.nn.utils.clip_grad_norm_(params, self.cfg.max_grad_norm)
        optimizer.step()

    def _soft_update(self) -> None:
        """``target_update.step()`` (``Q' <- Q' + (1 - eps) * (Q - Q')``, TorchRL's ``SoftUpdate``
        with ``eps = 1 - tau``: the same ``lerp_`` on the same tensors) as one foreach call, without
        its per-step TensorDict traversal (~0.1 ms of a ~9 ms step at HalfCheetah's sizes)."""
        targets, sources = self._soft_pairs
        with torch.no_grad():
            torch._foreach_lerp_(targets, sources, 1 - self.target_update.eps)

    # -- hooks --------------------------------------------------------------------------------------
    def _applied(self, name: str) -> None:
        if name == "tau":
            self.target_update.eps = 1.0 - float(self.cfg.tau)

    # -- checkpoints --------------------------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        """The loss (actor, twin Q networks, their targets, alpha), the optimisers, the counters,
        hyperparameters set by hooks, and the replay buffer's manifest (its rows are in chunk
        files under ``<run_dir>/replay``: ``save`` writes those added since the last one)."""
        return self._state(self.replay.save())

    def snapshot_state(self) -> dict[str, Any]:
        """``state_dict`` for an eval round, with no file written: the buffer's manifest is a
        ``Replay.snapshot``, made whole by ``settle_state`` if the round's state is ever saved."""
        return self._state(self.replay.snapshot())

    def settle_state(self, sd: dict[str, Any]) -> dict[str, Any]:
        """``sd`` as a checkpoint file may hold it (``Replay.settle``)."""
        return {**sd, "replay": self.replay.settle(sd["replay"])}

    def _state(self, replay: dict[str, Any]) -> dict[str, Any]:
        return {
            "loss": self.loss.state_dict(),
            "optimizers": {k: o.state_dict() for k, o in self._optimizers().items()},
            "iteration": self.iteration,
            "frames": self.frames,
            "gradient_steps": self.gradient_steps,
            "owed": self._owed,
            "hyperparameters": self.hyperparameters(),
            "replay": replay,
        }

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        self.load_training_state(sd)
        self.iteration = int(sd["iteration"])
        self.frames = int(sd["frames"])
        self.gradient_steps = int(sd["gradient_steps"])
        self._owed = float(sd["owed"])
        self._set_uniform()
        self.replay.load_state_dict(sd["replay"])

    def load_training_state(self, sd: dict[str, Any]) -> None:
        """The networks, targets, alpha, optimisers and hooks' hyperparameters of ``sd``; not the
        counters nor the replay buffer (PBT's exploit: they stay the member's own)."""
        self.loss.load_state_dict(sd["loss"])
        for k, o in self._optimizers().items():
            o.load_state_dict(sd["optimizers"][k])
        self._load_hyperparameters(sd)

    def checkpoint_written(
        self,
        ckpt_dir: Path | None = None,
        path: Path | None = None,
        state: dict[str, Any] | None = None,
    ) -> None:
        """After the trainer state ``state`` is on disk at ``path`` and old checkpoints pruned:
        delete the chunk files that no checkpoint in ``ckpt_dir`` names (``replay_keep``), so a
        resume that falls back to an older checkpoint still finds its rows. Without ``ckpt_dir``:
        only the last save's chunks are kept."""
        if ckpt_dir is None:
            self.replay.commit(None)
            return
        if path is not None and state is not None:
            self._keeper.note(path, state)
        named = self._keeper.named(ckpt_dir)
        if named is not None:
            self.replay.commit(None, named=named)


def _soft_update_pairs(update: SoftUpdate) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
    """The (target, source) tensors ``update.step()`` lerps, as two aligned lists (the loss's
    parameters are loaded in place on resume and by PBT: these stay its tensors)."""
    targets, sources = [], []
    for key, source in update._sources.items(True, True):
        key = key if isinstance(key, tuple) else (key,)
        targets.append(update._targets.get(("target_" + key[0], *key[1:])).data)
        sources.append(source.data)
    return targets, sources
