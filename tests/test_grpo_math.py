"""GRPO: group advantages against numbers worked out by hand; a whole update against a plain-torch
GRPO; save -> load keeps the reference policy; the errors a bad setting gives."""

from __future__ import annotations

import copy
import math
from dataclasses import replace

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Bounded

from conftest import clipped_adam_step
from rlexp.algorithms import make_algorithm
from rlexp.algorithms.grpo import GRPO, group_advantages
from rlexp.algorithms.ppo import PPO, NonFiniteError
from rlexp.config.schema import ActorOnlyConfig, AlgorithmConfig, GRPOConfig, PolicyConfig
from rlexp.config.validate import ConfigError
from rlexp.policies.actor_critic import make_policy

# 4 envs, T = 4, gamma = 0.5. Env 0 terminates at t=1, env 1 is truncated at t=2, env 2 terminates
# at t=0 and is truncated at t=2 (two episode ends), env 3 runs on.
REWARD = torch.tensor(
    [
        [1.0, 2.0, 3.0, 4.0],
        [2.0, 0.0, 1.0, 2.0],
        [0.0, 1.0, 0.0, 1.0],
        [1.0, 1.0, 1.0, 1.0],
    ]
)
TERMINATED = torch.tensor(
    [[0, 1, 0, 0], [0, 0, 0, 0], [1, 0, 0, 0], [0, 0, 0, 0]], dtype=torch.bool
)
TRUNCATED = torch.tensor([[0, 0, 0, 0], [0, 0, 1, 0], [0, 0, 1, 0], [0, 0, 0, 0]], dtype=torch.bool)
# G_t = r_t + 0.5 G_t+1 (1 - done_t), G_4 = 0; a truncation cuts like a termination (no bootstrap):
#   env 0: G3 = 4, G2 = 3 + 2 = 5, G1 = 2 (done), G0 = 1 + 1 = 2
#   env 1: G3 = 2, G2 = 1 (done), G1 = 0 + 0.5 = 0.5, G0 = 2 + 0.25 = 2.25
#   env 2: G3 = 1, G2 = 0 (done), G1 = 1 + 0 = 1, G0 = 0 (done)
#   env 3: G3 = 1, G2 = 1.5, G1 = 1.75, G0 = 1.875
RETURNS = [
    [2.0, 2.0, 5.0, 4.0],
    [2.25, 0.5, 1.0, 2.0],
    [0.0, 1.0, 0.0, 1.0],
    [1.875, 1.75, 1.5, 1.0],
]
# Alive up to and including the first done.
MASK = [[1, 1, 0, 0], [1, 1, 1, 0], [1, 0, 0, 0], [1, 1, 1, 1]]


def _advantages(group_size: int, truncate: bool):
    return group_advantages(
        REWARD, TERMINATED | TRUNCATED, 0.5, group_size, 1e-8, truncate_at_first_done=truncate
    )


def test_group_advantages_truncated_at_the_first_done():
    returns, mask, adv = _advantages(group_size=2, truncate=True)
    assert returns.tolist() == RETURNS
    assert mask.tolist() == MASK
    # Group 0 (envs 0, 1). t0: 2 vs 2.25, mean 2.125, population std 0.125 -> -1, +1 (the sample
    # std would give -/+0.707). t1: 2 vs 0.5, mean 1.25, std 0.75 -> +1, -1. t2: env 1 alone
    # (env 0 ended at t1): its own mean, 0. t3: none alive.
    # Group 1 (envs 2, 3). t0: 0 vs 1.875 -> -1, +1. t1..t3: env 3 alone -> 0.
    expected = [[-1, 1, 0, 0], [1, -1, 0, 0], [-1, 0, 0, 0], [1, 0, 0, 0]]
    torch.testing.assert_close(adv, torch.tensor(expected, dtype=torch.float32))


def test_group_advantages_without_truncation_compare_every_step():
    returns, mask, adv = _advantages(group_size=2, truncate=False)
    assert returns.tolist() == RETURNS
    assert mask.tolist() == [[1, 1, 1, 1]] * 4
    # Group 0: t2 5 vs 1, t3 4 vs 2. Group 1: t1 1 vs 1.75, t2 0 vs 1.5, t3 1 vs 1: std 0 -> 0.
    expected = [[-1, 1, 1, 1], [1, -1, -1, -1], [-1, -1, -1, 0], [1, 1, 1, 0]]
    torch.testing.assert_close(adv, torch.tensor(expected, dtype=torch.float32))


def test_group_advantages_use_the_population_std_of_the_alive_members():
    """One group of four: at t1 env 2 (ended at t0, G = 1) is left out of the mean and the std."""
    _, _, adv = _advantages(group_size=4, truncate=True)
    # t0: G = [2, 2.25, 0, 1.875], mean 1.53125, deviations [0.46875, 0.71875, -1.53125, 0.34375],
    #     variance (0.2197265625 + 0.5166015625 + 2.3447265625 + 0.1181640625) / 4 = 0.7998046875
    t0 = [d / math.sqrt(0.7998046875) for d in (0.46875, 0.71875, -1.53125, 0.34375)]
    # t1: envs 0, 1, 3 alive, G = [2, 0.5, 1.75]: mean 17/12, deviations [7/12, -11/12, 4/12],
    #     variance (49 + 121 + 16) / 144 / 3 = 31/72
    std1 = math.sqrt(31 / 72)
    t1 = [7 / 12 / std1, -11 / 12 / std1, 0.0, 4 / 12 / std1]
    # t2: envs 1, 3 alive, G = [1, 1.5] -> -1, +1. t3: env 3 alone -> 0.
    expected = torch.tensor([t0, t1, [0.0, -1.0, 0.0, 1.0], [0.0] * 4]).T
    torch.testing.assert_close(adv, expected)


def test_group_size_must_divide_the_number_of_envs():
    with pytest.raises(ValueError, match=r"algorithm\.group_size=3 .*env\.num_envs=4"):
        _advantages(group_size=3, truncate=True)
    pol = make_policy(ActorOnlyConfig(), 3, 2, Bounded(-1.0, 1.0, shape=(2,)))
    algo = make_algorithm(GRPOConfig(group_size=3, compile="false"), pol, 1)
    with pytest.raises(ValueError, match=r"algorithm\.group_size=3 .*env\.num_envs=4"):
        algo.update(_rollout(pol, envs=4, steps=4))


def test_make_algorithm_dispatches_and_ppo_needs_a_critic():
    actor_only = make_policy(ActorOnlyConfig(), 3, 2, Bounded(-1.0, 1.0, shape=(2,)))
    with_critic = make_policy(PolicyConfig(), 3, 2, Bounded(-1.0, 1.0, shape=(2,)))
    with pytest.raises(
        ValueError,
        match=r"^algorithm=ppo needs a critic: policy=actor_critic \(policy.name=actor_only has none\)$",
    ):
        make_algorithm(AlgorithmConfig(), actor_only, 1)
    ppo = make_algorithm(AlgorithmConfig(), with_critic, 1)
    grpo = make_algorithm(GRPOConfig(), actor_only, 1)
    assert isinstance(ppo, PPO) and not ppo.reset_each_rollout
    assert isinstance(grpo, GRPO) and grpo.reset_each_rollout
    assert not make_algorithm(
        GRPOConfig(reset_every_rollout=False), actor_only, 1
    ).reset_each_rollout
    with pytest.raises(
        ValueError, match=r"algorithm\.name='dqn'; choose from \['ppo', 'grpo', 'sac', 'td3'\]"
    ):
        make_algorithm(GRPOConfig(name="dqn"), actor_only, 1)
    # compile=true compiles GRPO's fused step: refused where the fused step cannot cover the run
    with pytest.raises(ConfigError, match=r"algorithm\.compile=true.*distributed gradient"):
        make_algorithm(GRPOConfig(compile="true"), actor_only, 1, grad_sync=lambda tensors: None)


def _rollout(pol, envs: int, steps: int, obs_dim: int = 3, log_prob_noise: float = 0.0):
    """A rollout [envs, steps] with terminations and truncations, actions sampled by ``pol``."""
    obs = torch.randn(envs, steps, obs_dim)
    terminated = torch.zeros(envs, steps, 1, dtype=torch.bool)
    truncated = torch.zeros(envs, steps, 1, dtype=torch.bool)
    terminated[0, steps // 3] = True
    truncated[1, steps // 2] = True
    if envs > 2:
        terminated[2, 1], truncated[2, steps - 2] = True, True
    with torch.no_grad():
        _, _, action, log_prob = pol.sampling_policy().sample(obs)
    return TensorDict(
        {
            "observation": obs,
            "action": action,
            "action_log_prob": log_prob + log_prob_noise * torch.randn(envs, steps),
            "next": {
                "observation": torch.randn(envs, steps, obs_dim),
                "reward": torch.randn(envs, steps, 1),
                "terminated": terminated,
                "truncated": truncated,
                "done": terminated | truncated,
            },
        },
        batch_size=[envs, steps],
    )


def _reference_grpo_update(pol, initial, batch, cfg, seed):
    """A whole GRPO update in plain torch, written from the rule (loops over groups and steps, no
    rlexp code): returns, alive masks and group advantages, then epochs of shuffled minibatches of
    the masked clipped surrogate - entropy bonus + k3 KL to ``initial``, global grad-norm clipping
    and Adam by hand. Returns the mean of each loss term over the minibatches."""
    reward = batch["next", "reward"].squeeze(-1)
    done = batch["next", "done"].squeeze(-1)
    n, steps = reward.shape
    returns = torch.zeros(n, steps)
    mask = torch.ones(n, steps)
    for i in range(n):
        g = 0.0
        for t in reversed(range(steps)):
            g = float(reward[i, t]) + cfg.gamma * g * (0.0 if done[i, t] else 1.0)
            returns[i, t] = g
        if cfg.truncate_at_first_done and done[i].any():
            first = int(done[i].nonzero()[0])
            mask[i, first + 1 :] = 0.0
    adv = torch.zeros(n, steps)
    for start in range(0, n, cfg.group_size):
        members = range(start, start + cfg.group_size)
        for t in range(steps):
            alive = [i for i in members if mask[i, t] == 1]
            if not alive:
                continue
            values = torch.tensor([float(returns[i, t]) for i in alive], dtype=torch.float64)
            mean, std = values.mean(), values.std(unbiased=False)
            for i in alive:
                adv[i, t] = float((returns[i, t] - mean) / (std + cfg.epsilon))
    obs = batch["observation"].reshape(n * steps, -1)
    act = batch["action"].reshape(n * steps, -1)
    old = batch["action_log_prob"].reshape(-1)
    flat_adv, flat_mask = adv.reshape(-1), mask.reshape(-1)
    params = [p for p in pol.parameters() if p.requires_grad]
    m = [torch.zeros_like(p) for p in params]
    v = [torch.zeros_like(p) for p in params]
    step = 0
    total, mb = n * steps, cfg.mini_batch_size
    sums = {"policy": 0.0, "entropy": 0.0, "entropy_term": 0.0, "kl_ref": 0.0}
    count = 0
    torch.manual_seed(seed)
    shuffle = torch.Generator()
    shuffle.manual_seed(int(torch.randint(2**62, (1,)).item()))
    for _ in range(cfg.num_epochs):
        perm = torch.randperm(total, generator=shuffle)
        for begin in range(0, total - mb + 1, mb):
            idx = perm[begin : begin + mb]
            w = flat_mask[idx]
            denom = max(float(w.sum()), 1.0)
            loc, scale = pol.actor_net(obs[idx])
            dist = torch.distributions.Normal(loc, scale)
            log_prob = dist.log_prob(act[idx]).sum(-1)
            with torch.no_grad():
                ref_loc, ref_scale = initial.actor_net(obs[idx])
                ref = torch.distributions.Normal(ref_loc, ref_scale).log_prob(act[idx]).sum(-1)
            ratio = torch.exp(log_prob - old[idx])
            a, eps = flat_adv[idx], cfg.clip_epsilon
            surrogate = torch.min(ratio * a, ratio.clamp(1 - eps, 1 + eps) * a)
            policy_loss = -(w * surrogate).sum() / denom
            entropy = (w * dist.entropy().sum(-1)).sum() / denom
            entropy_loss = -cfg.entropy_coeff * entropy
            d = ref - log_prob
            kl = (w * (torch.exp(d) - d - 1)).sum() / denom
            grads = torch.autograd.grad(policy_loss + entropy_loss + cfg.kl_coeff * kl, params)
            step += 1
            clipped_adam_step(params, grads, m, v, step, cfg)
            sums["policy"] += policy_loss.item()
            sums["entropy_term"] += entropy_loss.item()
            sums["entropy"] += entropy.item()
            sums["kl_ref"] += kl.item()
            count += 1
    return {k: s / count for k, s in sums.items()}, float(mask.mean())


def _grpo_setup(**overrides):
    torch.manual_seed(0)
    obs_dim, act_dim = 3, 2
    pol = make_policy(ActorOnlyConfig(), obs_dim, act_dim, Bounded(-1.0, 1.0, shape=(act_dim,)))
    pol.normalizer.update(torch.randn(100, obs_dim) * 2 + 1)
    cfg = GRPOConfig(
        gamma=0.9,
        group_size=2,
        kl_coeff=0.5,
        entropy_coeff=0.01,
        num_epochs=2,
        mini_batch_size=12,
        lr=1e-2,  # large steps: a wrong update rule could not hide in the tolerance
        compile="false",
        **overrides,
    )
    return pol, cfg


def test_grpo_update_matches_a_plain_torch_grpo():
    """The update (TorchRL's distribution and k3, fused Adam, guarded step, statistics as tensors)
    moves the parameters exactly as a GRPO written out by hand, with the reference being the initial
    policy as a function: its normaliser statistics too, not the ones updated since."""
    pol, cfg = _grpo_setup()
    initial = copy.deepcopy(pol)
    algo = make_algorithm(cfg, pol, total_iterations=10)
    # 6 envs (3 groups) x 8 steps = 48 samples: 4 minibatches of 12 per epoch
    batch = _rollout(pol, envs=6, steps=8, log_prob_noise=0.3)  # ratios leave the clip
    pol.normalizer.update(torch.randn(50, 3) - 1)  # as after an earlier iteration
    ref_pol = copy.deepcopy(pol)
    before = copy.deepcopy(pol)
    torch.manual_seed(123)
    metrics = algo.update(batch.clone())
    expected, mask_fraction = _reference_grpo_update(ref_pol, initial, batch, cfg, seed=123)

    assert 0.0 < mask_fraction < 1.0
    assert metrics["grpo/mask_fraction"] == pytest.approx(mask_fraction)
    assert metrics["loss/policy"] == pytest.approx(expected["policy"], rel=1e-4, abs=1e-6)
    assert metrics["loss/entropy"] == pytest.approx(expected["entropy"], rel=1e-4, abs=1e-6)
    assert metrics["loss/entropy_term"] == pytest.approx(expected["entropy_term"], rel=1e-4)
    assert metrics["loss/kl_ref"] == pytest.approx(expected["kl_ref"], rel=1e-4, abs=1e-7)
    assert metrics["loss/kl_ref"] > 0 and metrics["loss/clip_fraction"] > 0
    assert metrics["loss/learning_rate"] == cfg.lr and algo.iteration == 1
    for (name, p), r, p0 in zip(
        pol.named_parameters(), ref_pol.parameters(), before.parameters(), strict=True
    ):
        torch.testing.assert_close(p, r, rtol=1e-5, atol=1e-5, msg=f"parameter {name} differs")
        assert (p - p0).abs().max() > 1e-3, f"{name} did not move: the comparison would be vacuous"


def test_an_all_masked_minibatch_has_zero_loss():
    pol, cfg = _grpo_setup()
    algo = make_algorithm(cfg, pol, total_iterations=1)
    flat, _ = algo.prepare(_rollout(pol, envs=2, steps=4))
    flat.set("mask", torch.zeros(8))
    out = algo.loss(flat)
    for key in ("loss_objective", "loss_entropy", "loss_kl"):
        assert out[key].item() == 0.0, key


def test_state_dict_round_trip_keeps_the_reference():
    """A learner rebuilt around the trained policy (as a resumed run builds it) and loaded from the
    first one's state makes the same next update: the reference is the run's initial policy, not
    the policy it was rebuilt around."""
    pol, cfg = _grpo_setup()
    algo = make_algorithm(cfg, pol, total_iterations=10)
    algo.update(_rollout(pol, envs=4, steps=6, log_prob_noise=0.3))
    pol.normalizer.update(torch.randn(30, 3))
    saved = copy.deepcopy({"policy": pol.state_dict(), "algorithm": algo.state_dict()})
    assert "reference" in saved["algorithm"]

    torch.manual_seed(99)  # other initial weights: all that matters comes from the state dicts
    resumed_pol = make_policy(ActorOnlyConfig(), 3, 2, Bounded(-1.0, 1.0, shape=(2,)))
    resumed_pol.load_state_dict(saved["policy"])
    resumed = make_algorithm(cfg, resumed_pol, total_iterations=10)
    assert not torch.equal(
        resumed.reference.state_dict()["module.0.module.log_std"],
        algo.reference.state_dict()["module.0.module.log_std"],
    ), "built around the trained policy, the reference differs until loaded"
    resumed.load_state_dict(saved["algorithm"])

    batch = _rollout(pol, envs=4, steps=6, log_prob_noise=0.3)
    torch.manual_seed(7)
    first = algo.update(batch.clone())
    torch.manual_seed(7)
    second = resumed.update(batch.clone())
    assert first == second
    assert resumed.iteration == algo.iteration == 2
    for (name, p), q in zip(pol.named_parameters(), resumed_pol.parameters(), strict=True):
        assert torch.equal(p, q), f"{name} differs after the resumed update"

    no_reference = make_algorithm(replace(cfg, kl_coeff=0.0), resumed_pol, total_iterations=10)
    assert no_reference.reference is None and "reference" not in no_reference.state_dict()
    with pytest.raises(ValueError, match="no GRPO reference policy"):
        resumed.load_state_dict(no_reference.state_dict())


def test_non_finite_reward_stops_the_update_naming_the_loss():
    pol, cfg = _grpo_setup()
    algo = make_algorithm(cfg, pol, total_iterations=1)
    batch = _rollout(pol, envs=2, steps=6)
    batch["next", "reward"][0, 0] = float("nan")
    before = copy.deepcopy(pol)
    with pytest.raises(
        NonFiniteError, match=r"^non-finite loss \(loss_objective.*\) in GRPO update"
    ):
        algo.update(batch)
    for p, p0 in zip(pol.parameters(), before.parameters(), strict=True):
        assert torch.equal(p, p0)
