"""GAE against numbers worked out by hand; the collection policy's log-density against TorchRL's."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.modules import ValueOperator

import conftest
from conftest import PLAIN_PPO
from rlexp.algorithms.ppo import make_gae
from rlexp.config.schema import AlgorithmConfig, PolicyConfig
from rlexp.policies.actor_critic import ObservationNormalizer, make_policy


class _ObsIsValue(torch.nn.Module):
    def forward(self, obs):
        return obs


def _gae(terminated, truncated):
    """gamma 0.9, lambda 0.8; V(s_t) = [0.5, 1.0, 1.5], V(s_t+1) = [1.0, 1.5, 2.0], r = [1, 2, 3]."""
    cfg = AlgorithmConfig(gamma=0.9, lmbda=0.8, **PLAIN_PPO)
    gae = make_gae(cfg, ValueOperator(_ObsIsValue(), in_keys=["observation"]))
    term = torch.tensor(terminated).reshape(1, 3, 1)
    trunc = torch.tensor(truncated).reshape(1, 3, 1)
    td = TensorDict(
        {
            "observation": torch.tensor([[0.5], [1.0], [1.5]]).reshape(1, 3, 1),
            "next": {
                "observation": torch.tensor([[1.0], [1.5], [2.0]]).reshape(1, 3, 1),
                "reward": torch.tensor([1.0, 2.0, 3.0]).reshape(1, 3, 1),
                "terminated": term,
                "truncated": trunc,
                "done": term | trunc,
            },
        },
        batch_size=[1, 3],
    )
    gae(td)
    return td["advantage"].reshape(-1).tolist(), td["value_target"].reshape(-1).tolist()


def test_gae_without_episode_end():
    # delta = r + 0.9 V' - V = [1.4, 2.35, 3.3]; A2 = 3.3; A1 = 2.35 + 0.72 * 3.3; A0 = 1.4 + 0.72 * A1
    adv, target = _gae([False, False, False], [False, False, False])
    assert adv == pytest.approx([4.80272, 4.726, 3.3], abs=1e-5)
    assert target == pytest.approx([4.80272 + 0.5, 4.726 + 1.0, 3.3 + 1.5], abs=1e-5)


def test_gae_termination_does_not_bootstrap():
    # terminated at t=1: delta1 = 2 - 1.0 = 1.0, trace cut; A0 = 1.4 + 0.72 * 1.0
    adv, _ = _gae([False, True, False], [False, False, False])
    assert adv == pytest.approx([2.12, 1.0, 3.3], abs=1e-5)


def test_gae_truncation_bootstraps_from_the_final_observation():
    # truncated at t=1: delta1 = 2 + 0.9 * 1.5 - 1.0 = 2.35 (bootstrapped), trace cut; A0 = 1.4 + 0.72 * 2.35
    adv, _ = _gae([False, False, False], [False, True, False])
    assert adv == pytest.approx([3.092, 2.35, 3.3], abs=1e-5)


def _policy():
    from torchrl.data import Bounded

    spec = Bounded(-1.0, 1.0, shape=(5, 3))
    torch.manual_seed(0)
    pol = make_policy(PolicyConfig(init_log_std=-0.3), obs_dim=4, act_dim=3, action_spec=spec)
    with torch.no_grad():
        pol.actor_net.log_std.copy_(torch.tensor([-0.5, 0.0, 0.4]))
    return pol


def test_sampling_policy_log_prob_matches_torchrl_distribution():
    pol = _policy()
    td = TensorDict({"observation": torch.randn(5, 4)}, batch_size=[5])
    out = pol.sampling_policy()(td.clone())
    dist = pol.actor.get_dist(td.clone())
    ref = dist.log_prob(out["action"])
    torch.testing.assert_close(out["action_log_prob"], ref, rtol=1e-5, atol=1e-5)
    assert not torch.equal(out["action"], out["loc"])  # it sampled


def test_deterministic_policy_returns_the_mean():
    pol = _policy()
    td = TensorDict({"observation": torch.randn(5, 4)}, batch_size=[5])
    out = pol.sampling_policy(deterministic=True)(td.clone())
    torch.testing.assert_close(out["action"], out["loc"])


def test_observation_normalizer_matches_numpy_over_batches():
    rng = np.random.default_rng(0)
    data = [rng.normal(3.0, 2.0, size=(n, 4)).astype(np.float32) for n in (7, 100, 33)]
    norm = ObservationNormalizer(4)
    for batch in data:
        norm.update(torch.from_numpy(batch))
    allx = np.concatenate(data).astype(np.float64)
    np.testing.assert_allclose(norm.mean.numpy(), allx.mean(0), rtol=1e-10)
    np.testing.assert_allclose(norm.var.numpy(), allx.var(0), rtol=1e-10)
    x = torch.from_numpy(data[0])
    expected = np.clip((data[0] - allx.mean(0)) / np.sqrt(allx.var(0) + 1e-8), -10, 10)
    np.testing.assert_allclose(norm(x).numpy(), expected, rtol=1e-5, atol=1e-5)
    assert "mean" in norm.state_dict() and "count" in norm.state_dict()


@pytest.mark.parametrize("env_name", ["hopper", "push_cube"])
def test_fast_collector_gives_the_same_batches_as_torchrl_loop(env_name, monkeypatch):
    """The lean rollout loop is an optimisation only: same values as TorchRL's generic Collector
    (Hopper: the all-numpy loop, numpy sampler and ``step_arrays``; PushCube: the tensor loop)."""
    from torchrl.collectors import Collector

    from conftest import compose
    from rlexp.config.validate import to_root_config
    from rlexp.envs.factory import make_env
    from rlexp.training.collector import RolloutCollector

    def batches(cls):
        torch.manual_seed(0)
        env_cfg = to_root_config(compose([f"env={env_name}"])).env
        env = make_env(env_cfg, 4, seed=0)
        pol = make_policy(
            PolicyConfig(),
            env.observation_spec["observation"].shape[-1],
            env.action_spec.shape[-1],
            env.action_spec,
        )
        sampling = pol.sampling_policy()
        col = cls(
            env,
            sampling,
            frames_per_batch=4 * 150,
            total_frames=-1,
            trust_policy=True,
            track_traj_ids=False,
        )
        # as RolloutCollector sets it: the numpy sampler's noise drawn a rollout (150 steps) at a
        # time; TorchRL's loop then takes the same draws step by step
        sampling.set_noise_block(150)
        it = iter(col)
        out = [next(it) for _ in range(3)]  # 450 steps per env: episodes end and reset on the way
        col.shutdown()
        return out

    array_rollouts = []
    array_rollout = RolloutCollector._array_rollout
    monkeypatch.setattr(
        RolloutCollector,
        "_array_rollout",
        lambda *a: array_rollouts.append(1) or array_rollout(*a),
    )
    slow, fast = batches(Collector), batches(RolloutCollector)
    assert len(array_rollouts) == (3 if env_name == "hopper" else 0)
    assert any(b["next", "done"].any() for b in slow)
    for s, f in zip(slow, fast, strict=True):
        assert f.batch_size == s.batch_size
        for key in f.keys(True, True):
            assert torch.equal(f[key], s[key]), f"{key} differs"
        for key in (
            "action_log_prob",
            ("next", "observation"),
            ("next", "reward"),
            ("next", "terminated"),
            ("next", "truncated"),
        ):
            assert key in f.keys(True, True)


def test_ppo_minibatch_loss_and_gradients_match_a_reference_implementation():
    """rlexp's PPO step (TorchRL ClipPPOLoss as configured, fast sampling policy's log-probs) gives
    the loss and gradients of the textbook formulas written out in plain torch."""
    from torchrl.data import Bounded

    from rlexp.algorithms.ppo import LOSS_KEYS, make_algorithm

    torch.manual_seed(0)
    n, obs_dim, act_dim = 64, 5, 2
    cfg = AlgorithmConfig(clip_epsilon=0.2, entropy_coeff=0.01, critic_coeff=0.5, **PLAIN_PPO)
    pol = make_policy(PolicyConfig(), obs_dim, act_dim, Bounded(-1.0, 1.0, shape=(n, act_dim)))
    with torch.no_grad():
        pol.actor_net.log_std.copy_(torch.tensor([-0.3, 0.2]))
    algo = make_algorithm(cfg, pol, total_iterations=1)
    obs = torch.randn(n, obs_dim)
    with torch.no_grad():  # collection runs without grad
        td = pol.sampling_policy()(TensorDict({"observation": obs}, batch_size=[n]))
    # the policy moved since collection: old log-probs differ, so ratios leave [0.8, 1.2] both ways
    old_log_prob = td["action_log_prob"] + 0.3 * torch.randn(n)
    advantage = torch.randn(n, 1) * 2 + 0.5
    value_target = torch.randn(n, 1)
    batch = TensorDict(
        {
            "observation": obs,
            "action": td["action"],
            "action_log_prob": old_log_prob,
            "advantage": advantage,
            "value_target": value_target,
        },
        batch_size=[n],
    )
    params = [p for p in pol.parameters() if p.requires_grad]

    out = algo.loss(batch.clone())
    total = sum(out[k] for k in LOSS_KEYS if k in out.keys())
    grads = torch.autograd.grad(total, params)

    # Reference: PPO-clip (Schulman et al. 2017) with per-minibatch advantage normalisation.
    loc, scale = pol.actor_net(obs)
    dist = torch.distributions.Normal(loc, scale)
    log_prob = dist.log_prob(td["action"]).sum(-1)
    adv = advantage.squeeze(-1)
    adv = (adv - adv.mean()) / adv.std()
    ratio = torch.exp(log_prob - old_log_prob)
    policy_loss = -torch.min(ratio * adv, ratio.clamp(0.8, 1.2) * adv).mean()
    value_loss = 0.5 * (pol.critic_net(obs) - value_target).pow(2).mean()
    entropy_loss = -0.01 * dist.entropy().sum(-1).mean()
    ref_total = policy_loss + value_loss + entropy_loss
    ref_grads = torch.autograd.grad(ref_total, params)

    torch.testing.assert_close(out["loss_objective"], policy_loss, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(out["loss_critic"], value_loss, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(out["loss_entropy"], entropy_loss, rtol=1e-5, atol=1e-6)
    assert ((ratio < 0.8) | (ratio > 1.2)).any(), "the clip must be active somewhere"
    for g, r in zip(grads, ref_grads, strict=True):
        torch.testing.assert_close(g, r, rtol=1e-4, atol=1e-6)


def _reference_ppo_update(pol, batch, cfg, seed):
    """A whole PPO update in plain torch, written from the papers: GAE (Schulman et al. 2016) with
    bootstrapping cut at terminations and traces cut at episode ends, then epochs of shuffled
    minibatches of PPO-clip + value + entropy losses, global grad-norm clipping and Adam (Kingma &
    Ba 2015) by hand. Returns the mean of each loss over the minibatches."""
    obs, nxt = batch["observation"], batch["next"]
    with torch.no_grad():
        value = pol.critic_net(obs).squeeze(-1)  # [B, T]
        next_value = pol.critic_net(nxt["observation"]).squeeze(-1)
    reward = nxt["reward"].squeeze(-1)
    not_term = (~nxt["terminated"].squeeze(-1)).float()
    not_done = (~nxt["done"].squeeze(-1)).float()
    adv = torch.zeros_like(reward)
    running = torch.zeros(reward.shape[0])
    for t in reversed(range(reward.shape[1])):
        delta = reward[:, t] + cfg.gamma * next_value[:, t] * not_term[:, t] - value[:, t]
        running = delta + cfg.gamma * cfg.lmbda * not_done[:, t] * running
        adv[:, t] = running
    target = adv + value
    flat_obs = obs.reshape(-1, obs.shape[-1])
    flat_act = batch["action"].reshape(-1, batch["action"].shape[-1])
    flat_old = batch["action_log_prob"].reshape(-1)
    flat_adv, flat_target = adv.reshape(-1), target.reshape(-1)
    params = [p for p in pol.parameters() if p.requires_grad]
    m = [torch.zeros_like(p) for p in params]
    v = [torch.zeros_like(p) for p in params]
    step = 0
    n, mb = flat_obs.shape[0], cfg.mini_batch_size
    sums = {"policy": 0.0, "value": 0.0, "entropy_term": 0.0, "entropy": 0.0}
    count = 0
    torch.manual_seed(seed)
    shuffle = torch.Generator()  # rlexp's minibatch order: its own generator, seeded per update
    shuffle.manual_seed(int(torch.randint(2**62, (1,)).item()))
    for _ in range(cfg.num_epochs):
        perm = torch.randperm(n, generator=shuffle)
        for start in range(0, n - mb + 1, mb):
            idx = perm[start : start + mb]
            loc, scale = pol.actor_net(flat_obs[idx])
            dist = torch.distributions.Normal(loc, scale)
            log_prob = dist.log_prob(flat_act[idx]).sum(-1)
            a = flat_adv[idx]
            a = (a - a.mean()) / a.std()
            ratio = torch.exp(log_prob - flat_old[idx])
            eps = cfg.clip_epsilon
            policy_loss = -torch.min(ratio * a, ratio.clamp(1 - eps, 1 + eps) * a).mean()
            value_loss = (
                cfg.critic_coeff
                * (pol.critic_net(flat_obs[idx]).squeeze(-1) - flat_target[idx]).pow(2).mean()
            )
            entropy = dist.entropy().sum(-1).mean()
            entropy_loss = -cfg.entropy_coeff * entropy
            grads = torch.autograd.grad(policy_loss + value_loss + entropy_loss, params)
            step += 1
            conftest.clipped_adam_step(params, grads, m, v, step, cfg)
            sums["policy"] += policy_loss.item()
            sums["value"] += value_loss.item()
            sums["entropy_term"] += entropy_loss.item()
            sums["entropy"] += entropy.item()
            count += 1
    return {k: s / count for k, s in sums.items()}


@pytest.mark.parametrize(
    "compile_loss", ["false", pytest.param("true", marks=conftest.needs_compiler)]
)
def test_ppo_update_matches_a_plain_torch_ppo(compile_loss):
    """The optimised update (TorchRL GAE + ClipPPOLoss, fused Adam, statistics kept as tensors, the
    loss through torch.compile when on) moves the parameters exactly as a PPO written out by hand."""
    import copy

    from torchrl.data import Bounded

    from rlexp.algorithms.ppo import make_algorithm

    torch.manual_seed(0)
    envs, steps, obs_dim, act_dim = 2, 24, 5, 2
    cfg = AlgorithmConfig(
        gamma=0.9,
        lmbda=0.8,
        entropy_coeff=0.01,
        num_epochs=2,
        mini_batch_size=12,
        lr=1e-2,  # large steps: a wrong update rule could not hide in the tolerance
        compile=compile_loss,
        **PLAIN_PPO,
    )
    pol = make_policy(PolicyConfig(), obs_dim, act_dim, Bounded(-1.0, 1.0, shape=(act_dim,)))
    pol.normalizer.update(torch.randn(100, obs_dim) * 2 + 1)
    terminated = torch.zeros(envs, steps, 1, dtype=torch.bool)
    truncated = torch.zeros(envs, steps, 1, dtype=torch.bool)
    terminated[0, 7], truncated[1, 15], terminated[1, 20] = True, True, True
    # A rollout's layout: s_t+1 is the step's next observation unless the episode ended there.
    next_obs = torch.randn(envs, steps, obs_dim)
    obs = torch.randn(envs, steps, obs_dim)
    continues = ~(terminated | truncated)[:, :-1]
    obs[:, 1:] = torch.where(continues, next_obs[:, :-1], obs[:, 1:])
    with torch.no_grad():
        loc, scale, action, log_prob = pol.sampling_policy().sample(obs)
    batch = TensorDict(
        {
            "observation": obs,
            "action": action,
            "action_log_prob": log_prob + 0.2 * torch.randn(envs, steps),  # ratios leave the clip
            "next": {
                "observation": next_obs,
                "reward": torch.randn(envs, steps, 1),
                "terminated": terminated,
                "truncated": truncated,
                "done": terminated | truncated,
            },
        },
        batch_size=[envs, steps],
    )
    ref_pol = copy.deepcopy(pol)
    initial = copy.deepcopy(pol)
    algo = make_algorithm(cfg, pol, total_iterations=1_000_000)  # long run: "true" compiles
    torch.manual_seed(123)
    metrics = algo.update(batch.clone())
    expected = _reference_ppo_update(ref_pol, batch, cfg, seed=123)

    assert algo.compiled is (compile_loss == "true")
    assert metrics["loss/policy"] == pytest.approx(expected["policy"], rel=1e-4, abs=1e-6)
    assert metrics["loss/value"] == pytest.approx(expected["value"], rel=1e-4, abs=1e-6)
    # loss/entropy is the policy's entropy; loss/entropy_term the loss term -entropy_coeff * it
    assert metrics["loss/entropy"] == pytest.approx(expected["entropy"], rel=1e-4, abs=1e-6)
    assert metrics["loss/entropy_term"] == pytest.approx(expected["entropy_term"], rel=1e-4)
    for (name, p), r, p0 in zip(
        pol.named_parameters(), ref_pol.parameters(), initial.parameters(), strict=True
    ):
        torch.testing.assert_close(p, r, rtol=1e-4, atol=1e-5, msg=f"parameter {name} differs")
        assert (p - p0).abs().max() > 1e-3, f"{name} did not move: the comparison would be vacuous"


@pytest.mark.parametrize("env_name", ["hopper", "push_cube"])
def test_advantages_equal_torchrl_gae_with_its_own_value_network(env_name):
    """compute_advantages reuses V(s_t+1) for V(s'_t) where the rollout continues: the values,
    advantages and targets are those of TorchRL's GAE evaluating V(s) and V(s') itself."""
    from conftest import compose
    from rlexp.algorithms.ppo import make_algorithm
    from rlexp.config.validate import to_root_config
    from rlexp.envs.factory import make_env
    from rlexp.training.collector import RolloutCollector

    torch.manual_seed(0)
    env = make_env(to_root_config(compose([f"env={env_name}"])).env, 4, seed=0)
    obs_dim, act_dim = env.observation_spec["observation"].shape[-1], env.action_spec.shape[-1]
    pol = make_policy(PolicyConfig(), obs_dim, act_dim, env.action_spec)
    col = RolloutCollector(
        env, pol.sampling_policy(), frames_per_batch=4 * 300, total_frames=-1, trust_policy=True
    )
    batch = next(iter(col))
    col.shutdown()
    pol.normalizer.update(batch["observation"])  # a non-trivial critic input
    assert batch["next", "done"].any(), "episodes must end inside the rollout"
    mine = make_algorithm(AlgorithmConfig(**PLAIN_PPO), pol, 1).compute_advantages(batch.clone())
    theirs = make_gae(AlgorithmConfig(), pol.critic)(batch.clone())
    for key in ("state_value", ("next", "state_value"), "advantage", "value_target"):
        torch.testing.assert_close(mine[key], theirs[key], rtol=1e-5, atol=1e-5, msg=str(key))
