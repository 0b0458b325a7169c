"""Recurrent PPO (policy.memory): the collector's stored states and episode starts, the sequence
cutting, the recurrent values for GAE and the sequence loss, each against a hand-written loop over
the steps with the LSTM / GRU equations written out (no nn.LSTM / nn.GRU call in the reference)."""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict
from torch import distributions as D
from torch.nn import functional as F
from torchrl.data import Bounded
from torchrl.data import MultiCategorical as MultiCategoricalSpec

from rlexp.algorithms import make_algorithm
from rlexp.algorithms.recurrent_ppo import RecurrentPPO, cut_sequences
from rlexp.config.schema import AlgorithmConfig, EnvConfig, MemoryConfig, PolicyConfig
from rlexp.envs.factory import make_env
from rlexp.policies.actor_critic import make_policy, policy_for_env
from rlexp.training.collector import RolloutCollector


# -- the reference: recurrent cells and MLPs written out ----------------------------------------------
def cell(rnn, layer: int, x, h, c):
    """One step of layer ``layer`` of ``rnn`` (torch's weights, the textbook equations)."""
    w_ih, w_hh = getattr(rnn, f"weight_ih_l{layer}"), getattr(rnn, f"weight_hh_l{layer}")
    b_ih, b_hh = getattr(rnn, f"bias_ih_l{layer}"), getattr(rnn, f"bias_hh_l{layer}")
    gi, gh = x @ w_ih.T + b_ih, h @ w_hh.T + b_hh
    if isinstance(rnn, torch.nn.LSTM):
        i, f, g, o = (gi + gh).chunk(4, -1)
        c = torch.sigmoid(f) * c + torch.sigmoid(i) * torch.tanh(g)
        return torch.sigmoid(o) * torch.tanh(c), c
    ri, zi, ni = gi.chunk(3, -1)
    rh, zh, nh = gh.chunk(3, -1)
    r, z = torch.sigmoid(ri + rh), torch.sigmoid(zi + zh)
    n = torch.tanh(ni + r * nh)
    return (1 - z) * n + z * h, None


def core_step(core, x, h, c):
    """All layers, one step: x [in], h / c [layers, H] -> (y [H], h', c')."""
    hs, cs = [], []
    for layer in range(core.num_layers):
        x, c_new = cell(core.rnn, layer, x, h[layer], None if c is None else c[layer])
        hs.append(x)
        cs.append(c_new)
    return x, torch.stack(hs), (None if c is None else torch.stack(cs))


def mlp(seq, x):
    for m in seq:
        x = x @ m.weight.T + m.bias if isinstance(m, torch.nn.Linear) else torch.tanh(x)
    return x


def state_of(stored: dict, who: str, lstm: bool):
    return stored[f"{who}_h"], (stored[f"{who}_c"] if lstm else None)


# -- fixtures ---------------------------------------------------------------------------------------
def _policy(kind: str, shared: bool = False, categorical: bool = True, seed: int = 3):
    torch.manual_seed(seed)
    cfg = PolicyConfig(
        memory=MemoryConfig(type=kind, hidden_size=5, num_layers=2, shared=shared),
        init_log_std=-0.3,
    )
    cfg.actor.hidden_sizes = [6]
    cfg.critic.hidden_sizes = [7]
    if categorical:
        spec = MultiCategoricalSpec(nvec=[3], shape=(1,))
        return make_policy(cfg, 3, 1, spec, normalize_observations=False, nvec=[3])
    return make_policy(cfg, 3, 2, Bounded(-1, 1, shape=(2,)), normalize_observations=False)


#: An env's episode starts in a rollout of 7 steps: env 0 ends an episode after step 1 (so step 2
#: starts one, mid-sequence for sequence_length 3) and after step 5; env 1 after step 3.
IS_INIT = torch.tensor(
    [
        [False, False, True, False, False, False, True],
        [True, False, False, False, True, False, False],
    ]
)


@torch.no_grad()
def _rollout(policy, categorical: bool) -> TensorDict:
    """A made-up rollout [2, 7] whose stored states are what the collector would have stored:
    carried from a random starting state, zeroed where an episode starts."""
    g = torch.Generator().manual_seed(11)
    envs, steps = IS_INIT.shape
    obs = torch.randn(envs, steps, 3, generator=g)
    state = {
        k: torch.randn(v.shape, generator=g) * 0.5 for k, v in policy.initial_state(envs).items()
    }
    stored = {k: [] for k in state}
    lstm = policy.memory_cfg.type == "lstm"
    for t in range(steps):
        for k in state:
            state[k] = torch.where(IS_INIT[:, t].reshape(-1, 1, 1), 0.0, state[k])
            stored[k].append(state[k])
        for who in ("actor", "critic"):
            if f"{who}_h" not in state:
                continue
            net = policy.actor_net if who == "actor" else policy.critic_net
            core = policy.actor_core if who == "actor" else policy.critic_core
            for e in range(envs):
                _, h, c = core_step(
                    core,
                    net.features(obs[e, t]),
                    state[f"{who}_h"][e],
                    (state[f"{who}_c"][e] if lstm else None),
                )
                state[f"{who}_h"] = state[f"{who}_h"].clone()
                state[f"{who}_h"][e] = h
                if lstm:
                    state[f"{who}_c"] = state[f"{who}_c"].clone()
                    state[f"{who}_c"][e] = c
    action = (
        torch.randint(0, 3, (envs, steps, 1), generator=g)
        if categorical
        else torch.randn(envs, steps, 2, generator=g)
    )
    terminated = torch.zeros(envs, steps, 1, dtype=torch.bool)
    truncated = torch.zeros(envs, steps, 1, dtype=torch.bool)
    terminated[0, 1] = truncated[0, 5] = terminated[1, 3] = True
    done = terminated | truncated
    # within an episode the next observation is the following step's; at an end, the final one
    next_obs = torch.randn(envs, steps, 3, generator=g)
    follows = torch.cat([~done[:, :-1, 0], torch.zeros(envs, 1, dtype=torch.bool)], 1)
    next_obs[:, :-1][follows[:, :-1]] = obs[:, 1:][follows[:, :-1]]
    return TensorDict(
        {
            "observation": obs,
            "action": action,
            "action_log_prob": torch.randn(envs, steps, generator=g) * 0.1 - 1.0,
            "advantage": torch.randn(envs, steps, 1, generator=g),
            "value_target": torch.randn(envs, steps, 1, generator=g),
            "state_value": torch.randn(envs, steps, 1, generator=g),
            "is_init": IS_INIT.unsqueeze(-1),
            "recurrent_state": TensorDict(
                {k: torch.stack(v, 1) for k, v in stored.items()}, [envs, steps]
            ),
            "next": {
                "observation": next_obs,
                "reward": torch.randn(envs, steps, 1, generator=g),
                "terminated": terminated,
                "truncated": truncated,
                "done": done,
            },
        },
        batch_size=[envs, steps],
    )


def test_sequences_are_cut_per_env_in_time_order_and_the_last_one_padded():
    policy = _policy("lstm")
    batch = _rollout(policy, True)
    seqs, starts = cut_sequences(batch, 3)
    # 7 steps in sequences of 3: [0, 1, 2], [3, 4, 5], [6, pad, pad] per env
    assert seqs.shape == torch.Size([6, 3])
    assert seqs["valid"].tolist() == [[True] * 3, [True] * 3, [True, False, False]] * 2
    for s, (e, first) in enumerate([(0, 0), (0, 3), (0, 6), (1, 0), (1, 3), (1, 6)]):
        n = min(3, 7 - first)
        assert torch.equal(seqs["observation"][s, :n], batch["observation"][e, first : first + n])
        assert torch.equal(seqs["is_init"][s, :n], batch["is_init"][e, first : first + n])
        assert not seqs["is_init"][s, n:].any() and not seqs["observation"][s, n:].any()
        for name, start in starts.items():
            assert torch.equal(start[s], batch["recurrent_state", name][e, first])


@pytest.mark.parametrize("kind", ["lstm", "gru"])
@pytest.mark.parametrize("shared", [False, True], ids=["own-cores", "shared"])
def test_sequence_outputs_reset_the_state_where_an_episode_starts(kind, shared):
    policy = _policy(kind, shared)
    batch = _rollout(policy, True)
    seqs, starts = cut_sequences(batch, 3)
    params, value = policy.sequence_outputs(
        seqs["observation"], starts, seqs["is_init"].squeeze(-1)
    )
    lstm = kind == "lstm"
    for s in range(seqs.shape[0]):
        ah, ac = state_of({k: v[s] for k, v in starts.items()}, "actor", lstm)
        if shared:
            ch, cc = ah, ac
        else:
            ch, cc = state_of({k: v[s] for k, v in starts.items()}, "critic", lstm)
        for t in range(3):
            if seqs["is_init"][s, t]:
                ah, ch = torch.zeros_like(ah), torch.zeros_like(ch)
                ac = None if ac is None else torch.zeros_like(ac)
                cc = None if cc is None else torch.zeros_like(cc)
            x = seqs["observation"][s, t]
            y, ah, ac = core_step(policy.actor_core, x, ah, ac)
            if shared:
                cy = y
            else:
                cy, ch, cc = core_step(policy.critic_core, x, ch, cc)
            torch.testing.assert_close(
                params[0][s, t], mlp(policy.actor_net.mlp, y), atol=1e-5, rtol=1e-5
            )
            torch.testing.assert_close(
                value[s, t], mlp(policy.critic_net.mlp, cy), atol=1e-5, rtol=1e-5
            )


def _algo(policy, **kw) -> RecurrentPPO:
    cfg = AlgorithmConfig(
        sequence_length=3,
        clip_epsilon=0.15,
        entropy_coeff=0.013,
        critic_coeff=0.7,
        loss_critic_type="smooth_l1",
        clip_value=0.25,
        gamma=0.93,
        lmbda=0.81,
        normalize_rewards=False,
        clip_rewards=None,
        anneal_lr=False,
        compile="false",
        **kw,
    )
    algo = make_algorithm(cfg, policy, total_iterations=3, nan_guard=True)
    assert isinstance(algo, RecurrentPPO)
    return algo


def _reference_loss(policy, batch, categorical: bool, cfg) -> torch.Tensor:
    """The PPO loss of every sequence of 3 steps of ``batch`` (one minibatch), step by step."""
    lstm = policy.memory_cfg.type == "lstm"
    logp, ent, val, rows = [], [], [], []
    envs, steps = batch.shape
    for e in range(envs):
        for first in range(0, steps, 3):
            start = {k: batch["recurrent_state", k][e, first] for k in policy.state_names}
            ah, ac = state_of(start, "actor", lstm)
            ch, cc = state_of(start, "critic", lstm)
            for t in range(first, min(first + 3, steps)):
                if batch["is_init"][e, t]:
                    ah, ch = ah * 0, ch * 0
                    ac, cc = (ac * 0, cc * 0) if lstm else (None, None)
                x = batch["observation"][e, t]
                y, ah, ac = core_step(policy.actor_core, x, ah, ac)
                cy, ch, cc = core_step(policy.critic_core, x, ch, cc)
                out = mlp(policy.actor_net.mlp, y)
                if categorical:
                    dist = D.Categorical(logits=out)
                    logp.append(dist.log_prob(batch["action"][e, t, 0]))
                    ent.append(dist.entropy())
                else:
                    std = policy.actor_net.log_std.clamp(-5.0, 2.0).exp()
                    dist = D.Normal(out, std)
                    logp.append(dist.log_prob(batch["action"][e, t]).sum())
                    ent.append(dist.entropy().sum())
                val.append(mlp(policy.critic_net.mlp, cy)[0])
                rows.append((e, t))
    logp, ent, val = torch.stack(logp), torch.stack(ent), torch.stack(val)
    idx = tuple(zip(*rows, strict=True))
    adv = batch["advantage"][idx].squeeze(-1)
    adv = (adv - adv.mean()) / adv.std()
    ratio = torch.exp(logp - batch["action_log_prob"][idx])
    eps = cfg.clip_epsilon
    surrogate = torch.min(ratio * adv, ratio.clamp(1 - eps, 1 + eps) * adv)
    target, old = batch["value_target"][idx].squeeze(-1), batch["state_value"][idx].squeeze(-1)
    clipped = old + (val - old).clamp(-cfg.clip_value, cfg.clip_value)
    value_loss = torch.max(
        F.smooth_l1_loss(val, target, reduction="none"),
        F.smooth_l1_loss(clipped, target, reduction="none"),
    )
    return -surrogate.mean() + cfg.critic_coeff * value_loss.mean() - cfg.entropy_coeff * ent.mean()


@pytest.mark.parametrize(
    "kind,categorical",
    [("lstm", True), ("lstm", False), ("gru", True)],
    ids=["lstm-discrete", "lstm-box", "gru-discrete"],
)
def test_the_sequence_loss_and_its_gradients_equal_a_plain_torch_ppo(kind, categorical):
    policy = _policy(kind, categorical=categorical)
    algo = _algo(policy)
    batch = _rollout(policy, categorical)
    seqs, starts = cut_sequences(batch, 3)
    total, stats = algo.sequence_loss(seqs, starts)
    grads = torch.autograd.grad(total, algo.params)
    expected = _reference_loss(policy, batch, categorical, algo.cfg)
    want = torch.autograd.grad(expected, algo.params)
    torch.testing.assert_close(total, expected, atol=1e-5, rtol=1e-5)
    for name, g, w in zip(algo.param_names, grads, want, strict=True):
        torch.testing.assert_close(g, w, atol=1e-5, rtol=1e-4, msg=f"gradient of {name}")
    assert float(stats["clip_fraction"]) > 0  # the clipped branch is exercised


@pytest.mark.parametrize("kind", ["lstm", "gru"])
def test_gae_values_carry_the_critic_state_and_bootstrap_a_truncation_from_the_state_after_it(kind):
    policy = _policy(kind)
    algo = _algo(policy)
    batch = _rollout(policy, True)
    algo.compute_advantages(batch)
    lstm = kind == "lstm"
    gamma, lmbda = 0.93, 0.81
    for e in range(2):
        h, c = state_of(
            {k: batch["recurrent_state", k][e, 0] for k in policy.state_names}, "critic", lstm
        )
        values, next_values = [], []
        for t in range(7):
            if batch["is_init"][e, t]:
                h, c = h * 0, (c * 0 if lstm else None)
            y, h, c = core_step(policy.critic_core, batch["observation"][e, t], h, c)
            values.append(mlp(policy.critic_net.mlp, y)[0])
            # V(s'_t) from the state after step t: the episode's end too (a truncation's bootstrap)
            y_next, _, _ = core_step(policy.critic_core, batch["next", "observation"][e, t], h, c)
            next_values.append(mlp(policy.critic_net.mlp, y_next)[0])
        values, next_values = torch.stack(values), torch.stack(next_values)
        ended = batch["next", "done"][e].squeeze(-1)
        torch.testing.assert_close(
            batch["state_value"][e].squeeze(-1), values, atol=1e-5, rtol=1e-5
        )
        # within an episode V(s'_t) is V(s_t+1); at an end, the critic's step from the state after t
        torch.testing.assert_close(
            batch["next", "state_value"][e].squeeze(-1), next_values, atol=1e-5, rtol=1e-5
        )
        reward = batch["next", "reward"][e].squeeze(-1)
        term = batch["next", "terminated"][e].squeeze(-1).float()
        adv, running = torch.zeros(7), 0.0
        for t in reversed(range(7)):
            delta = reward[t] + gamma * next_values[t] * (1 - term[t]) - values[t]
            running = delta + gamma * lmbda * (1 - ended[t].float()) * running
            adv[t] = running
        torch.testing.assert_close(batch["advantage"][e].squeeze(-1), adv, atol=1e-5, rtol=1e-5)


def test_the_collector_stores_the_state_before_each_step_and_zeroes_it_where_an_episode_ended():
    """CartPole with a 12-step limit: episodes end by falling (terminated) and by the limit
    (truncated) inside the rollouts; every stored state, episode start and log-probability is the
    hand-written loop's, and the state carries over from one rollout to the next."""
    torch.manual_seed(0)
    env_cfg = EnvConfig(
        name="CartPole-v1",
        backend="gymnasium",
        num_envs=2,
        max_episode_steps=12,
        normalize_observations=False,
    )
    env = make_env(env_cfg, 2, seed=4)
    cfg = PolicyConfig(memory=MemoryConfig(type="lstm", hidden_size=4, num_layers=2))
    cfg.actor.hidden_sizes = [5]
    policy = policy_for_env(cfg, env_cfg, env)
    steps = 30
    col = RolloutCollector(
        env, policy.sampling_policy(), frames_per_batch=2 * steps, total_frames=-1,
        trust_policy=True, auto_register_policy_transforms=False,
    )  # fmt: skip
    try:
        rollouts = iter(col)
        first, second = next(rollouts), next(rollouts)
    finally:
        col.shutdown()
    nxt = first["next"]
    assert nxt["terminated"].any() and nxt["truncated"].any(), "both kinds of end must occur"
    for batch in (first, second):
        for e in range(2):
            for t in range(steps):
                stored = {k: batch["recurrent_state", k][e, t] for k in policy.state_names}
                h, c = state_of(stored, "actor", True)
                x = batch["observation"][e, t]
                y, h1, c1 = core_step(policy.actor_core, x, h, c)
                logp = D.Categorical(logits=mlp(policy.actor_net.mlp, y)).log_prob(
                    batch["action"][e, t, 0]
                )
                torch.testing.assert_close(
                    batch["action_log_prob"][e, t], logp, atol=1e-5, rtol=1e-5
                )
                if t + 1 < steps:
                    ended = bool(batch["next", "done"][e, t])
                    assert bool(batch["is_init"][e, t + 1]) == ended
                    after = batch["recurrent_state", "actor_h"][e, t + 1]
                    torch.testing.assert_close(
                        after, torch.zeros_like(h1) if ended else h1, atol=1e-6, rtol=1e-5
                    )
    assert first["is_init"][:, 0].all()  # the first rollout starts every episode
    # the second rollout starts from the first one's last state (zeros where that step ended)
    for e in range(2):
        stored = {k: first["recurrent_state", k][e, -1] for k in policy.state_names}
        _, h1, _ = core_step(
            policy.actor_core, first["observation"][e, -1], *state_of(stored, "actor", True)
        )
        ended = bool(first["next", "done"][e, -1])
        assert bool(second["is_init"][e, 0]) == ended
        torch.testing.assert_close(
            second["recurrent_state", "actor_h"][e, 0],
            torch.zeros_like(h1) if ended else h1,
            atol=1e-6,
            rtol=1e-5,
        )


def test_an_update_trains_sequences_and_leaves_the_mlp_path_alone():
    policy = _policy("gru", categorical=False)
    algo = _algo(policy, num_epochs=2, mini_batch_size=6)
    batch = _rollout(policy, False)
    before = [p.detach().clone() for p in algo.params]
    out = algo.update(batch)
    assert all(math.isfinite(v) for v in out.values())
    assert {"loss/policy", "loss/value", "loss/entropy", "loss/grad_norm"} <= set(out)
    # 6 sequences, 2 per minibatch (6 steps // 3), 2 epochs: 6 optimiser steps on every parameter
    assert all(not torch.equal(a, b) for a, b in zip(before, algo.params, strict=True))
    assert int(algo.optimizer.state[algo.params[0]]["step"]) == 6
