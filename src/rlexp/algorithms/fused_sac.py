"""SAC's (and TD3's: ``FusedTD3``) gradient step as one function of plain tensors (``algorithm.compile``, docs/sac.md "Speed"):
the critics', actor's and alpha's losses of TorchRL's ``SACLoss`` written out on the same
parameters (the twin Q networks as stacked ``[n, out, in]`` weights, one batched matmul per layer
instead of ``vmap``), the same random draws in the same order (the next action's noise, then the
current one's), so the TorchRL path and this one compute the same step (tested); the optimisers
and the target update are the learner's own (fused Adam, one ``lerp_`` over the targets).

``torch.compile`` takes the loss function (forward and backward) whole; eager, it already skips
TorchRL's per-step TensorDict and ``vmap`` bookkeeping.

``trainer.precision=bf16``: the actor's and the Q networks' layers run under autocast, their
outputs cast to float32 (``runtime.precision.mixed``) before the targets and losses, as the
networks' own ``forward`` does on TorchRL's path."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import torch
from torch.nn import functional as F

from rlexp.runtime.precision import mixed

_FUNCTIONS: dict[str, Callable[[torch.Tensor], torch.Tensor]] = {
    "relu": torch.relu,
    "tanh": torch.tanh,
    "elu": F.elu,
    "gelu": F.gelu,
    "silu": F.silu,
    "swish": F.silu,
}
_LOG_SQRT_2PI = 0.5 * math.log(2 * math.pi)


def _mlp(layers: list[tuple[torch.Tensor, torch.Tensor]], act, x: torch.Tensor) -> torch.Tensor:
    for i, (w, b) in enumerate(layers):
        x = F.linear(x, w, b)
        if i < len(layers) - 1:
            x = act(x)
    return x


def _qs(layers: list[tuple[torch.Tensor, torch.Tensor]], act, x: torch.Tensor) -> torch.Tensor:
    """Stacked Q networks on ``x`` [B, d] (or [n, B, d]) -> [n, B]."""
    for i, (w, b) in enumerate(layers):  # w [n, out, in], b [n, out]
        x = torch.baddbmm(b.unsqueeze(1), x.expand(w.shape[0], *x.shape[-2:]), w.transpose(1, 2))
        if i < len(layers) - 1:
            x = act(x)
    return x.squeeze(-1)


def _networks(policy: Any) -> tuple[Callable, Callable]:
    """``_mlp`` and ``_qs`` at the policy's precision (``trainer.precision``)."""
    net = policy.actor_net
    return (
        mixed(_mlp, net.autocast_dtype, net.autocast_device),
        mixed(_qs, net.autocast_dtype, net.autocast_device),
    )


class FusedSAC:
    """The step of ``algorithms.sac.SAC`` on its own parameters and optimisers."""

    def __init__(self, algo: Any, compiled: bool) -> None:
        policy, loss = algo.policy, algo.loss
        self.algo = algo
        mlp = policy.actor_net.mlp
        self.actor = [(m.weight, m.bias) for m in mlp if isinstance(m, torch.nn.Linear)]
        self.actor_act = _FUNCTIONS[policy.cfg.actor.activation]
        self.q_act = _FUNCTIONS[policy.cfg.critic.activation]
        self._mlp, self._qs = _networks(policy)
        qp = loss.qvalue_network_params.flatten_keys(".")
        tq = loss.target_qvalue_network_params.flatten_keys(".")
        n_layers = len([k for k in qp.keys() if k.endswith(".weight")])
        names = [
            (f"module.mlp.{2 * i}.weight", f"module.mlp.{2 * i}.bias") for i in range(n_layers)
        ]
        self.q = [(qp[w], qp[b]) for w, b in names]
        self.target = [(tq[w], tq[b]) for w, b in names]
        self.target_flat = [t for pair in self.target for t in pair]
        self.q_flat = [t for pair in self.q for t in pair]
        self.normalizer = policy.normalizer
        self.actor_index = policy.actor_net.inputs.index
        self.q_index = policy.make_q().module.inputs.index
        self.low, self.high = policy.action_low, policy.action_high
        self.log_half_range = torch.log((self.high - self.low) / 2).sum()
        self.min_log_std = policy.actor_net.min_log_std
        self.max_log_std = policy.actor_net.max_log_std
        self.compiled = compiled
        fn = self._losses
        self._fn = torch.compile(fn, dynamic=False) if compiled else fn

    def _features(self, obs: torch.Tensor, index: torch.Tensor | None) -> torch.Tensor:
        x = self.normalizer(obs)
        return x if index is None else x.index_select(-1, index)

    def _policy(self, obs: torch.Tensor, eps: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """A reparameterised action of the tanh-squashed Gaussian and its log-density."""
        loc, log_std = self._mlp(
            self.actor, self.actor_act, self._features(obs, self.actor_index)
        ).chunk(2, -1)
        log_std = log_std.clamp(self.min_log_std, self.max_log_std)
        u = loc + log_std.exp() * eps
        t = torch.tanh(u)
        # tanh's log-Jacobian as TorchRL's TanhTransform: 2 * (log 2 - u - softplus(-2u))
        log_det = 2.0 * (math.log(2.0) - u - F.softplus(-2.0 * u))
        log_prob = (-0.5 * eps.pow(2) - log_std - _LOG_SQRT_2PI - log_det).sum(-1)
        action = self.low + (self.high - self.low) * (t + 1.0) * 0.5
        return action, log_prob - self.log_half_range

    def _losses(self, obs, action, reward, next_obs, terminated, eps_next, eps_now, log_alpha,
                target_entropy, gamma):  # fmt: skip
        alpha = log_alpha.detach().exp()
        with torch.no_grad():
            a_next, logp_next = self._policy(next_obs, eps_next)
            x_next = torch.cat([self._features(next_obs, self.q_index), a_next], -1)
            q_next = self._qs(self.target, self.q_act, x_next).min(0).values - alpha * logp_next
            y = reward + gamma * (1.0 - terminated) * q_next
        x = torch.cat([self._features(obs, self.q_index), action], -1)
        q_loss = (self._qs(self.q, self.q_act, x) - y).pow(2).mean(1).sum()
        a_new, logp = self._policy(obs, eps_now)
        frozen = [(w.detach(), b.detach()) for w, b in self.q]
        x_new = torch.cat([self._features(obs, self.q_index), a_new], -1)
        actor_loss = (alpha * logp - self._qs(frozen, self.q_act, x_new).min(0).values).mean()
        alpha_loss = (-log_alpha * (logp.detach() + target_entropy)).mean()
        return q_loss, actor_loss, alpha_loss, alpha, -logp.detach().mean()

    def step(self, batch) -> dict[str, torch.Tensor]:
        algo = self.algo
        obs, action = batch["observation"], batch["action"]
        nxt = batch["next"]
        reward = nxt["reward"].reshape(-1)
        terminated = nxt["terminated"].reshape(-1).to(reward.dtype)
        steps = batch.get("steps_to_next_obs", None)  # n-step: gamma ** steps per transition
        gamma = (
            algo.cfg.gamma
            if steps is None
            else algo.cfg.gamma ** steps.reshape(-1).to(reward.dtype)
        )
        shape = (obs.shape[0], self.low.shape[-1])
        eps_next = torch.randn(shape, device=obs.device)  # SACLoss's order: the target's first
        eps_now = torch.randn(shape, device=obs.device)
        log_alpha = algo.loss.log_alpha
        q_loss, actor_loss, alpha_loss, alpha, entropy = self._fn(
            obs, action, reward, nxt["observation"], terminated, eps_next, eps_now, log_alpha,
            algo.loss.target_entropy, gamma,
        )  # fmt: skip
        return algo._apply_losses(q_loss, actor_loss, alpha_loss, alpha, entropy)


def _stacked(params: Any, mlp: torch.nn.Sequential) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """The (weight, bias) pairs of a loss's parameter TensorDict for the Linear layers of ``mlp``
    (the same names: ``...mlp.<i>.weight``), in order."""
    flat = params.flatten_keys(".")
    out = []
    for i, m in enumerate(mlp):
        if isinstance(m, torch.nn.Linear):
            w = next(k for k in flat.keys() if k.endswith(f"mlp.{i}.weight"))
            out.append((flat[w], flat[w[: -len("weight")] + "bias"]))
    return out


class FusedTD3:
    """The step of ``algorithms.td3.TD3`` (TorchRL's ``TD3Loss`` written out, its smoothing noise
    drawn first as there): the critics' loss and Adam step; every ``policy_delay``-th step the
    actor's loss on the updated critics, its Adam step and the soft target update."""

    def __init__(self, algo: Any) -> None:
        policy, loss = algo.policy, algo.loss
        self.algo = algo
        mlp = policy.actor_net.mlp
        self.actor = [(m.weight, m.bias) for m in mlp if isinstance(m, torch.nn.Linear)]
        self.target_actor = _stacked(loss.target_actor_network_params, mlp)
        self.actor_act = _FUNCTIONS[policy.cfg.actor.activation]
        self.q_act = _FUNCTIONS[policy.cfg.critic.activation]
        self._mlp, self._qs = _networks(policy)
        q_mlp = policy.make_q().module.mlp
        self.q = _stacked(loss.qvalue_network_params, q_mlp)
        self.target_q = _stacked(loss.target_qvalue_network_params, q_mlp)
        self.sources = [t for pair in self.actor + self.q for t in pair]
        self.targets = [t for pair in self.target_actor + self.target_q for t in pair]
        self.normalizer = policy.normalizer
        self.actor_index = policy.actor_net.inputs.index
        self.q_index = policy.make_q().module.inputs.index
        self.low, self.high = policy.action_low, policy.action_high

    def _features(self, obs: torch.Tensor, index: torch.Tensor | None) -> torch.Tensor:
        x = self.normalizer(obs)
        return x if index is None else x.index_select(-1, index)

    def _mu(self, layers, obs: torch.Tensor) -> torch.Tensor:
        u = self._mlp(layers, self.actor_act, self._features(obs, self.actor_index))
        return self.low + (self.high - self.low) * (torch.tanh(u) + 1.0) * 0.5

    def step(self, batch) -> dict[str, torch.Tensor]:
        algo = self.algo
        obs, action, nxt = batch["observation"], batch["action"], batch["next"]
        reward = nxt["reward"].reshape(-1)
        terminated = nxt["terminated"].reshape(-1).to(reward.dtype)
        steps = batch.get("steps_to_next_obs", None)
        gamma = (
            algo.cfg.gamma
            if steps is None
            else algo.cfg.gamma ** steps.reshape(-1).to(reward.dtype)
        )
        loss = algo.loss
        noise = (torch.randn_like(action) * loss.policy_noise).clamp(
            -loss.noise_clip, loss.noise_clip
        )
        with torch.no_grad():
            next_obs = nxt["observation"]
            a_next = (self._mu(self.target_actor, next_obs) + noise).clamp(self.low, self.high)
            x_next = torch.cat([self._features(next_obs, self.q_index), a_next], -1)
            y = (
                reward
                + gamma
                * (1.0 - terminated)
                * self._qs(self.target_q, self.q_act, x_next).min(0).values
            )
        x = torch.cat([self._features(obs, self.q_index), action], -1)
        q_loss = (self._qs(self.q, self.q_act, x) - y).pow(2).mean(1).sum()
        algo._step(algo.q_optimizer, algo.q_params, q_loss, "qvalue")
        out = {"loss/qvalue": q_loss.detach()}
        if (algo.gradient_steps + 1) % algo.cfg.policy_delay == 0:
            frozen = [(w[:1].detach(), b[:1].detach()) for w, b in self.q]  # Q_1
            x_pi = torch.cat([self._features(obs, self.q_index), self._mu(self.actor, obs)], -1)
            actor_loss = -self._qs(frozen, self.q_act, x_pi)[0].mean()
            algo._step(algo.actor_optimizer, algo.actor_params, actor_loss, "actor")
            with torch.no_grad():
                torch._foreach_lerp_(self.targets, self.sources, float(algo.cfg.tau))
            out["loss/actor"] = actor_loss.detach()
        return out
