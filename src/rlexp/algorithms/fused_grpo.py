"""GRPO's minibatch step on the fused machinery (``fused_step.FusedStep``): ``GRPO.loss``'s maths on
plain tensors (the mask-weighted clipped surrogate, the entropy term while ``entropy_coeff != 0``,
the k3 KL to the frozen reference with ``kl_coeff > 0``, the statistics it logs), the same
operations in the same order, so that an eager update equals the TensorDict path's
(``tests/test_fast_update_grpo.py``). Backward, clipping, Adam, the NaN guard and compiling are
``FusedStep``'s, shared with PPO.
"""

from __future__ import annotations

import torch

from rlexp.algorithms.fused_step import FusedStep

#: the loss terms, as named in NaN-guard messages
LOSS_KEYS = ("loss_objective", "loss_entropy", "loss_kl")
#: per-minibatch statistics, averaged over the update (the fused step's row order too)
STAT_KEYS = (*LOSS_KEYS, "entropy", "kl_ref", "approx_kl", "clip_fraction", "grad_norm")


class FusedGRPOStep(FusedStep):
    """GRPO's minibatch steps over plain tensors: one row of STAT_KEYS per minibatch (``loss_kl``
    and ``kl_ref`` are 0 without a reference, ``loss_entropy`` is ``-entropy_coeff * entropy``
    whether or not the term is in the loss: ``GRPO.update`` logs only what the loss had)."""

    name = "grpo"
    #: ``clip_low`` / ``clip_high``: 1 -/+ clip_epsilon, rounded once from the double as the
    #: TensorDict path's Python-float bounds are
    hyper_keys = ("clip_low", "clip_high", "entropy_coeff", "kl_coeff", "max_grad_norm")
    stat_keys = STAT_KEYS

    def __init__(self, algo, compiled: bool) -> None:
        """``algo``: the ``GRPO`` whose policy, optimiser, reference and settings the step uses."""
        self.has_reference = algo.reference is not None
        self.minibatch_keys = (
            "observation",
            "action",
            "action_log_prob",
            "advantage",
            "mask",
            *(("ref_log_prob",) if self.has_reference else ()),
        )
        super().__init__(algo, compiled)

    def hyper_values(self, cfg) -> list[float]:
        eps = float(cfg.clip_epsilon)
        return [1.0 - eps, 1.0 + eps, cfg.entropy_coeff, cfg.kl_coeff, cfg.max_grad_norm]

    def loss_terms(self, stats: torch.Tensor, hyper: torch.Tensor) -> dict[str, torch.Tensor]:
        terms = {"loss_objective": stats[0]}
        if float(hyper[2]) != 0.0:  # as GRPO.loss: the entropy term only while it is on
            terms["loss_entropy"] = stats[1]
        if self.has_reference:
            terms["loss_kl"] = stats[2]
        return terms

    def loss(
        self,
        obs: torch.Tensor,
        action: torch.Tensor,
        old_log_prob: torch.Tensor,
        advantage: torch.Tensor,
        mask: torch.Tensor,
        *rest: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(total loss, STAT_KEYS but ``grad_norm``) of one minibatch; ``rest``: the reference's
        log-probabilities (with a reference), then ``hyper``."""
        ref_log_prob, hyper = rest if self.has_reference else (None, rest[0])
        low, high, entropy_coeff, kl_coeff = hyper[0], hyper[1], hyper[2], hyper[3]
        dist = self._dist(obs)
        log_prob = self._log_prob(dist, action)
        denom = mask.sum().clamp(min=1)  # an all-masked minibatch: loss 0

        def mean(x: torch.Tensor) -> torch.Tensor:
            return (mask * x).sum() / denom

        log_ratio = log_prob - old_log_prob
        ratio = log_ratio.exp()
        surrogate = torch.min(ratio * advantage, ratio.clamp(low, high) * advantage)
        entropy = mean(self._entropy(dist))  # after the surrogate, as GRPO.loss (autograd's order)
        loss_objective = -mean(surrogate)
        loss_entropy = -entropy_coeff * entropy
        # GRPO.update's rule: the entropy term joins the total only while entropy_coeff != 0
        total = loss_objective + torch.where(entropy_coeff != 0, loss_entropy, 0.0)
        zero = entropy.new_zeros(())
        loss_kl = kl_ref = zero
        if ref_log_prob is not None:
            diff = ref_log_prob - log_prob  # TorchRL's k3_kl_token_estimate
            kl_ref = mean(diff.expm1() - diff)
            loss_kl = kl_coeff * kl_ref
            total = total + loss_kl
        with torch.no_grad():  # PPO's diagnostics (TorchRL's kl_approx, clip_fraction), masked
            approx_kl = mean(-log_ratio)
            clip_fraction = mean(((ratio < low) | (ratio > high)).to(mask.dtype))
        stats = torch.stack(
            [loss_objective, loss_entropy, loss_kl, entropy, kl_ref, approx_kl, clip_fraction]
        ).detach()
        return total, stats
