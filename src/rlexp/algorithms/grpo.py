"""GRPO for continuous control: no critic; each env's discounted Monte-Carlo return is compared with
the other members of its group (blocks of ``group_size`` consecutive envs, reset together before each
rollout), PPO's clipped surrogate on that advantage, and a k3 KL penalty to a frozen copy of the
initial policy.

The rule, as our users' system defines it (``group_advantages`` is the pure function):

- returns ``G_t = r_t + gamma * G_{t+1} * (1 - done_t)`` backwards, ``G_T = 0`` (no bootstrap at the
  rollout's end; ``done`` = terminated or truncated);
- with ``truncate_at_first_done``, env i's steps count (mask 1) up to and including its first done
  in the rollout, not after (the steps of its later episodes have no group to compare with);
- ``A[i, t] = (G[i, t] - mean) / (std + epsilon)``, mean and population std over the members of env
  i's group still alive (mask 1) at step t; 0 where the mask is 0;
- the loss is a mask-weighted mean over each minibatch (of all the rollout's steps, shuffled):
  ``-min(r A, clip(r, 1 - eps, 1 + eps) A) - entropy_coeff H + kl_coeff k3(ref, logp)``, with
  ``r = exp(logp - old_logp)`` and ``k3 = exp(ref - logp) - (ref - logp) - 1``.

TorchRL 0.14.1's ``torchrl.objectives.llm.GRPOLoss`` does not fit: it takes an ``LLMWrapperBase``
actor, reads token tensors (``("tokens", "full")``, assistant / attention masks) and aggregates over
token sequences; and its ``MCAdvantage`` normalises per-step rewards or whole-trajectory returns of
completed trajectories written to a replay buffer, not per-step discounted returns over the members
still alive. So the advantage and loss are written here in plain torch; the distributions are
TorchRL's (``policy.actor.get_dist``: the ``IndependentNormal`` PPO's loss uses) and the KL term is
TorchRL's ``k3_kl_token_estimate``. The optimiser step (gradient sync, NaN guard, clipping, fused
Adam) is PPO's, from ``base.py``. ``tests/test_grpo_math.py`` checks it against a plain-torch GRPO.

The minibatch step is ``fused_grpo.py`` (this loss's maths on plain tensors, backward, clipping and
Adam on PPO's fused machinery) wherever it covers the run, eager unless ``algorithm.compile`` says
(auto: PPO's saving rule; true: refused at build time where the fused step cannot cover the run);
the TensorDict path below otherwise (distributed gradient averaging, a non-fused Adam), chosen once
at the first update and logged. ``tests/test_fast_update_grpo.py`` checks the two equal.
"""

from __future__ import annotations

import copy
import dataclasses
import logging
from typing import Any

import torch
from tensordict import TensorDictBase
from torchrl.objectives.llm import k3_kl_token_estimate

from rlexp.algorithms.base import (
    AUTO_COMPILE_MIN_SAVING_S,
    GradSync,
    MutableHyperparameters,
    compile_saving_s,
    make_optimizer,
    parse_compile,
)
from rlexp.algorithms.fused_grpo import LOSS_KEYS, STAT_KEYS, FusedGRPOStep
from rlexp.algorithms.fused_step import unsupported as fused_unsupported
from rlexp.config.schema import GRPOConfig
from rlexp.config.validate import ConfigError
from rlexp.policies.actor_critic import Policy
from rlexp.policies.encoders import channels_last_images

log = logging.getLogger(__name__)

__all__ = ["GRPO", "LOSS_KEYS", "STAT_KEYS", "group_advantages"]


def group_advantages(
    reward: torch.Tensor,
    done: torch.Tensor,
    gamma: float,
    group_size: int,
    epsilon: float,
    truncate_at_first_done: bool,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Discounted returns, the alive mask and group-relative advantages of a rollout [N, T]
    (``done`` bool); groups are blocks of ``group_size`` consecutive envs. Returns float tensors
    ``(returns, mask, advantages)``, each [N, T]."""
    if reward.dim() != 2 or done.shape != reward.shape:
        raise ValueError(
            f"group_advantages takes reward and done of shape [num_envs, T]; got "
            f"{tuple(reward.shape)} and {tuple(done.shape)}"
        )
    n, steps = reward.shape
    if group_size < 1 or n % group_size != 0:
        raise ValueError(
            f"algorithm.group_size={group_size} does not divide env.num_envs={n}: groups are blocks "
            "of group_size consecutive envs; choose a group_size that divides env.num_envs"
        )
    done = done.bool()
    not_done = (~done).to(reward.dtype)
    returns = torch.empty_like(reward)
    running = reward.new_zeros(n)  # G_T = 0: no bootstrap at the rollout's end
    for t in range(steps - 1, -1, -1):
        running = reward[:, t] + gamma * running * not_done[:, t]
        returns[:, t] = running
    if truncate_at_first_done:
        dones_before = done.long().cumsum(1) - done.long()  # dones at steps < t
        alive = dones_before == 0
    else:
        alive = torch.ones_like(done)
    # [groups, group_size, T]; torch.where, not a product: a masked step's value never leaks in
    g_alive = alive.reshape(n // group_size, group_size, steps)
    g_ret = torch.where(g_alive, returns.reshape(g_alive.shape), 0.0)
    count = g_alive.sum(1, keepdim=True).clamp(min=1).to(reward.dtype)
    mean = g_ret.sum(1, keepdim=True) / count
    dev = torch.where(g_alive, g_ret - mean, 0.0)
    std = (dev.pow(2).sum(1, keepdim=True) / count).sqrt()  # population std of the alive members
    advantages = (dev / (std + epsilon)).reshape(n, steps)
    return returns, alive.to(reward.dtype), advantages


class GRPO(MutableHyperparameters):
    """One GRPO learner: ``update(batch)`` computes group advantages, then the clipped-surrogate
    epochs with the KL penalty to the initial policy on a rollout [num_envs, T]."""

    #: Whether the first update may choose the fused minibatch step (fused_grpo.py) over today's.
    use_fused_step: bool = True

    def __init__(
        self,
        cfg: GRPOConfig,
        policy: Policy,
        total_iterations: int,
        nan_guard: bool = True,
        grad_sync: GradSync | None = None,
    ) -> None:
        if cfg.name != "grpo":
            raise ValueError(f"algorithm.name={cfg.name!r}; GRPO is 'grpo'")
        if cfg.group_size < 1:
            raise ValueError(f"algorithm.group_size={cfg.group_size}; must be >= 1")
        self.cfg = dataclasses.replace(cfg)  # its own copy: hooks may change its values
        self.policy = policy
        self.total_iterations = max(1, total_iterations)
        self.nan_guard = nan_guard
        self.grad_sync = grad_sync  # distributed: averages the gradients over ranks
        self.reset_each_rollout = cfg.reset_every_rollout  # a group's members start together
        # The initial policy as a function (parameters and normaliser statistics), frozen.
        self.reference: torch.nn.Module | None = None
        if cfg.kl_coeff > 0:
            self.reference = copy.deepcopy(policy.actor)
            self.reference.requires_grad_(False)
        # All trainable parameters, as PPO: the checkpoint's optimiser state has one per parameter
        # (a critic, if the policy has one, gets no gradient and stays as it is).
        named = [(n, p) for n, p in policy.named_parameters() if p.requires_grad]
        self.param_names = [n for n, _ in named]  # for NaN-guard messages
        self.params = [p for _, p in named]
        self.optimizer = make_optimizer(self.params, cfg)
        self.compile = parse_compile(cfg.compile)
        if self.compile == "true":  # only the fused step compiles: fail at build time, naming why
            self._check_compile_true()
        self.compiled = False  # whether the minibatch step runs through torch.compile
        # The fused minibatch step, chosen at the first update where it covers the run; None: the
        # TensorDict path (GRPO.loss, then guarded_step).
        self.fused: FusedGRPOStep | None = None
        self._step_decided = False
        self._shuffle = torch.Generator()  # minibatch order (CPU: randperm indexes a CPU batch)
        self.iteration = 0

    @torch.no_grad()
    def prepare(self, batch: TensorDictBase) -> tuple[TensorDictBase, torch.Tensor]:
        """The rollout flattened to [N*T] with ``advantage``, ``mask`` and (with a reference)
        ``ref_log_prob`` of each action; and the mask [N, T]."""
        if batch.batch_dims != 2:
            raise ValueError(
                f"GRPO takes a rollout [num_envs, T]; got batch size {tuple(batch.batch_size)}"
            )
        cfg = self.cfg
        _, mask, advantages = group_advantages(
            batch.get(("next", "reward")).squeeze(-1),
            batch.get(("next", "done")).squeeze(-1),  # terminated | truncated
            cfg.gamma,
            cfg.group_size,
            cfg.epsilon,
            cfg.truncate_at_first_done,
        )
        flat = batch.select("observation", "action", "action_log_prob").reshape(-1)
        flat.set("action_log_prob", flat.get("action_log_prob").reshape(flat.shape))
        flat.set("advantage", advantages.reshape(flat.shape))
        flat.set("mask", mask.reshape(flat.shape))
        if self.reference is not None:  # frozen: once per rollout, not per minibatch
            dist = self.reference.get_dist(flat.select("observation"))
            flat.set("ref_log_prob", dist.log_prob(flat.get("action")))
        return flat, mask

    def loss(self, minibatch: TensorDictBase) -> dict[str, torch.Tensor]:
        """The loss terms (LOSS_KEYS present) and statistics of one minibatch, mask-weighted."""
        cfg = self.cfg
        dist = self.policy.actor.get_dist(minibatch.select("observation"))
        log_prob = dist.log_prob(minibatch.get("action"))
        mask = minibatch.get("mask")
        denom = mask.sum().clamp(min=1)  # an all-masked minibatch: loss 0

        def mean(x: torch.Tensor) -> torch.Tensor:
            return (mask * x).sum() / denom

        log_ratio = log_prob - minibatch.get("action_log_prob")
        ratio = log_ratio.exp()
        advantage = minibatch.get("advantage")
        low, high = 1.0 - cfg.clip_epsilon, 1.0 + cfg.clip_epsilon
        surrogate = torch.min(ratio * advantage, ratio.clamp(low, high) * advantage)
        entropy = mean(dist.entropy())  # logged always (the policy's real entropy)
        out = {"loss_objective": -mean(surrogate), "entropy": entropy.detach()}
        if cfg.entropy_coeff != 0.0:
            out["loss_entropy"] = -cfg.entropy_coeff * entropy
        if self.reference is not None:
            kl_ref = mean(k3_kl_token_estimate(minibatch.get("ref_log_prob"), log_prob))
            out["loss_kl"] = cfg.kl_coeff * kl_ref
            out["kl_ref"] = kl_ref.detach()
        with torch.no_grad():  # PPO's diagnostics (TorchRL's kl_approx, clip_fraction), masked
            out["approx_kl"] = mean(-log_ratio)
            out["clip_fraction"] = mean(((ratio < low) | (ratio > high)).to(mask.dtype))
        return out

    def update(self, batch: TensorDictBase) -> dict[str, float]:
        """Group advantages over the rollout, then ``num_epochs`` passes of shuffled minibatches."""
        lr = self.learning_rate()
        for group in self.optimizer.param_groups:
            group["lr"] = lr
        flat, mask = self.prepare(batch)
        flat = channels_last_images(flat)  # the encoders' layout once, not per minibatch
        n = flat.shape[0]
        mb = min(self.cfg.mini_batch_size, n)
        if not self._step_decided:
            self._decide_step(
                updates=self.total_iterations * self.cfg.num_epochs * (n // mb), mb=mb
            )
        # Minibatch order from a generator of its own, seeded from the global RNG once per update
        # (as PPO): nothing the loss draws can change it.
        self._shuffle.manual_seed(int(torch.randint(2**62, (1,)).item()))
        if self.fused is not None:
            # The fused step's rows hold every STAT_KEYS: keep the loss's own, as the TensorDict
            # path's rows do (the same columns, so the same means to the bit).
            keys = [k for k in STAT_KEYS if self._in_loss(k)]
            columns = [STAT_KEYS.index(k) for k in keys]
            stats = torch.stack(self.fused.epochs(flat, self.cfg, mb, self._shuffle))[:, columns]
        else:
            rows, keys = self._epochs(flat, mb)
            stats = torch.stack(rows)
        self.iteration += 1
        # Only what was computed is logged: a term the loss does not have is absent, never 0.
        means = dict(zip(keys, stats.mean(0).tolist(), strict=True))
        metrics = {
            "loss/policy": means["loss_objective"],
            "loss/entropy": means["entropy"],  # the policy's mean entropy
            "loss/grad_norm": means["grad_norm"],
            "loss/clip_fraction": means["clip_fraction"],
            "loss/approx_kl": means["approx_kl"],
            "loss/learning_rate": lr,
            **self.policy.metrics(),  # loss/log_std for a Gaussian policy
            "grpo/mask_fraction": float(mask.mean()),
        }
        if "loss_entropy" in means:  # the entropy term of the loss: -entropy_coeff * entropy
            metrics["loss/entropy_term"] = means["loss_entropy"]
        if self.reference is not None:
            metrics["loss/kl_ref"] = means["kl_ref"]
        return metrics

    def _in_loss(self, key: str) -> bool:
        """Whether ``loss`` computes the statistic ``key`` with today's settings."""
        if key == "loss_entropy":
            return self.cfg.entropy_coeff != 0.0
        return key not in ("loss_kl", "kl_ref") or self.reference is not None

    def _epochs(self, flat: TensorDictBase, mb: int) -> tuple[list[torch.Tensor], list[str]]:
        """The TensorDict path: ``loss`` on TensorDict slices, then ``guarded_step``; per minibatch
        a row of the statistics named by the returned keys."""
        n = flat.shape[0]
        rows: list[torch.Tensor] = []  # per minibatch: the STAT_KEYS present, one tensor
        keys: list[str] = []
        for epoch in range(self.cfg.num_epochs):
            shuffled = flat[torch.randperm(n, generator=self._shuffle)]
            for start in range(0, n - mb + 1, mb):
                out = self.loss(shuffled[start : start + mb])
                terms = {k: out[k] for k in LOSS_KEYS if k in out}
                total = terms["loss_objective"]
                for key in LOSS_KEYS[1:]:
                    if key in terms:
                        total = total + terms[key]
                out["grad_norm"] = self.backward_and_step(
                    total, terms, f"GRPO update (epoch {epoch}, minibatch {start // mb})"
                )
                keys = keys or [k for k in STAT_KEYS if k in out]
                rows.append(torch.stack([out[k].detach() for k in keys]))
        return rows, keys

    def _check_compile_true(self) -> None:
        """``algorithm.compile=true``: a ``ConfigError`` where the fused step cannot cover the run
        or torch.compile cannot run (GRPO's TensorDict path has no compiled form)."""
        from rlexp.algorithms.ppo import compile_unavailable

        problem = fused_unsupported(self) or compile_unavailable(
            self.params[0].device if self.params else None
        )
        if problem is not None:
            raise ConfigError(
                f"algorithm.compile=true, but GRPO compiles only its fused minibatch step, which "
                f"cannot run here: {problem}; use algorithm.compile=auto or false"
            )

    def _decide_step(self, updates: int, mb: int) -> None:
        """The minibatch step for this run (once, at the first update): fused, compiled where
        ``algorithm.compile`` says (auto: PPO's saving rule), or the TensorDict path."""
        self._step_decided = True
        problem = fused_unsupported(self) if self.use_fused_step else "switched off"
        if problem is not None:
            log.info("[grpo] minibatch step: GRPO.loss on TensorDicts (not fused: %s)", problem)
            return
        compiled = self.compile == "true"
        if self.compile == "auto":
            saving = compile_saving_s(updates, mb, fused=True)
            compiled = saving >= AUTO_COMPILE_MIN_SAVING_S
            log.info(
                "[grpo] algorithm.compile=auto: %s (%d minibatch updates, estimated saving %.0f s, "
                "threshold %.0f s)",
                "torch.compile of the fused step" if compiled else "eager",
                updates,
                saving,
                AUTO_COMPILE_MIN_SAVING_S,
            )
        if compiled and self.compile == "auto":
            from rlexp.algorithms.ppo import compile_unavailable

            problem = compile_unavailable(self.params[0].device if self.params else None)
            if problem is not None:
                log.warning("[grpo] algorithm.compile=auto: eager step (%s)", problem)
                compiled = False
        self.fused = FusedGRPOStep(self, compiled=compiled)
        self.compiled = compiled
        log.info("[grpo] minibatch step: fused (%s)", "compiled" if compiled else "eager")

    def state_dict(self) -> dict[str, Any]:
        """Optimiser, iteration and, with ``kl_coeff > 0``, the frozen reference policy."""
        sd: dict[str, Any] = {
            "optimizer": self.optimizer.state_dict(),
            "iteration": self.iteration,
            "hyperparameters": self.hyperparameters(),
        }
        if self.reference is not None:
            sd["reference"] = self.reference.state_dict()
        return sd

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        """Restore ``state_dict``'s output; the reference too, so a resumed run pulls towards the
        same initial policy."""
        if self.reference is not None:
            if "reference" not in sd:
                raise ValueError(
                    "the checkpoint's algorithm state has no GRPO reference policy, which "
                    "algorithm.kl_coeff > 0 needs: it was saved with kl_coeff=0 or by another "
                    "algorithm; resume with algorithm.kl_coeff=0 or start a new run"
                )
            self.reference.load_state_dict(sd["reference"])
        self.optimizer.load_state_dict(sd["optimizer"])
        self.iteration = int(sd["iteration"])
        self._load_hyperparameters(sd)

    def mutable(self) -> tuple[str, ...]:
        """``kl_coeff`` only when there is a reference to pull towards (kl_coeff > 0 at the start)."""
        names = super().mutable()
        return tuple(n for n in names if n != "kl_coeff" or self.reference is not None)
