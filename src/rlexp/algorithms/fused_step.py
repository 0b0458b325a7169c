"""The minibatch step as one function of plain tensors: the loss's forward, backward, the gradient
norm, clipping and fused Adam; run through ``torch.compile`` when ``algorithm.compile`` says so,
eager otherwise. ``FusedStep`` is that machinery; ``FusedPPOStep`` gives it PPO's loss (TorchRL's
``ClipPPOLoss`` as ``ppo.py`` configures it, written out), ``fused_grpo.FusedGRPOStep`` GRPO's.

Why: per minibatch, today's path builds TensorDicts (the slice, the loss's clone and output), runs
TorchRL's loss (compiled or not) and then an eager optimiser step; at 64 samples that Python and
dispatch work costs more than the arithmetic (issue #32). Here the minibatches are slices of plain
tensors gathered once per epoch, and the hyperparameters hooks may change (``lr``,
``clip_epsilon``, ``entropy_coeff``, ``max_grad_norm``, ``critic_coeff``, GRPO's ``kl_coeff``) enter
as 0-dim tensors, so a change never recompiles.

What stays as it was: the optimiser (its state is ``torch.optim.Adam``'s, stepped by the same
``_fused_adam_`` kernel, so checkpoints do not change), the minibatch order, the statistics, and the
NaN guard, checked between the backward and the step as ``guarded_step`` does. What it does not
cover falls back to today's path (``unsupported``): distributed gradient averaging, rsl_rl's
adaptive learning rate (``desired_kl``), a non-fused Adam. ``tests/test_fast_update.py`` checks it
against ``ClipPPOLoss`` for losses, gradients and updated parameters, and
``tests/test_fast_update_grpo.py`` against GRPO's TensorDict path.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Sequence

import torch
from tensordict import TensorDictBase
from torch.nn import functional as F

from rlexp.algorithms.base import NonFiniteError, what_was_non_finite
from rlexp.policies.heads import GaussianActorNet, MultiCategorical

log = logging.getLogger(__name__)

#: The flattened rollout's entries a minibatch step reads, in its arguments' order.
MINIBATCH_KEYS = (
    "observation",
    "action",
    "action_log_prob",
    "advantage",
    "value_target",
    "state_value",
)
#: Order of the per-minibatch statistics the step returns (ppo.STAT_KEYS' names).
STEP_STATS = (
    "loss_objective",
    "loss_critic",
    "loss_entropy",
    "entropy",
    "grad_norm",
    "clip_fraction",
    "kl_approx",
)
#: The mutable hyperparameters the loss and clipping read, in the order of the ``hyper`` tensor
#: (float32, as ClipPPOLoss's buffers); ``lr`` rides apart (float64: Adam's own is a Python float).
HYPER_KEYS = ("clip_epsilon", "entropy_coeff", "critic_coeff", "max_grad_norm")
_HALF_LOG_2PI = math.log(math.sqrt(2 * math.pi))  # torch.distributions.Normal's constant
#: Inductor options of the compiled step: no ``assert_size_stride`` on every input of every call
#: (~130 per minibatch step here, ~70 us of 900: the step's inputs are the same tensors, with the
#: same shapes, for the whole run, and dynamo's guards still check them).
_INDUCTOR = {"size_asserts": False}
_DISTANCE = {"l1": F.l1_loss, "l2": F.mse_loss, "smooth_l1": F.smooth_l1_loss}


def unsupported(algo) -> str | None:
    """Why the fused step cannot stand in for ``algo``'s (a ``PPO`` or ``GRPO``) today, or None
    when it can."""
    if algo.grad_sync is not None:
        return "distributed gradient averaging runs between backward and the optimiser step"
    if getattr(algo.cfg, "desired_kl", None) is not None:
        return "algorithm.desired_kl changes the learning rate before every minibatch"
    if not all(g.get("fused") for g in algo.optimizer.param_groups):
        return "Adam is not the fused kernel on this device"
    if any(g.get("amsgrad") or g.get("weight_decay") for g in algo.optimizer.param_groups):
        return "Adam has amsgrad or weight decay"
    if algo.cfg.name == "grpo" and getattr(algo.policy, "critic", None) is not None:
        # torch's Adam skips a parameter without a gradient; the fused step has no such case
        return "the policy's critic gets no gradient under GRPO (policy=actor_only fuses)"
    return None


def _step_hooks(optimizer: torch.optim.Optimizer) -> tuple[list[Callable], list[Callable]]:
    """The pre- and post-step hooks ``optimizer.step()`` would run (global ones included)."""
    from torch.optim import optimizer as optim

    pre = [
        *optim._global_optimizer_pre_hooks.values(),
        *optimizer._optimizer_step_pre_hooks.values(),
    ]
    post = [
        *optimizer._optimizer_step_post_hooks.values(),
        *optim._global_optimizer_post_hooks.values(),
    ]
    return pre, post


class FusedStep:
    """The machinery of a fused minibatch step over plain tensors (forward and backward, gradient
    norm, NaN guard, clipping, Adam on ``torch.optim.Adam``'s state, compiling); a subclass gives
    the loss and says what it reads and returns: ``epochs`` runs an update's steps, one statistics
    row (``stat_keys``) per minibatch."""

    #: the algorithm's name in log lines and NaN-guard messages
    name: str = ""
    #: the flattened rollout's entries a minibatch step reads, in ``loss``'s arguments' order
    minibatch_keys: tuple[str, ...] = ()
    #: the mutable hyperparameters ``loss`` reads from ``hyper`` (0-dim float32 each, built by
    #: ``hyper_values``); the last is ``max_grad_norm``, which the clipping reads
    hyper_keys: tuple[str, ...] = ()
    #: the order of a step's statistics row (``grad_norm`` among them; the others ``loss``'s, in
    #: the same order)
    stat_keys: tuple[str, ...] = ()

    def __init__(self, algo, compiled: bool) -> None:
        """``algo``: the learner whose policy, optimiser and settings the step uses."""
        self.policy = algo.policy
        self.params: list[torch.nn.Parameter] = algo.params
        self.param_names: list[str] = algo.param_names
        self.optimizer: torch.optim.Adam = algo.optimizer
        self.nan_guard: bool = algo.nan_guard
        group = self.optimizer.param_groups[0]
        self.adam = (*group["betas"], group["eps"])
        self.gaussian = isinstance(self.policy.actor_net, GaussianActorNet)
        self.compiled = compiled
        self.compile_choice: str = algo.compile
        self._grad_norm_at = self.stat_keys.index("grad_norm")
        self._first = compiled  # the first compiled call compiles (``_first_step``)
        self._state: tuple[list[torch.Tensor], ...] | None = None  # Adam's, per update
        self._grads: Callable = self._loss_and_grads
        self._apply: Callable = self._clip_and_adam
        if compiled:
            self._grads = torch.compile(self._loss_and_grads, dynamic=False, options=_INDUCTOR)
            self._apply = torch.compile(self._clip_and_adam, dynamic=False, options=_INDUCTOR)

    def loss(self, *minibatch: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(total loss, the statistics but ``grad_norm`` in ``stat_keys`` order) of one minibatch;
        its arguments: the ``minibatch_keys`` tensors, then ``hyper``."""
        raise NotImplementedError

    def hyper_values(self, cfg) -> list[float]:
        """The values of ``hyper_keys`` for an update (read from the learner's config)."""
        return [float(getattr(cfg, k)) for k in self.hyper_keys]

    def loss_terms(self, stats: torch.Tensor, hyper: torch.Tensor) -> dict[str, torch.Tensor]:
        """The loss terms the total had, named for the NaN guard's message."""
        raise NotImplementedError

    def minibatch_data(self, flat: TensorDictBase) -> list[torch.Tensor]:
        """The ``minibatch_keys`` tensors of the flattened rollout, one row per sample."""
        return [flat.get(k) for k in self.minibatch_keys]

    # -- the policy's distribution: TorchRL's IndependentNormal (torch's Normal, summed over the
    # action dims) or rlexp's MultiCategorical, the same operations in the same order
    def _dist(
        self, obs: torch.Tensor, cache: dict | None = None
    ) -> tuple[torch.Tensor, torch.Tensor] | MultiCategorical:
        """(loc, scale) of the Gaussian head, or the categorical head's distribution, on ``obs``
        (``cache``: image features the critic reads too, ``policies.inputs.encode``)."""
        if self.gaussian:
            return self.policy.actor_net(obs, cache)
        return MultiCategorical(self.policy.actor_net(obs, cache), self.policy.actor_net.nvec)

    def _log_prob(self, dist, action: torch.Tensor) -> torch.Tensor:
        if self.gaussian:
            loc, scale = dist
            var = scale**2  # Normal.log_prob's order (autograd sums the gradients in it)
            log_scale = scale.log()
            log_prob = -((action - loc) ** 2) / (2 * var) - log_scale - _HALF_LOG_2PI
            return log_prob.sum(-1)
        return dist.log_prob(action)

    def _entropy(self, dist) -> torch.Tensor:
        if self.gaussian:  # a log of its own, as Normal.entropy's (gradients sum in its order)
            return (0.5 + 0.5 * math.log(2 * math.pi) + dist[1].log()).sum(-1)
        return dist.entropy()

    def _log_prob_entropy(
        self, obs: torch.Tensor, action: torch.Tensor, cache: dict | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        dist = self._dist(obs, cache)
        return self._log_prob(dist, action), self._entropy(dist)

    def _loss_and_grads(self, *minibatch: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """Forward, backward and the gradient norm (before clipping)."""
        for p in self.params:
            p.grad = None
        total, stats = self.loss(*minibatch)
        total.backward()
        grad_norm = torch.nn.utils.get_total_norm([p.grad for p in self.params])
        return total.detach(), stats, grad_norm

    @torch.no_grad()
    def _clip_and_adam(
        self,
        grad_norm: torch.Tensor,
        hyper: torch.Tensor,
        lr: torch.Tensor | float,
        state: tuple[list[torch.Tensor], list[torch.Tensor], list[torch.Tensor]],
    ) -> None:
        """clip_grads_with_norm_ (max_grad_norm, ``hyper``'s last entry, <= 0: off), then Adam on ``torch.optim.Adam``'s
        state (``state``: its step counts, first and second moments)."""
        max_grad_norm = hyper[-1]
        grads = [p.grad for p in self.params]
        # clip_grads_with_norm_ to the bit: its float / tensor is reciprocal() * float in torch
        coef = ((grad_norm + 1e-6).reciprocal() * max_grad_norm).clamp(max=1.0)
        torch._foreach_mul_(grads, torch.where(max_grad_norm > 0, coef, 1.0))
        steps, exp_avgs, exp_avg_sqs = state
        beta1, beta2, eps = self.adam  # constants: read once, so no guard watches param_groups
        torch._foreach_add_(steps, 1)
        if not self.compiled:  # the kernel torch.optim.Adam(fused=True).step() calls
            torch._fused_adam_(
                self.params,
                grads,
                exp_avgs,
                exp_avg_sqs,
                [],
                steps,
                amsgrad=False,
                lr=lr,
                beta1=beta1,
                beta2=beta2,
                weight_decay=0.0,
                eps=eps,
                maximize=False,
            )
            return
        # Compiled: the same update rule as tensor ops (inductor has no kernel for _fused_adam_;
        # it fuses these into one loop), the step count and learning rate as tensors.
        for param, grad, m, v, step in zip(
            self.params, grads, exp_avgs, exp_avg_sqs, steps, strict=True
        ):
            m.lerp_(grad, 1 - beta1)
            v.mul_(beta2).addcmul_(grad, grad, value=1 - beta2)
            step_size = lr / (1 - beta1**step)
            denom = (v.sqrt() / (1 - beta2**step).sqrt()).add_(eps)
            param.sub_(step_size * m / denom)

    def _adam_state(self) -> tuple[list[torch.Tensor], list[torch.Tensor], list[torch.Tensor]]:
        """Adam's state tensors: step counts, first and second moments (created as
        ``Adam._init_group`` does with ``fused=True`` where missing)."""
        for p in self.params:
            state = self.optimizer.state[p]
            if not state:
                state["step"] = torch.zeros((), dtype=torch.float32, device=p.device)
                state["exp_avg"] = torch.zeros_like(p, memory_format=torch.preserve_format)
                state["exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.preserve_format)
        states = [self.optimizer.state[p] for p in self.params]
        return (
            [s["step"] for s in states],
            [s["exp_avg"] for s in states],
            [s["exp_avg_sq"] for s in states],
        )

    def step(
        self,
        minibatch: Sequence[torch.Tensor],
        hyper: torch.Tensor,
        lr: torch.Tensor | float,
        where: str,
    ) -> torch.Tensor:
        """One guarded minibatch step; its statistics in ``stat_keys`` order."""
        total, stats, grad_norm = self._grads(*minibatch, hyper)
        if self.nan_guard and not torch.isfinite(grad_norm + total).all():
            terms = self.loss_terms(stats, hyper)
            what = what_was_non_finite(terms, total, self.params, self.param_names, False)
            raise NonFiniteError(f"non-finite {what} in {where}")
        if self._state is None:  # Adam's state appears at its first step, as torch.optim.Adam's
            self._state = self._adam_state()
        pre, post = _step_hooks(self.optimizer)
        for hook in pre:  # as torch.optim.Optimizer.step: callbacks see every optimiser step
            hook(self.optimizer, (), {})
        self._apply(grad_norm, hyper, lr, self._state)
        for hook in post:
            hook(self.optimizer, (), {})
        at = self._grad_norm_at
        return torch.cat([stats[:at], grad_norm.reshape(1), stats[at:]])

    def epochs(
        self, flat: TensorDictBase, cfg, mb: int, generator: torch.Generator
    ) -> list[torch.Tensor]:
        """``cfg.num_epochs`` passes of shuffled minibatches over the flattened rollout (the order
        the learner's TensorDict path draws from ``generator``); one statistics row per minibatch."""
        n = flat.shape[0]
        data = self.minibatch_data(flat)
        device = data[0].device
        hyper = torch.tensor(self.hyper_values(cfg), device=device)
        lr: torch.Tensor | float = float(self.optimizer.param_groups[0]["lr"])
        if self.compiled:  # a tensor: a new rate (annealing, hooks) must not recompile
            lr = torch.tensor(lr, dtype=torch.float64, device=device)
        # Adam's state tensors, looked up afresh: ``load_state_dict`` replaces them.
        self._state = self._adam_state() if self.optimizer.state else None
        rows = []
        for epoch in range(cfg.num_epochs):
            # One gather per epoch, then contiguous slices (views), as ppo.update does.
            perm = torch.randperm(n, generator=generator)
            shuffled = [t[perm] for t in data]
            for start in range(0, n - mb + 1, mb):
                where = f"{self.name.upper()} update (epoch {epoch}, minibatch {start // mb})"
                batch = [t[start : start + mb] for t in shuffled]
                step = self._first_step if self._first else self.step
                rows.append(step(batch, hyper, lr, where))
        return rows

    def _first_step(self, batch, hyper, lr, where) -> torch.Tensor:
        """The first compiled step compiles: its random draws undone (a resumed run compiles at
        another point), a backend failure falls back to eager unless ``algorithm.compile=true``."""
        from rlexp.checkpoints.files import rng_state, set_rng_state

        self._first = False
        t0 = time.perf_counter()
        rng = rng_state()
        try:
            out = self.step(batch, hyper, lr, where)
        except NonFiniteError:
            raise
        except Exception as exc:
            if self.compile_choice == "true":
                raise
            log.warning(
                "[%s] torch.compile failed, eager fused step from here on: %s", self.name, exc
            )
            self._grads, self._apply, self.compiled = (
                self._loss_and_grads,
                self._clip_and_adam,
                False,
            )
            return self.step(batch, hyper, float(lr), where)
        finally:
            set_rng_state(rng)  # the step itself draws nothing: only compiling did
        log.info(
            "[%s] loss compiled in %.1f s (the fused minibatch step)",
            self.name,
            time.perf_counter() - t0,
        )
        return out


class FusedPPOStep(FusedStep):
    """PPO's minibatch steps: ClipPPOLoss's maths for rlexp's settings on plain tensors."""

    name = "ppo"
    minibatch_keys = MINIBATCH_KEYS
    hyper_keys = HYPER_KEYS
    stat_keys = STEP_STATS

    def __init__(self, algo, compiled: bool) -> None:
        """``algo``: the ``PPO`` whose policy, optimiser and settings the step uses."""
        cfg = algo.cfg
        self.loss_critic_type: str = cfg.loss_critic_type
        self.normalize_advantage: bool = cfg.normalize_advantage
        self.clip_value: float | None = cfg.clip_value
        super().__init__(algo, compiled)

    def minibatch_data(self, flat: TensorDictBase) -> list[torch.Tensor]:
        data = super().minibatch_data(flat)
        data[2] = data[2].reshape(flat.shape[0])  # action_log_prob: one per sample
        return data

    def loss_terms(self, stats: torch.Tensor, hyper: torch.Tensor) -> dict[str, torch.Tensor]:
        terms = dict(zip(STEP_STATS[:3], stats[:3], strict=True))
        if float(hyper[1]) == 0.0:  # as ppo.update: a switched-off term is not a culprit
            del terms["loss_entropy"]
        return terms

    def loss(
        self,
        obs: torch.Tensor,
        action: torch.Tensor,
        old_log_prob: torch.Tensor,
        advantage: torch.Tensor,
        value_target: torch.Tensor,
        old_value: torch.Tensor,
        hyper: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(total loss, the statistics but ``grad_norm`` in STEP_STATS order) of one minibatch."""
        clip_epsilon, entropy_coeff, critic_coeff = hyper[0], hyper[1], hyper[2]
        if self.normalize_advantage and advantage.numel() > 1:  # torchrl _standardize
            advantage = (advantage - advantage.mean()) / advantage.std().clamp_min(
                torch.finfo(torch.float).resolution
            )
        # a shared image encoder runs once for both heads (policy.share_encoder; no-op without images)
        cache: dict = {}
        log_prob, entropy = self._log_prob_entropy(obs, action, cache)
        log_weight = (log_prob - old_log_prob).unsqueeze(-1)
        kl_approx = (old_log_prob - log_prob).unsqueeze(-1)
        gain1 = log_weight.exp() * advantage
        log_weight_clip = log_weight.clamp((-clip_epsilon).log1p(), clip_epsilon.log1p())
        clip_fraction = (log_weight_clip != log_weight).to(log_weight.dtype).mean()
        gain2 = log_weight_clip.exp() * advantage
        gain = torch.stack([gain1, gain2], -1).min(dim=-1).values
        loss_objective = (-gain).mean()
        entropy = entropy.unsqueeze(-1)
        loss_entropy = (-entropy_coeff * entropy).mean()
        value = self.policy.critic_net(obs, cache)
        distance = _DISTANCE[self.loss_critic_type]
        loss_value = distance(value_target, value, reduction="none")
        if self.clip_value:  # torchrl _clip_value_loss: the more pessimistic of the two
            clipped = (value - old_value).clamp(-self.clip_value, self.clip_value)
            clipped_loss = distance(value_target, old_value + clipped, reduction="none")
            loss_value = torch.maximum(loss_value, clipped_loss)
        loss_critic = (critic_coeff * loss_value).mean()
        # ppo.update's rule: the entropy term joins the total only while entropy_coeff != 0
        total = loss_objective + loss_critic
        total = total + torch.where(entropy_coeff != 0, loss_entropy, 0.0)
        stats = torch.stack(
            [
                loss_objective,
                loss_critic,
                loss_entropy,
                entropy.mean(),
                clip_fraction,
                kl_approx.mean(),
            ]
        ).detach()
        return total, stats
