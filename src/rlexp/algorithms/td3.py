"""TD3 (Fujimoto et al. 2018) on TorchRL's ``TD3Loss``: twin Q networks, target policy smoothing
(the target action ``clip(mu'(s') + clip(eps, -c, c), low, high)``, ``eps ~ N(0, sigma^2)``), and
the actor and the targets updated every ``policy_delay`` critic updates. Noise scales are in
units of half the action range (SB3's, whose policy acts in [-1, 1]). docs/td3.md.

One gradient step: the critics' loss ``sum_i (Q_i(s, a) - y)^2`` with
``y = r + gamma * (1 - terminated) * min_i Q'_i(s', a')``; every ``policy_delay``-th step, after the
critics' Adam step, the actor's ``-Q_1(s, mu(s))`` and the targets
``theta' <- tau * theta + (1 - tau) * theta'`` (actor and critics), as SB3 and the paper.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torchrl.objectives import LossModule, TD3Loss

from rlexp.algorithms.base import parse_compile
from rlexp.algorithms.fused_sac import FusedTD3
from rlexp.algorithms.offpolicy import OffPolicy


class TD3(OffPolicy):
    """``algorithm=td3``."""

    def __init__(self, cfg, policy, total_iterations, nan_guard=True, grad_sync=None,
                 run_dir=None, seed=0) -> None:  # fmt: skip
        if cfg.name != "td3":
            raise ValueError(f"algorithm.name={cfg.name!r}; available: ['td3']")
        super().__init__(cfg, policy, total_iterations, nan_guard, grad_sync, run_dir, seed)
        self._noise_scales()
        # algorithm.compile: auto / true -> the fused step (fused_sac.FusedTD3, eager); false ->
        # TorchRL's TD3Loss step (the same numbers: tests/test_sac.py)
        self.fused = FusedTD3(self) if parse_compile(cfg.compile) != "false" else None

    def _make_loss(self, qnets: list) -> LossModule:
        p = self.policy
        return TD3Loss(
            actor_network=p.actor,
            qvalue_network=qnets,
            bounds=(p.action_low, p.action_high),
            num_qvalue_nets=len(qnets),
            loss_function="l2",
            delay_actor=True,
            delay_qvalue=True,
        )

    def _noise_scales(self) -> None:
        """The config's noise (x half range) into the loss's and the sampler's absolute units."""
        half = (self.policy.action_high - self.policy.action_low) * 0.5
        self.loss.policy_noise = self.cfg.target_policy_noise * half
        self.loss.noise_clip = self.cfg.target_noise_clip * half
        self.policy.exploration_noise = float(self.cfg.exploration_noise)

    def _applied(self, name: str) -> None:
        super()._applied(name)
        self._noise_scales()

    def _gradient_step(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        if self.fused is not None:
            return self.fused.step(batch)
        q_loss, _ = self.loss.value_loss(batch)
        self._step(self.q_optimizer, self.q_params, q_loss, "qvalue")
        out = {"loss/qvalue": q_loss.detach()}
        if (self.gradient_steps + 1) % self.cfg.policy_delay == 0:
            actor_loss, _ = self.loss.actor_loss(batch)
            self._step(self.actor_optimizer, self.actor_params, actor_loss, "actor")
            self._soft_update()
            out["loss/actor"] = actor_loss.detach()
        return out
