"""What every learner shares: the ``Algorithm`` interface the Trainer drives, Adam, the ``compile``
choice, and one guarded optimiser step (gradient sync -> NaN guard -> clip -> step) with the message
that says what was non-finite."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import TYPE_CHECKING, Any, Protocol

import torch

if TYPE_CHECKING:
    from tensordict import TensorDictBase

    from rlexp.config.schema import BaseAlgorithmConfig

COMPILE_CHOICES = ("auto", "true", "false")

#: ``algorithm.compile=auto`` compiles when the run's estimated saving is at least this many seconds.
AUTO_COMPILE_MIN_SAVING_S = 60.0
#: Estimated saving of a compiled over an eager minibatch update (loss forward + backward), measured
#: on a 2-core CPU (docs/performance.md): ~1 ms of Python and dispatch per update (1.25 vs 2.3 ms at
#: 64 samples, 64x64 tanh) plus ~2 us per sample (72 vs 90 ms at 8192 samples, 256x256 relu).
COMPILE_SAVING_PER_UPDATE_S = 1.0e-3
COMPILE_SAVING_PER_SAMPLE_S = 2.0e-6
#: The same for the fused minibatch step (fused_step.py), whose eager step has less Python to save:
#: 0.37 ms per update at 64 samples (1.30 vs 0.92 ms, benchmarks/ppo_floor.py); compiling it takes
#: 20-25 s on a cold inductor cache (the 60 s threshold leaves it paid back).
FUSED_COMPILE_SAVING_PER_UPDATE_S = 0.35e-3


def compile_saving_s(updates: int, mb: int, fused: bool) -> float:
    """``algorithm.compile=auto``'s estimate of what compiling saves over a run of ``updates``
    minibatch steps of ``mb`` samples (``fused``: the fused step's, else the loss's alone); it
    compiles when this is at least AUTO_COMPILE_MIN_SAVING_S."""
    per_update = FUSED_COMPILE_SAVING_PER_UPDATE_S if fused else COMPILE_SAVING_PER_UPDATE_S
    return updates * (per_update + COMPILE_SAVING_PER_SAMPLE_S * mb)


#: The distributed gradient average: all-reduces (mean) a list of tensors in place.
GradSync = Callable[[list[torch.Tensor]], None]


class NonFiniteError(FloatingPointError):
    """A NaN or Inf in a loss, a gradient or an observation: the run stops, checkpoints stay as they were."""


class Algorithm(Protocol):
    """What the Trainer needs of a learner (PPO, GRPO)."""

    #: updates done so far (drives LR annealing; saved in checkpoints)
    iteration: int
    #: whether the Trainer resets every env before each rollout (GRPO's groups start together)
    reset_each_rollout: bool

    def update(self, batch: TensorDictBase) -> dict[str, float]:
        """Learn from one rollout [num_envs, T]; returns ``loss/...`` metrics."""
        ...

    def learning_rate(self) -> float:
        """The learning rate the next update uses."""
        ...

    def state_dict(self) -> dict[str, Any]:
        """Optimiser state, iteration and anything else a bit-exact resume needs."""
        ...

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        """Restore what ``state_dict`` returned."""
        ...

    def hyperparameters(self) -> dict[str, float]:
        """The hyperparameters hooks may change (``set_hyperparameter``), with their values."""
        ...

    def set_hyperparameter(self, name: str, value: float) -> None:
        """Change one of ``hyperparameters()`` from the next update on."""
        ...


class MutableHyperparameters:
    """``hyperparameters`` / ``set_hyperparameter`` over the fields of the learner's own copy of its
    config (``self.cfg``) that ``rlexp.config.rules.MUTABLE_HYPERPARAMETERS`` names for the
    algorithm; ``_applied(name)`` pushes a change into whatever
    holds a copy of the value (a TorchRL loss's buffer). The values are part of ``state_dict`` so a
    resumed run continues with what hooks set."""

    cfg: Any
    iteration: int
    total_iterations: int

    def backward_and_step(
        self, total: torch.Tensor, terms: dict[str, torch.Tensor], where: str
    ) -> torch.Tensor:
        """One optimiser step of an on-policy learner's TensorDict path: zero the gradients,
        backward ``total``, then ``guarded_step`` with the learner's optimiser, parameters, gradient
        clipping, distributed averaging and NaN guard; the gradient norm (``where``: the message's
        place, e.g. the epoch and minibatch)."""
        self.optimizer.zero_grad(set_to_none=True)
        total.backward()
        return guarded_step(
            self.optimizer,
            self.params,
            self.param_names,
            total,
            terms,
            max_grad_norm=self.cfg.max_grad_norm,
            grad_sync=self.grad_sync,
            nan_guard=self.nan_guard,
            where=where,
        )

    def mutable(self) -> tuple[str, ...]:
        from rlexp.config.rules import MUTABLE_HYPERPARAMETERS

        return MUTABLE_HYPERPARAMETERS[self.cfg.name]

    def learning_rate(self) -> float:
        """``lr``, annealed linearly to 0 over ``total_iterations`` with ``anneal_lr``."""
        if not self.cfg.anneal_lr:
            return self.cfg.lr
        return self.cfg.lr * max(0.0, 1.0 - self.iteration / self.total_iterations)

    def hyperparameters(self) -> dict[str, float]:
        return {name: float(getattr(self.cfg, name)) for name in self.mutable()}

    def set_hyperparameter(self, name: str, value: float) -> None:
        if name not in self.mutable():
            raise ValueError(
                f"{name!r} is not a mutable hyperparameter of algorithm={self.cfg.name}; choose "
                f"from {sorted(self.mutable())}"
            )
        setattr(self.cfg, name, float(value))
        self._applied(name)

    def _applied(self, name: str) -> None:
        """A hyperparameter changed (the learner reads the others from ``self.cfg`` when used)."""

    def _load_hyperparameters(self, sd: Mapping[str, Any]) -> None:
        for name, value in (sd.get("hyperparameters") or {}).items():
            if name in self.mutable() and float(getattr(self.cfg, name)) != float(value):
                self.set_hyperparameter(name, value)


def parse_compile(value: str | bool) -> str:
    """``algorithm.compile`` as one of COMPILE_CHOICES (true/false may arrive as bools or 'True')."""
    choice = str(value).strip().lower()
    if choice not in COMPILE_CHOICES:
        raise ValueError(f"algorithm.compile={value!r}; choose from {list(COMPILE_CHOICES)}")
    return choice


def make_optimizer(params: list[torch.nn.Parameter], cfg: BaseAlgorithmConfig) -> torch.optim.Adam:
    """Adam; the fused kernel on CPU and CUDA (one kernel for all tensors, ~3.5x faster than foreach
    at 64x64 here), foreach elsewhere. Same update rule either way."""
    fused = bool(params) and all(p.device.type in ("cpu", "cuda") for p in params)
    if fused:
        return torch.optim.Adam(params, lr=cfg.lr, eps=cfg.adam_eps, fused=True)
    return torch.optim.Adam(params, lr=cfg.lr, eps=cfg.adam_eps, foreach=True)


def guarded_step(
    optimizer: torch.optim.Optimizer,
    params: Sequence[torch.nn.Parameter],
    param_names: Sequence[str],
    loss: torch.Tensor,
    terms: Mapping[str, torch.Tensor],
    *,
    max_grad_norm: float,
    grad_sync: GradSync | None,
    nan_guard: bool,
    where: str,
) -> torch.Tensor:
    """After ``loss.backward()``: average the gradients over ranks, stop on a non-finite loss or
    gradient (``NonFiniteError`` naming ``terms``' culprits or the parameters, then ``where``),
    clip to ``max_grad_norm`` (<= 0: off) and step. Returns the gradient norm before clipping."""
    loss_seen = loss.detach()
    if grad_sync is not None:
        for p in params:
            if p.grad is None:
                p.grad = torch.zeros_like(p)
        # The loss rides along in the gradients' all-reduce: a non-finite loss on any rank makes it
        # non-finite on all, so all ranks stop together (one rank raising alone would leave the
        # others blocked in their next collective).
        loss_seen = loss_seen.reshape(1).clone()
        grad_sync([*(p.grad for p in params), loss_seen])
    grad_norm = torch.nn.utils.get_total_norm([p.grad for p in params if p.grad is not None])
    # A non-finite loss gives a non-finite gradient norm: one check before the step, before
    # clipping by a NaN norm turns every gradient into NaN.
    if nan_guard and not torch.isfinite(grad_norm + loss_seen).all():
        what = what_was_non_finite(terms, loss_seen, params, param_names, grad_sync is not None)
        raise NonFiniteError(f"non-finite {what} in {where}")
    if max_grad_norm > 0:  # = clip_grad_norm_, with the norm taken above
        torch.nn.utils.clip_grads_with_norm_(params, max_grad_norm, grad_norm)
    optimizer.step()
    return grad_norm


def what_was_non_finite(
    terms: Mapping[str, torch.Tensor],
    loss_seen: torch.Tensor,
    params: Sequence[torch.nn.Parameter],
    param_names: Sequence[str],
    synced: bool,
) -> str:
    """The loss terms (and, distributed, the ranks) or the parameters whose gradients were NaN/Inf.

    Distributed (``synced``), every rank gets here at the same minibatch (the decision is taken on
    all-reduced values), so the ranks can gather what each of them saw."""
    import torch.distributed as dist

    mine = [k for k, v in terms.items() if not torch.isfinite(v).all()]
    if synced and dist.is_available() and dist.is_initialized():
        from rlexp.runtime.distributed import all_gather_object

        seen = [
            f"{', '.join(keys)} on rank {rank}"
            for rank, keys in enumerate(all_gather_object(mine))
            if keys
        ]
        if seen:
            return f"loss ({'; '.join(seen)})"
    elif mine:
        return f"loss ({', '.join(mine)})"
    names = [
        name
        for name, p in zip(param_names, params, strict=True)
        if p.grad is not None and not torch.isfinite(p.grad).all()
    ]
    if names:
        shown = ", ".join(names[:3]) + (f" and {len(names) - 3} more" if len(names) > 3 else "")
        averaged = " after averaging over ranks" if synced else ""
        return f"gradient ({shown}){averaged}"
    if not torch.isfinite(loss_seen).all():  # not here, not gathered: another rank's loss
        return "loss on another rank"
    return "gradient norm (the gradients are finite, their norm overflows)"
