"""SAC (Haarnoja et al. 2018, the version with automatic entropy tuning) on TorchRL's ``SACLoss``:
twin Q networks and their soft-updated targets, the tanh-squashed Gaussian actor, and
``alpha = exp(log_alpha)`` tuned so that the policy's entropy approaches ``target_entropy``
(``auto``: ``-act_dim``). docs/sac.md.

One gradient step: the critics' loss ``sum_i (Q_i(s, a) - y)^2`` with
``y = r + gamma * (1 - terminated) * (min_i Q'_i(s', a') - alpha * log pi(a'|s'))``,
``a' ~ pi(.|s')``; the actor's ``alpha * log pi(a~|s) - min_i Q_i(s, a~)`` (reparameterised
``a~``, the Q networks detached); alpha's ``-log_alpha * (log pi(a~|s) + target_entropy)``; three
Adam steps, then the targets ``Q' <- tau * Q + (1 - tau) * Q'``. A truncated transition
bootstraps (``terminated`` is 0), a terminated one does not.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torchrl.objectives import LossModule, SACLoss

from rlexp.algorithms.base import NonFiniteError, parse_compile
from rlexp.algorithms.fused_sac import FusedSAC
from rlexp.algorithms.offpolicy import OffPolicy


class SAC(OffPolicy):
    """``algorithm=sac``."""

    def __init__(self, cfg, policy, total_iterations, nan_guard=True, grad_sync=None,
                 run_dir=None, seed=0) -> None:  # fmt: skip
        if cfg.name != "sac":
            raise ValueError(f"algorithm.name={cfg.name!r}; available: ['sac']")
        super().__init__(cfg, policy, total_iterations, nan_guard, grad_sync, run_dir, seed)
        if self.cfg.target_entropy == "auto":  # resolved once: hooks and logs see the number
            self.cfg.target_entropy = -float(policy.act_dim)
        self.loss.target_entropy.fill_(float(self.cfg.target_entropy))
        self.alpha_params = [self.loss.log_alpha] if not cfg.fixed_alpha else []
        self.alpha_optimizer = (
            self._adam(self.alpha_params, cfg.alpha_lr) if self.alpha_params else None
        )
        # algorithm.compile: true -> the fused step compiled; auto -> the fused step (eager);
        # false -> TorchRL's SACLoss step (the same numbers: tests/test_sac.py)
        self.compile = parse_compile(cfg.compile)
        self.fused: FusedSAC | None = None
        if self.compile != "false":
            self.fused = FusedSAC(self, compiled=self.compile == "true")

    def _make_loss(self, qnets: list) -> LossModule:
        c = self.cfg
        target = (
            -float(self.policy.act_dim) if c.target_entropy == "auto" else float(c.target_entropy)
        )
        return SACLoss(
            actor_network=self.policy.actor,
            qvalue_network=qnets,
            num_qvalue_nets=len(qnets),
            loss_function="l2",
            alpha_init=c.alpha_init,
            fixed_alpha=c.fixed_alpha,
            target_entropy=target,
            delay_actor=False,
            delay_qvalue=True,
        )

    def _optimizers(self) -> dict[str, torch.optim.Optimizer]:
        out = super()._optimizers()
        if self.alpha_optimizer is not None:
            out["alpha"] = self.alpha_optimizer
        return out

    def _lr_of(self) -> dict[str, float]:
        out = super()._lr_of()
        scale = self.learning_rate() / self.cfg.lr if self.cfg.lr > 0 else 1.0
        out["alpha"] = self.cfg.alpha_lr * scale
        return out

    def _applied(self, name: str) -> None:
        super()._applied(name)
        if name == "target_entropy":
            self.loss.target_entropy.fill_(float(self.cfg.target_entropy))

    def _gradient_step(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        if self.fused is not None:
            return self.fused.step(batch)
        out = self.loss(batch)
        return self._apply_losses(out["loss_qvalue"], out["loss_actor"], out["loss_alpha"],
                                  out["alpha"], out["entropy"])  # fmt: skip

    def _apply_losses(
        self, q_loss, actor_loss, alpha_loss, alpha, entropy
    ) -> dict[str, torch.Tensor]:
        """One backward through the three losses (they touch disjoint parameters: the actor's
        loss sees the Q networks detached), the NaN guard, clipping, the three Adam steps and the
        soft target update."""
        self.q_optimizer.zero_grad(set_to_none=True)
        self.actor_optimizer.zero_grad(set_to_none=True)
        total = q_loss + actor_loss
        if self.alpha_optimizer is not None:
            self.alpha_optimizer.zero_grad(set_to_none=True)
            total = total + alpha_loss
        total.backward()
        if self.nan_guard and not torch.isfinite(total.detach()):
            bad = [k for k, v in (("qvalue", q_loss), ("actor", actor_loss), ("alpha", alpha_loss))
                   if not torch.isfinite(v)]  # fmt: skip
            raise NonFiniteError(f"non-finite loss ({', '.join(bad)}) in algorithm=sac")
        if self.cfg.max_grad_norm > 0:
            torch.nn.utils.clip_grad_norm_(self.q_params, self.cfg.max_grad_norm)
            torch.nn.utils.clip_grad_norm_(self.actor_params, self.cfg.max_grad_norm)
        self.q_optimizer.step()
        self.actor_optimizer.step()
        if self.alpha_optimizer is not None:
            self.alpha_optimizer.step()
        self._soft_update()
        return {
            "loss/qvalue": q_loss.detach(),
            "loss/actor": actor_loss.detach(),
            "loss/alpha": alpha_loss.detach(),
            "loss/entropy_coeff": alpha.detach(),
            "loss/entropy": entropy.detach(),
        }
