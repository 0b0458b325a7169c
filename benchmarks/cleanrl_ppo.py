"""PPO in plain PyTorch, in the style of CleanRL's ``ppo_continuous_action.py``: the baseline that
``benchmarks/ppo_throughput.py`` times rlexp against. One file, no framework: a Gymnasium vector env,
an actor-critic of two MLPs, a rollout buffer of plain tensors, GAE, the clipped-surrogate epochs.

The maths is rlexp's (and SB3's): GAE(gamma, lambda) whose trace is cut at every episode end, with
truncated episodes bootstrapped from V(true final observation) (added to the reward, as SB3 does);
clipped surrogate, squared-error value loss, entropy bonus, per-minibatch advantage normalisation,
global grad-norm clipping, Adam with eps 1e-5; an optional running mean/std observation normaliser
updated once per rollout after the update (as rlexp's). The env must auto-reset in the same step
(Gymnasium ``AutoresetMode.SAME_STEP``) and report ``final_obs`` / ``_final_obs`` in its infos.

    PYTHONPATH=src .venv/bin/python benchmarks/cleanrl_ppo.py --env HalfCheetah-v5 --total-steps 20480
"""

from __future__ import annotations

import argparse
import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn


@dataclass
class Args:
    steps_per_env: int = 2048  # rollout length per env (CleanRL's num_steps)
    num_epochs: int = 10  # passes over each rollout (update_epochs)
    mini_batch_size: int = 64  # samples per gradient step (batch_size // num_minibatches)
    lr: float = 3e-4  # Adam learning rate (constant)
    adam_eps: float = 1e-5  # Adam epsilon, as in CleanRL / SB3
    gamma: float = 0.99  # discount
    lmbda: float = 0.95  # GAE lambda
    clip_epsilon: float = 0.2  # surrogate clipping
    entropy_coeff: float = 0.0  # entropy bonus weight
    critic_coeff: float = 0.5  # value-loss weight
    max_grad_norm: float = 0.5  # global gradient-norm clip
    hidden_sizes: tuple[int, ...] = (64, 64)  # actor and critic MLP widths
    activation: str = "tanh"  # tanh | relu
    normalize_observations: bool = True  # running mean/std of observations, clipped to +-10
    seed: int = 0


ACTIVATIONS = {"tanh": nn.Tanh, "relu": nn.ReLU}


def mlp(
    in_dim: int, out_dim: int, hidden: tuple[int, ...], act: str, last_gain: float
) -> nn.Sequential:
    """Linear/activation stack with orthogonal init (sqrt 2 hidden, ``last_gain`` output)."""
    layers: list[nn.Module] = []
    last = in_dim
    for width in hidden:
        lin = nn.Linear(last, width)
        nn.init.orthogonal_(lin.weight, math.sqrt(2))
        nn.init.zeros_(lin.bias)
        layers += [lin, ACTIVATIONS[act]()]
        last = width
    out = nn.Linear(last, out_dim)
    nn.init.orthogonal_(out.weight, last_gain)
    nn.init.zeros_(out.bias)
    return nn.Sequential(*layers, out)


class Agent(nn.Module):
    """Gaussian actor with a state-independent log-std, separate critic, shared obs normaliser."""

    def __init__(self, obs_dim: int, act_dim: int, args: Args) -> None:
        super().__init__()
        self.actor = mlp(obs_dim, act_dim, args.hidden_sizes, args.activation, 0.01)
        self.critic = mlp(obs_dim, 1, args.hidden_sizes, args.activation, 1.0)
        self.log_std = nn.Parameter(torch.zeros(act_dim))
        self.normalize = args.normalize_observations
        self.register_buffer("mean", torch.zeros(obs_dim, dtype=torch.float64))
        self.register_buffer("var", torch.ones(obs_dim, dtype=torch.float64))
        self.register_buffer("count", torch.zeros((), dtype=torch.float64))
        self.register_buffer("shift", torch.zeros(obs_dim))
        self.register_buffer("scale", torch.ones(obs_dim))

    def norm(self, obs: torch.Tensor) -> torch.Tensor:
        return torch.clamp(obs * self.scale + self.shift, -10.0, 10.0) if self.normalize else obs

    @torch.no_grad()
    def update_normalizer(self, obs: torch.Tensor) -> None:
        """Fold a rollout's observations into the running mean/variance (parallel Welford)."""
        if not self.normalize:
            return
        x = obs.reshape(-1, obs.shape[-1]).double()
        n = x.shape[0]
        b_mean, b_var = x.mean(0), x.var(0, unbiased=False)
        delta, total = b_mean - self.mean, self.count + n
        self.var.copy_(
            (self.var * self.count + b_var * n + delta**2 * self.count * n / total) / total
        )
        self.mean.add_(delta * n / total)
        self.count.fill_(total)
        std = torch.sqrt(self.var + 1e-8)
        self.scale.copy_((1 / std).float())
        self.shift.copy_((-self.mean / std).float())

    def value(self, obs: torch.Tensor) -> torch.Tensor:
        return self.critic(self.norm(obs)).squeeze(-1)

    def dist(self, obs: torch.Tensor) -> torch.distributions.Normal:
        return torch.distributions.Normal(self.actor(self.norm(obs)), self.log_std.exp())


def train(
    envs,
    args: Args,
    total_steps: int,
    on_iteration: Callable[[int, dict[str, float]], None] | None = None,
) -> Agent:
    """Train on a Gymnasium vector env (``AutoresetMode.SAME_STEP``) for ``total_steps`` env steps."""
    torch.manual_seed(args.seed)
    n = envs.num_envs
    obs_dim = int(np.prod(envs.single_observation_space.shape))
    act_dim = int(np.prod(envs.single_action_space.shape))
    low = envs.single_action_space.low
    high = envs.single_action_space.high
    agent = Agent(obs_dim, act_dim, args)
    optimizer = torch.optim.Adam(agent.parameters(), lr=args.lr, eps=args.adam_eps)
    T = args.steps_per_env
    batch = T * n
    mb = min(args.mini_batch_size, batch)

    # the rollout buffer, [T, num_envs, ...]
    obs_buf = torch.zeros(T, n, obs_dim)
    act_buf = torch.zeros(T, n, act_dim)
    logp_buf = torch.zeros(T, n)
    rew_buf = torch.zeros(T, n)
    done_buf = torch.zeros(T, n)
    val_buf = torch.zeros(T, n)

    next_obs = torch.as_tensor(envs.reset(seed=args.seed)[0], dtype=torch.float32)
    iterations = -(-total_steps // batch)
    for iteration in range(iterations):
        # -- rollout: one policy forward per step, the env steps all copies
        for t in range(T):
            obs_buf[t] = next_obs
            with torch.no_grad():
                dist = agent.dist(next_obs)
                action = dist.sample()
                logp_buf[t] = dist.log_prob(action).sum(-1)
                val_buf[t] = agent.value(next_obs)
            act_buf[t] = action
            obs, reward, term, trunc, infos = envs.step(np.clip(action.numpy(), low, high))
            reward = torch.as_tensor(reward, dtype=torch.float32)
            # Truncated (not terminated) episodes: bootstrap from V(true final observation).
            ids = np.flatnonzero(np.logical_and(trunc, np.logical_not(term)))
            if ids.size:
                final = np.stack([infos["final_obs"][i] for i in ids]).astype(np.float32)
                with torch.no_grad():
                    reward[ids] += args.gamma * agent.value(torch.from_numpy(final))
            rew_buf[t] = reward
            done_buf[t] = torch.as_tensor(np.logical_or(term, trunc), dtype=torch.float32)
            next_obs = torch.as_tensor(obs, dtype=torch.float32)

        # -- GAE: the trace is cut where an episode ended (done_buf[t] refers to step t's outcome)
        with torch.no_grad():
            next_value = agent.value(next_obs)
            adv = torch.zeros(T, n)
            last = torch.zeros(n)
            for t in reversed(range(T)):
                nonterminal = 1.0 - done_buf[t]
                v_next = next_value if t == T - 1 else val_buf[t + 1]
                delta = rew_buf[t] + args.gamma * v_next * nonterminal - val_buf[t]
                last = delta + args.gamma * args.lmbda * nonterminal * last
                adv[t] = last
            returns = adv + val_buf

        # -- update: epochs x shuffled minibatches
        b_obs, b_act = obs_buf.reshape(batch, obs_dim), act_buf.reshape(batch, act_dim)
        b_logp, b_adv, b_ret = logp_buf.reshape(-1), adv.reshape(-1), returns.reshape(-1)
        stats = {k: torch.zeros(()) for k in ("loss/policy", "loss/value", "loss/entropy")}
        count = 0
        for _ in range(args.num_epochs):
            perm = torch.randperm(batch)
            for start in range(0, batch - mb + 1, mb):
                idx = perm[start : start + mb]
                dist = agent.dist(b_obs[idx])
                logp = dist.log_prob(b_act[idx]).sum(-1)
                ratio = (logp - b_logp[idx]).exp()
                a = b_adv[idx]
                a = (a - a.mean()) / (a.std() + 1e-8)  # per-minibatch normalisation
                pg_loss = torch.max(
                    -a * ratio, -a * ratio.clamp(1 - args.clip_epsilon, 1 + args.clip_epsilon)
                ).mean()
                v_loss = (agent.value(b_obs[idx]) - b_ret[idx]).pow(2).mean()
                entropy = dist.entropy().sum(-1).mean()
                loss = pg_loss + args.critic_coeff * v_loss - args.entropy_coeff * entropy
                optimizer.zero_grad(set_to_none=True)
                loss.backward()
                nn.utils.clip_grad_norm_(agent.parameters(), args.max_grad_norm)
                optimizer.step()
                stats["loss/policy"] += pg_loss.detach()
                stats["loss/value"] += v_loss.detach()
                stats["loss/entropy"] += entropy.detach()
                count += 1
        agent.update_normalizer(b_obs)
        if on_iteration is not None:
            on_iteration(iteration, {k: float(v) / max(count, 1) for k, v in stats.items()})
    return agent


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--env", default="HalfCheetah-v5")
    parser.add_argument("--num-envs", type=int, default=1)
    parser.add_argument("--total-steps", type=int, default=20480)
    parser.add_argument("--seed", type=int, default=0)
    cli = parser.parse_args()
    import gymnasium as gym

    torch.set_num_threads(1)
    envs = gym.vector.SyncVectorEnv(
        [lambda: gym.make(cli.env) for _ in range(cli.num_envs)],
        autoreset_mode=gym.vector.AutoresetMode.SAME_STEP,
    )
    start = time.perf_counter()

    def report(it: int, stats: dict[str, float]) -> None:
        steps = (it + 1) * Args.steps_per_env * cli.num_envs
        print(f"iteration {it}: {steps / (time.perf_counter() - start):.0f} steps/s {stats}")

    train(envs, Args(seed=cli.seed), cli.total_steps, report)


if __name__ == "__main__":
    main()
