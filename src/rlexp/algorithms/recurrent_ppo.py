"""PPO for a recurrent policy (``policy.memory.type`` lstm / gru; docs/policies.md "Memory").

What differs from ``ppo.PPO`` and why:

- Values for GAE: the recurrent critic runs over each env's rollout in order, from the state stored
  at the rollout's first step, carried, and zeroed where an episode starts (``is_init``);
  V(s'_t) of a step that ended an episode (a truncated one bootstraps from it) and of the last
  step comes from the state after that step (``RecurrentActorCritic.rollout_values``). GAE itself
  is TorchRL's, as for the MLP policy.
- Minibatches are whole sequences: each env's rollout is cut into sequences of
  ``algorithm.sequence_length`` steps (the last one padded and masked when the length does not
  divide the rollout), each starting from the hidden state the collector stored before its first
  step, the state zeroed inside a sequence where an episode starts. A minibatch holds
  ``max(1, mini_batch_size // sequence_length)`` sequences, shuffled each epoch.
- The loss is ClipPPOLoss's maths (clipped surrogate, entropy bonus, l1/l2/smooth-l1 value loss,
  value clipping, per-minibatch advantage normalisation) over the valid (unpadded) steps, written
  on plain tensors, then ``guarded_step`` (distributed gradient averaging, the NaN guard,
  clipping, Adam). Not the fused step (fused_step.py), nor ``torch.compile``: both win by
  removing per-minibatch Python and dispatch around a small MLP, while a recurrent minibatch's
  forward is a data-dependent loop over the steps where some sequence resets (a different graph
  per minibatch), dominated by the LSTM / GRU kernels.
"""

from __future__ import annotations

import logging
import math

import torch
from tensordict import TensorDictBase
from torch.nn import functional as F

from rlexp.algorithms.fused_step import MINIBATCH_KEYS
from rlexp.algorithms.ppo import PPO, STAT_KEYS, adaptive_learning_rate
from rlexp.policies.heads import MultiCategorical, categorical_kl, gaussian_kl

log = logging.getLogger(__name__)

_HALF_LOG_2PI = math.log(math.sqrt(2 * math.pi))
_DISTANCE = {"l1": F.l1_loss, "l2": F.mse_loss, "smooth_l1": F.smooth_l1_loss}
#: The rollout's entries a sequence minibatch carries (besides the dist keys for desired_kl).
SEQUENCE_KEYS = (*MINIBATCH_KEYS, "is_init")


def cut_sequences(
    batch: TensorDictBase, length: int, keys: tuple[str, ...] = SEQUENCE_KEYS
) -> tuple[TensorDictBase, dict[str, torch.Tensor]]:
    """A rollout [E, T] -> (sequences [S, length] of ``keys`` plus ``valid`` (bool: not padding),
    the recurrent state before each sequence's first step, [S, layers, H] per name).

    Env e's rollout gives sequences e * n .. e * n + n - 1 (n = ceil(T / length)), in time order;
    a last sequence shorter than ``length`` is padded with zeros (``valid`` False there)."""
    envs, steps = batch.shape
    n = -(-steps // length)
    pad = n * length - steps
    data = batch.select(*keys)
    data.set("valid", torch.ones(envs, steps, dtype=torch.bool, device=batch.device))
    if pad:
        data = data.apply(
            lambda x: torch.cat([x, x.new_zeros((envs, pad, *x.shape[2:]))], 1),
            batch_size=[envs, n * length],
        )
    sequences = data.reshape(envs * n, length)
    state = batch.get("recurrent_state")
    starts = {
        name: state.get(name)[:, ::length].reshape(envs * n, *state.get(name).shape[2:])
        for name in state.keys()
    }
    return sequences, starts


def log_prob_entropy(
    params: tuple[torch.Tensor, ...], action: torch.Tensor, nvec: tuple[int, ...] | None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Log-probability of ``action`` and entropy under the head's distribution: TorchRL's
    IndependentNormal (torch's Normal summed over the action dims) or rlexp's MultiCategorical."""
    if nvec is None:
        loc, scale = params
        log_prob = -((action - loc) ** 2) / (2 * scale**2) - scale.log() - _HALF_LOG_2PI
        entropy = 0.5 + 0.5 * math.log(2 * math.pi) + scale.log()
        return log_prob.sum(-1), entropy.sum(-1)
    dist = MultiCategorical(params[0], nvec)
    return dist.log_prob(action), dist.entropy()


def ppo_loss(
    log_prob: torch.Tensor,
    entropy: torch.Tensor,
    value: torch.Tensor,
    old_log_prob: torch.Tensor,
    advantage: torch.Tensor,
    value_target: torch.Tensor,
    old_value: torch.Tensor,
    cfg,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """ClipPPOLoss's terms as ppo.py configures it, on valid steps [N] (values [N, 1]):
    (total loss, the statistics by ``STAT_KEYS`` name but ``grad_norm``)."""
    if cfg.normalize_advantage and advantage.numel() > 1:
        advantage = (advantage - advantage.mean()) / advantage.std().clamp_min(
            torch.finfo(torch.float).resolution
        )
    log_weight = (log_prob - old_log_prob).unsqueeze(-1)
    eps = cfg.clip_epsilon
    log_weight_clip = log_weight.clamp(math.log1p(-eps), math.log1p(eps))
    gain = torch.minimum(log_weight.exp() * advantage, log_weight_clip.exp() * advantage)
    loss_objective = (-gain).mean()
    loss_entropy = (-cfg.entropy_coeff * entropy).mean()
    distance = _DISTANCE[cfg.loss_critic_type]
    loss_value = distance(value_target, value, reduction="none")
    if cfg.clip_value:  # the more pessimistic of the clipped and unclipped value losses
        clipped = old_value + (value - old_value).clamp(-cfg.clip_value, cfg.clip_value)
        loss_value = torch.maximum(loss_value, distance(value_target, clipped, reduction="none"))
    loss_critic = (cfg.critic_coeff * loss_value).mean()
    total = loss_objective + loss_critic
    if cfg.entropy_coeff != 0.0:
        total = total + loss_entropy
    stats = {
        "loss_objective": loss_objective,
        "loss_critic": loss_critic,
        "loss_entropy": loss_entropy,
        "entropy": entropy.mean(),
        "clip_fraction": (log_weight_clip != log_weight).float().mean(),
        "kl_approx": (old_log_prob - log_prob).mean(),
    }
    return total, stats


class RecurrentPPO(PPO):
    """PPO over sequences for a ``RecurrentActorCritic``; ``update`` is PPO's (reward scaling, GAE,
    the learning-rate schedule, metrics), with the recurrent values and the sequence epochs."""

    rollout_values = False  #: the recurrent critic's values come from its own pass (not collection)

    use_fused_step = False

    def __init__(self, cfg, policy, *args, **kwargs) -> None:
        if not getattr(policy, "recurrent", False):
            raise ValueError("RecurrentPPO trains a recurrent policy (policy.memory.type)")
        super().__init__(cfg, policy, *args, **kwargs)
        self.sequence_length = int(cfg.sequence_length)
        self._rollout: TensorDictBase | None = None  # the rollout of the update in progress

    @torch.no_grad()
    def compute_advantages(self, batch: TensorDictBase) -> TensorDictBase:
        """``state_value``, ``("next", "state_value")`` from the recurrent critic over the rollout
        in order, then TorchRL's GAE (``advantage``, ``value_target``)."""
        batch = as_env_time(batch)
        state = batch.get("recurrent_state")
        start = {name: state.get(name)[:, 0] for name in state.keys()}
        is_init = batch.get("is_init").reshape(batch.shape)
        value, next_value = self.policy.rollout_values(
            batch.get("observation"), batch.get(("next", "observation")), start, is_init
        )
        batch.set("state_value", value)
        batch.set(("next", "state_value"), next_value)
        self._rollout = batch
        return self.gae(batch)

    def _decide_compile(self, updates: int, mb: int) -> None:
        self._compile_decided = True
        log.info(
            "[ppo] recurrent policy: eager sequence loss, %d steps per sequence (no fused step "
            "or torch.compile: docs/policies.md)",
            self.sequence_length,
        )

    def _epochs(
        self, flat: TensorDictBase, mb: int, adaptive: bool
    ) -> tuple[list[torch.Tensor], list[str]]:
        """``num_epochs`` passes of shuffled minibatches of whole sequences (``flat``, the
        flattened rollout, only sizes them: ``mb`` steps make ``max(1, mb // L)`` sequences)."""
        batch, self._rollout = self._rollout, None
        if batch is None:
            raise RuntimeError("RecurrentPPO._epochs runs after compute_advantages")
        keys = SEQUENCE_KEYS + (tuple(self.policy.actor_net.dist_keys) if adaptive else ())
        sequences, starts = cut_sequences(batch, self.sequence_length, keys)
        count = sequences.shape[0]
        per_batch = min(count, max(1, mb // self.sequence_length))
        rows: list[torch.Tensor] = []
        for epoch in range(self.cfg.num_epochs):
            order = torch.randperm(count, generator=self._shuffle)
            for start in range(0, count - per_batch + 1, per_batch):
                index = order[start : start + per_batch].to(sequences.device)
                minibatch = sequences[index]
                state = {name: s[index] for name, s in starts.items()}
                if adaptive:
                    self._adapt_sequences(minibatch, state)
                total, stats = self.sequence_loss(minibatch, state)
                terms = {k: stats[k] for k in ("loss_objective", "loss_critic", "loss_entropy")}
                if self.cfg.entropy_coeff == 0.0:
                    del terms["loss_entropy"]
                grad_norm = self.backward_and_step(
                    total, terms, f"PPO update (epoch {epoch}, minibatch {start // per_batch})"
                )
                row = [grad_norm if k == "grad_norm" else stats[k] for k in STAT_KEYS]
                rows.append(torch.stack([r.detach().reshape(()) for r in row]))
        return rows, list(STAT_KEYS)

    def sequence_loss(
        self, minibatch: TensorDictBase, state: dict[str, torch.Tensor]
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """The loss of a minibatch of sequences [M, L] from their starting ``state``."""
        is_init = minibatch.get("is_init").reshape(minibatch.shape)
        params, value = self.policy.sequence_outputs(minibatch.get("observation"), state, is_init)
        valid = minibatch.get("valid")
        params = tuple(p[valid] for p in params)
        log_prob, entropy = log_prob_entropy(
            params, minibatch.get("action")[valid], self.policy.nvec
        )
        return ppo_loss(
            log_prob,
            entropy,
            value[valid],
            minibatch.get("action_log_prob")[valid].reshape(-1),
            minibatch.get("advantage")[valid],
            minibatch.get("value_target")[valid],
            minibatch.get("state_value")[valid],
            self.cfg,
        )

    @torch.no_grad()
    def _adapt_sequences(self, minibatch: TensorDictBase, state: dict[str, torch.Tensor]) -> None:
        """``algorithm.desired_kl`` on a minibatch of sequences (PPO's ``_adapt_learning_rate``)."""
        is_init = minibatch.get("is_init").reshape(minibatch.shape)
        params, _ = self.policy.sequence_outputs(minibatch.get("observation"), state, is_init)
        valid = minibatch.get("valid")
        old = [minibatch.get(k)[valid] for k in self.policy.actor_net.dist_keys]
        if self.policy.nvec is None:
            kl = gaussian_kl(old[0], old[1], params[0][valid], params[1][valid])
        else:
            kl = categorical_kl(old[0], params[0][valid], self.policy.nvec)
        if self.grad_sync is not None:
            kl = kl.reshape(1).clone()
            self.grad_sync([kl])
        self.cfg.lr = adaptive_learning_rate(self.cfg.lr, float(kl), self.cfg.desired_kl)
        self._set_lr(self.cfg.lr)


def as_env_time(batch: TensorDictBase) -> TensorDictBase:
    """A rollout as [E, T] (time last; several env batch dims flattened into one)."""
    if batch.batch_dims == 2:
        return batch
    if batch.batch_dims == 1:
        return batch.unsqueeze(0)
    return batch.reshape(-1, batch.shape[-1])
