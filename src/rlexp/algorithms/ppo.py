"""PPO: TorchRL's ``GAE`` and ``ClipPPOLoss``, Adam, epochs x minibatches, optional LR annealing."""

from __future__ import annotations

from collections.abc import Callable

import torch
from tensordict import TensorDictBase
from torchrl.objectives import ClipPPOLoss
from torchrl.objectives.value import GAE

from rlexp.config.schema import AlgorithmConfig
from rlexp.policies.actor_critic import ActorCritic

LOSS_KEYS = ("loss_objective", "loss_critic", "loss_entropy")


class NonFiniteError(FloatingPointError):
    """A NaN or Inf in a loss, a gradient or an observation: the run stops, checkpoints stay as they were."""


def make_gae(cfg: AlgorithmConfig, value_network) -> GAE:
    """TorchRL's GAE: bootstraps from V(next obs) unless ``terminated``; ``done`` cuts the trace."""
    return GAE(
        gamma=cfg.gamma,
        lmbda=cfg.lmbda,
        value_network=value_network,
        average_gae=False,
        differentiable=False,
    )


class PPO:
    """One PPO learner: ``update(batch)`` runs GAE then the clipped-surrogate epochs on a rollout."""

    def __init__(
        self,
        cfg: AlgorithmConfig,
        policy: ActorCritic,
        total_iterations: int,
        nan_guard: bool = True,
        grad_sync: Callable[[list[torch.Tensor]], None] | None = None,
    ) -> None:
        if cfg.name != "ppo":
            raise ValueError(f"algorithm.name={cfg.name!r}; available: ['ppo']")
        if cfg.loss_critic_type not in ("l1", "l2", "smooth_l1"):
            raise ValueError(
                f"algorithm.loss_critic_type={cfg.loss_critic_type!r}; choose from ['l1', 'l2', 'smooth_l1']"
            )
        self.cfg = cfg
        self.policy = policy
        self.total_iterations = max(1, total_iterations)
        self.nan_guard = nan_guard
        self.grad_sync = (
            grad_sync  # distributed: averages the gradients over ranks after every backward
        )
        self.gae = make_gae(cfg, policy.critic)
        self.loss = ClipPPOLoss(
            actor_network=policy.actor,
            critic_network=policy.critic,
            clip_epsilon=cfg.clip_epsilon,
            entropy_bonus=cfg.entropy_coeff != 0.0,
            entropy_coeff=cfg.entropy_coeff,
            critic_coeff=cfg.critic_coeff,
            loss_critic_type=cfg.loss_critic_type,
            normalize_advantage=cfg.normalize_advantage,
            clip_value=cfg.clip_value,
            functional=False,
        )
        self.loss.set_keys(sample_log_prob="action_log_prob")
        self.params = [p for p in policy.parameters() if p.requires_grad]
        self.optimizer = torch.optim.Adam(self.params, lr=cfg.lr, eps=cfg.adam_eps, foreach=True)
        self.iteration = 0

    def learning_rate(self) -> float:
        if not self.cfg.anneal_lr:
            return self.cfg.lr
        return self.cfg.lr * max(0.0, 1.0 - self.iteration / self.total_iterations)

    @torch.no_grad()
    def compute_advantages(self, batch: TensorDictBase) -> TensorDictBase:
        """Writes ``advantage`` and ``value_target`` (time is the last batch dim)."""
        return self.gae(batch)

    def update(self, batch: TensorDictBase) -> dict[str, float]:
        """GAE over the rollout, then ``num_epochs`` passes of shuffled minibatches."""
        lr = self.learning_rate()
        for group in self.optimizer.param_groups:
            group["lr"] = lr
        self.compute_advantages(batch)
        flat = batch.reshape(-1).select(
            "observation",
            "action",
            "action_log_prob",
            "advantage",
            "value_target",
            "state_value",
            strict=False,
        )
        n = flat.shape[0]
        mb = min(self.cfg.mini_batch_size, n)
        sums = {k: torch.zeros(()) for k in (*LOSS_KEYS, "grad_norm", "clip_fraction", "kl_approx")}
        count = 0
        for epoch in range(self.cfg.num_epochs):
            # One gather per epoch, then contiguous slices: cheaper than indexing every minibatch.
            shuffled = flat[torch.randperm(n)]
            for start in range(0, n - mb + 1, mb):
                minibatch = shuffled[start : start + mb]
                out = self.loss(minibatch)
                total = out["loss_objective"] + out["loss_critic"]
                if "loss_entropy" in out.keys():
                    total = total + out["loss_entropy"]
                self.optimizer.zero_grad(set_to_none=True)
                total.backward()
                if self.grad_sync is not None:
                    for p in self.params:
                        if p.grad is None:
                            p.grad = torch.zeros_like(p)
                    self.grad_sync([p.grad for p in self.params])
                if self.cfg.max_grad_norm > 0:
                    grad_norm = torch.nn.utils.clip_grad_norm_(self.params, self.cfg.max_grad_norm)
                else:
                    grad_norm = torch.nn.utils.get_total_norm(
                        [p.grad for p in self.params if p.grad is not None]
                    )
                if self.nan_guard and not (torch.isfinite(total) and torch.isfinite(grad_norm)):
                    bad = [k for k in LOSS_KEYS if k in out.keys() and not torch.isfinite(out[k])]
                    what = f"loss ({', '.join(bad)})" if bad else "gradient norm"
                    raise NonFiniteError(
                        f"non-finite {what} in PPO update (epoch {epoch}, minibatch {start // mb})"
                    )
                self.optimizer.step()
                for k in LOSS_KEYS:
                    if k in out.keys():
                        sums[k] += out[k].detach()
                sums["grad_norm"] += grad_norm.detach()
                if "clip_fraction" in out.keys():
                    sums["clip_fraction"] += out["clip_fraction"].detach()
                if "kl_approx" in out.keys():
                    sums["kl_approx"] += out["kl_approx"].detach()
                count += 1
        self.iteration += 1
        metrics = {k.replace("loss_", ""): float(v) / max(count, 1) for k, v in sums.items()}
        out = {
            "loss/policy": metrics["objective"],
            "loss/value": metrics["critic"],
            "loss/entropy": metrics["entropy"],
            "loss/grad_norm": metrics["grad_norm"],
            "loss/clip_fraction": metrics["clip_fraction"],
            "loss/approx_kl": metrics["kl_approx"],
            "loss/learning_rate": lr,
            "loss/log_std": float(self.policy.actor_net.log_std.detach().mean()),
        }
        return out

    def state_dict(self) -> dict:
        return {"optimizer": self.optimizer.state_dict(), "iteration": self.iteration}

    def load_state_dict(self, sd: dict) -> None:
        self.optimizer.load_state_dict(sd["optimizer"])
        self.iteration = int(sd["iteration"])


def make_algorithm(
    cfg: AlgorithmConfig,
    policy: ActorCritic,
    total_iterations: int,
    nan_guard: bool = True,
    grad_sync: Callable[[list[torch.Tensor]], None] | None = None,
) -> PPO:
    """Build the configured algorithm around ``policy`` (``grad_sync``: the distributed all-reduce)."""
    return PPO(cfg, policy, total_iterations, nan_guard, grad_sync)
