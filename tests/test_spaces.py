"""Spaces beyond Box (#28): observation flattening and action decoding against hand-written values,
the categorical head against torch's own distributions, and a whole PPO update with a categorical
policy against PPO written out in plain torch."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch
from gymnasium import spaces
from tensordict import TensorDict
from torchrl.data import MultiCategorical as MultiCategoricalSpec

import conftest
from conftest import PLAIN_PPO
from rlexp.config.schema import AlgorithmConfig, PolicyConfig
from rlexp.envs.layout_check import check_layout
from rlexp.envs.spaces import UnsupportedSpace, action_coding, obs_layout
from rlexp.policies.actor_critic import make_policy
from rlexp.policies.heads import MultiCategorical, categorical_kl


def test_nested_dict_and_tuple_are_flattened_in_sorted_key_order():
    # Keys listed out of order on purpose (Gymnasium keeps an OrderedDict's order); ints with start.
    space = spaces.Dict(
        {
            "zeta": spaces.Box(-1, 1, (2, 2), np.float32),
            "alpha": spaces.Tuple((spaces.Discrete(3, start=-1), spaces.MultiBinary(2))),
            "mid": spaces.Dict({"b": spaces.MultiDiscrete([2, 3], start=[1, 0])}),
        }
    )
    layout = obs_layout(space, "env.name='x'")
    assert [(p.key, p.kind, p.offset, p.size) for p in layout.parts] == [
        ("alpha/0", "discrete", 0, 3),
        ("alpha/1", "multi_binary", 3, 2),
        ("mid/b", "multi_discrete", 5, 5),
        ("zeta", "box", 10, 4),
    ]
    obs = {
        "zeta": np.array([[0.5, -0.25], [0.125, 1.0]], np.float32),
        "alpha": (1, np.array([1, 0], np.int8)),  # Discrete value 1 with start -1: index 2
        "mid": {"b": np.array([2, 0])},  # (2 - 1) of 2 values, (0 - 0) of 3 values
    }
    expected = [0, 0, 1] + [1, 0] + [0, 1, 1, 0, 0] + [0.5, -0.25, 0.125, 1.0]
    np.testing.assert_array_equal(layout.flatten(obs), np.array(expected, np.float32))
    assert layout.dim == 14 and not layout.plain
    assert layout.record()["parts"][2] == {
        "key": "mid/b",
        "kind": "multi_discrete",
        "shape": [2],
        "offset": 5,
        "size": 5,
        "nvec": [2, 3],
        "start": [1, 0],
    }


def test_a_plain_box_is_the_vector_and_a_multi_dim_box_is_flattened_in_c_order():
    assert obs_layout(spaces.Box(-1, 1, (3,), np.float64), "w").plain
    layout = obs_layout(spaces.Box(-1, 1, (2, 3), np.float64), "w")
    x = np.arange(6, dtype=np.float64).reshape(2, 3)
    np.testing.assert_array_equal(layout.flatten(x), np.arange(6, dtype=np.float32))


@pytest.mark.parametrize(
    ("space", "words"),
    [
        (spaces.Text(4), "Text"),
        (spaces.Dict({"a": spaces.Box(0, 1, (1,)), "t": spaces.Text(3)}), "at key 't'"),
        (spaces.Sequence(spaces.Discrete(2)), "Sequence"),
    ],
)
def test_unsupported_observations_are_one_line_naming_the_space(space, words):
    with pytest.raises(UnsupportedSpace) as err:
        obs_layout(space, "env.name='my:Env-v0'")
    msg = str(err.value)
    assert "\n" not in msg and words in msg and "env.name='my:Env-v0'" in msg
    assert "Dict/Tuple" in msg  # and what is supported


def test_action_decoding_adds_start_and_restores_shape_and_dtype():
    d = action_coding(spaces.Discrete(4, start=-2), "w")
    assert (d.kind, d.dim, d.nvec, d.start) == ("discrete", 1, (4,), (-2,))
    assert d.decode(np.array([3])) == 1 and isinstance(d.decode(np.array([0])), int)
    md = action_coding(spaces.MultiDiscrete([[2, 3], [4, 5]], start=[[1, 0], [-1, 2]]), "w")
    assert (md.dim, md.nvec, md.start) == (4, (2, 3, 4, 5), (1, 0, -1, 2))
    out = md.decode(np.array([1, 2, 0, 4]))
    np.testing.assert_array_equal(out, np.array([[2, 2], [-1, 6]]))
    assert out.shape == (2, 2) and out.dtype == np.int64
    mb = action_coding(spaces.MultiBinary((2, 2)), "w")
    assert (mb.dim, mb.nvec) == (4, (2, 2, 2, 2))
    out = mb.decode(np.array([1, 0, 0, 1]))
    np.testing.assert_array_equal(out, np.array([[1, 0], [0, 1]]))
    assert out.dtype == np.int8
    box = action_coding(spaces.Box(np.array([-1.0, 0.0]), np.array([2.0, 3.0])), "w")
    assert (box.kind, box.low, box.high) == ("box", (-1.0, 0.0), (2.0, 3.0))
    with pytest.raises(UnsupportedSpace, match="Tuple"):
        action_coding(spaces.Tuple((spaces.Discrete(2),)), "w")


@pytest.mark.parametrize("nvec", [(3,), (4, 4), (2, 5, 3)])
def test_multi_categorical_is_independent_torch_categoricals(nvec):
    torch.manual_seed(1)
    logits = torch.randn(6, sum(nvec)) * 2
    dist = MultiCategorical(logits, nvec)
    parts = [torch.distributions.Categorical(logits=x) for x in logits.split(nvec, -1)]
    action = torch.stack([p.sample() for p in parts], -1)
    ref_lp = sum(p.log_prob(action[:, i]) for i, p in enumerate(parts))
    torch.testing.assert_close(dist.log_prob(action), ref_lp)
    torch.testing.assert_close(dist.entropy(), sum(p.entropy() for p in parts))
    mode = torch.stack([x.argmax(-1) for x in logits.split(nvec, -1)], -1)
    assert torch.equal(dist.mode, mode) and torch.equal(dist.deterministic_sample, mode)
    assert dist.sample().shape == (6, len(nvec)) and dist.sample((5,)).shape == (5, 6, len(nvec))
    other = torch.randn(6, sum(nvec))
    ref_kl = sum(
        torch.distributions.kl_divergence(p, torch.distributions.Categorical(logits=q))
        for p, q in zip(parts, other.split(nvec, -1), strict=True)
    ).mean()
    torch.testing.assert_close(categorical_kl(logits, other, nvec), ref_kl)


def _categorical_policy(nvec, obs_dim=5, n=64):
    spec = MultiCategoricalSpec(nvec=list(nvec), shape=(n, len(nvec)), dtype=torch.int64)
    return make_policy(PolicyConfig(), obs_dim, len(nvec), spec, nvec=nvec)


@pytest.mark.parametrize("nvec", [(3,), (2, 4)])
def test_sampler_draws_from_the_softmax_and_scores_as_the_loss_distribution(nvec):
    torch.manual_seed(0)
    pol = _categorical_policy(nvec)
    obs = torch.randn(1, 5).expand(20000, 5)
    with torch.no_grad():
        logits, action, log_prob = pol.sampling_policy().sample(obs)
        dist = pol.actor.get_dist(TensorDict({"observation": obs}, batch_size=[20000]))
    torch.testing.assert_close(log_prob, dist.log_prob(action), rtol=1e-6, atol=1e-6)
    for i, block in enumerate(logits[0].split(nvec)):  # frequencies match the softmax
        freq = torch.bincount(action[:, i], minlength=nvec[i]).double() / 20000
        torch.testing.assert_close(freq, block.softmax(-1).double(), atol=0.015, rtol=0)
    with torch.no_grad():
        det = pol.sampling_policy(deterministic=True).sample(obs[:3])[1]
    assert torch.equal(det, dist.mode[:3])


def test_ppo_minibatch_with_a_categorical_policy_matches_textbook_ppo():
    """ClipPPOLoss over the MultiCategorical head, with non-default coefficients, against the
    formulas in plain torch (torch's own Categorical for log-probs and entropy)."""
    from rlexp.algorithms.ppo import LOSS_KEYS, make_algorithm

    torch.manual_seed(3)
    nvec, n = (3, 2), 48
    cfg = AlgorithmConfig(clip_epsilon=0.13, entropy_coeff=0.02, critic_coeff=0.7, **PLAIN_PPO)
    pol = _categorical_policy(nvec, n=n)
    algo = make_algorithm(cfg, pol, total_iterations=1)
    obs = torch.randn(n, 5)
    with torch.no_grad():
        _, action, log_prob = pol.sampling_policy().sample(obs)
    old = log_prob + 0.3 * torch.randn(n)
    advantage, target = torch.randn(n, 1) * 2 + 0.5, torch.randn(n, 1)
    batch = TensorDict(
        {
            "observation": obs,
            "action": action,
            "action_log_prob": old,
            "advantage": advantage,
            "value_target": target,
        },
        batch_size=[n],
    )
    params = [p for p in pol.parameters() if p.requires_grad]
    out = algo.loss(batch.clone())
    grads = torch.autograd.grad(sum(out[k] for k in LOSS_KEYS), params)

    parts = [torch.distributions.Categorical(logits=x) for x in pol.actor_net(obs).split(nvec, -1)]
    lp = sum(p.log_prob(action[:, i]) for i, p in enumerate(parts))
    adv = advantage.squeeze(-1)
    adv = (adv - adv.mean()) / adv.std()
    ratio = torch.exp(lp - old)
    policy = -torch.min(ratio * adv, ratio.clamp(0.87, 1.13) * adv).mean()
    value = 0.7 * (pol.critic_net(obs) - target).pow(2).mean()
    entropy = -0.02 * sum(p.entropy() for p in parts).mean()
    ref_grads = torch.autograd.grad(policy + value + entropy, params)
    assert ((ratio < 0.87) | (ratio > 1.13)).any() and ((ratio > 0.9) & (ratio < 1.1)).any()
    torch.testing.assert_close(out["loss_objective"], policy, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(out["loss_critic"], value, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(out["loss_entropy"], entropy, rtol=1e-5, atol=1e-6)
    for g, r in zip(grads, ref_grads, strict=True):
        torch.testing.assert_close(g, r, rtol=1e-4, atol=1e-6)


@pytest.mark.parametrize(
    "compile_loss", ["false", pytest.param("true", marks=conftest.needs_compiler)]
)
def test_categorical_update_with_adaptive_lr_moves_parameters_as_plain_torch(compile_loss):
    """A whole update (GAE, epochs, minibatches, clipping, Adam, rsl_rl's adaptive learning rate on
    the categorical KL) against a hand-written loop."""
    from rlexp.algorithms.ppo import adaptive_learning_rate, make_algorithm

    torch.manual_seed(0)
    envs, steps, nvec = 2, 16, (3, 4)
    cfg = AlgorithmConfig(
        gamma=0.93,
        lmbda=0.71,
        clip_epsilon=0.25,
        entropy_coeff=0.03,
        critic_coeff=0.4,
        num_epochs=2,
        mini_batch_size=8,
        lr=2e-2,
        max_grad_norm=0.3,
        compile=compile_loss,
        **{**PLAIN_PPO, "anneal_lr": False},
        desired_kl=0.001,
    )
    pol = _categorical_policy(nvec, n=envs)
    obs = torch.randn(envs, steps, 5)
    next_obs = torch.randn(envs, steps, 5)
    obs[:, 1:] = next_obs[:, :-1]
    with torch.no_grad():
        logits, action, log_prob = pol.sampling_policy().sample(obs)
    terminated = torch.zeros(envs, steps, 1, dtype=torch.bool)
    terminated[0, 5] = True
    batch = TensorDict(
        {
            "observation": obs,
            "logits": logits,
            "action": action,
            "action_log_prob": log_prob,
            "next": {
                "observation": next_obs,
                "reward": torch.randn(envs, steps, 1),
                "terminated": terminated,
                "truncated": torch.zeros_like(terminated),
                "done": terminated.clone(),
            },
        },
        batch_size=[envs, steps],
    )
    ref = copy.deepcopy(pol)
    algo = make_algorithm(cfg, pol, total_iterations=10**6)
    torch.manual_seed(7)
    metrics = algo.update(batch.clone())

    # reference
    with torch.no_grad():
        value = ref.critic_net(obs).squeeze(-1)
        next_value = ref.critic_net(next_obs).squeeze(-1)
    reward, not_term = batch["next", "reward"].squeeze(-1), (~terminated.squeeze(-1)).float()
    adv, running = torch.zeros(envs, steps), torch.zeros(envs)
    for t in reversed(range(steps)):
        delta = reward[:, t] + 0.93 * next_value[:, t] * not_term[:, t] - value[:, t]
        running = delta + 0.93 * 0.71 * not_term[:, t] * running
        adv[:, t] = running
    flat = {
        "obs": obs.reshape(-1, 5),
        "act": action.reshape(-1, 2),
        "old": log_prob.reshape(-1),
        "logits": logits.reshape(-1, 7),
        "adv": adv.reshape(-1),
        "target": (adv + value).reshape(-1),
    }
    params = [p for p in ref.parameters() if p.requires_grad]
    m, v = [torch.zeros_like(p) for p in params], [torch.zeros_like(p) for p in params]
    torch.manual_seed(7)
    shuffle = torch.Generator()
    shuffle.manual_seed(int(torch.randint(2**62, (1,)).item()))
    lr, step, entropies = 2e-2, 0, []
    for _ in range(2):
        perm = torch.randperm(envs * steps, generator=shuffle)
        for start in range(0, envs * steps, 8):
            i = perm[start : start + 8]
            with torch.no_grad():
                kl = categorical_kl(flat["logits"][i], ref.actor_net(flat["obs"][i]), nvec)
            lr = adaptive_learning_rate(lr, float(kl), 0.001)
            parts = [
                torch.distributions.Categorical(logits=x)
                for x in ref.actor_net(flat["obs"][i]).split(nvec, -1)
            ]
            lp = sum(p.log_prob(flat["act"][i][:, k]) for k, p in enumerate(parts))
            a = flat["adv"][i]
            a = (a - a.mean()) / a.std()
            ratio = torch.exp(lp - flat["old"][i])
            ent = sum(p.entropy() for p in parts).mean()
            loss = (
                -torch.min(ratio * a, ratio.clamp(0.75, 1.25) * a).mean()
                + 0.4
                * (ref.critic_net(flat["obs"][i]).squeeze(-1) - flat["target"][i]).pow(2).mean()
                - 0.03 * ent
            )
            grads = torch.autograd.grad(loss, params)
            step += 1
            conftest.clipped_adam_step(
                params, grads, m, v, step, AlgorithmConfig(lr=lr, max_grad_norm=0.3)
            )
            entropies.append(float(ent))
    assert algo.cfg.lr == pytest.approx(lr) and lr != 2e-2  # the KL moved the rate
    assert metrics["loss/entropy"] == pytest.approx(np.mean(entropies), rel=1e-4)
    assert metrics["loss/entropy_term"] == pytest.approx(-0.03 * np.mean(entropies), rel=1e-4)
    assert "loss/log_std" not in metrics  # a categorical policy has none: not made up
    for (name, p), r in zip(pol.named_parameters(), ref.parameters(), strict=True):
        torch.testing.assert_close(p, r, rtol=1e-4, atol=1e-5, msg=f"{name} differs")


def test_a_checkpoint_made_for_another_flattening_is_refused():
    from types import SimpleNamespace

    old = obs_layout(spaces.Dict({"a": spaces.Box(0, 1, (2,)), "b": spaces.Box(0, 1, (3,))}), "w")
    new = obs_layout(spaces.Dict({"a": spaces.Box(0, 1, (3,)), "b": spaces.Box(0, 1, (2,))}), "w")
    env = SimpleNamespace(obs_layout=new)
    check_layout(old.record(), SimpleNamespace(obs_layout=old), "checkpoint 'c.pt'")  # same: ok
    with pytest.raises(ValueError, match=r"checkpoint 'c.pt' was made for observations flattened"):
        check_layout(old.record(), env, "checkpoint 'c.pt'")


@pytest.mark.parametrize("env_id", ["CartPole-v1", "toy_envs:DictGoal-v0"])
def test_fast_collector_equals_torchrl_loop_with_a_categorical_policy(env_id):
    """The lean rollout loop with categorical actions (and a Dict observation) gives exactly the
    batches of TorchRL's generic Collector."""
    import toy_envs  # noqa: F401  (registers DictGoal-v0)
    from torchrl.collectors import Collector

    from rlexp.config.schema import EnvConfig
    from rlexp.envs.factory import make_env
    from rlexp.policies.actor_critic import policy_for_env
    from rlexp.training.collector import RolloutCollector

    def batches(cls):
        torch.manual_seed(0)
        env = make_env(EnvConfig(name=env_id, max_episode_steps=40), 3, seed=2)
        pol = policy_for_env(PolicyConfig(), EnvConfig(), env)
        col = cls(env, pol.sampling_policy(), frames_per_batch=3 * 60, total_frames=-1,
                  trust_policy=True, track_traj_ids=False)  # fmt: skip
        it = iter(col)
        out = [next(it) for _ in range(2)]
        col.shutdown()
        return out

    slow, fast = batches(Collector), batches(RolloutCollector)
    assert any(b["next", "done"].any() for b in slow)
    for s, f in zip(slow, fast, strict=True):
        assert f["action"].dtype == torch.int64
        for key in f.keys(True, True):
            assert torch.equal(f[key], s[key]), f"{key} differs"


@pytest.mark.parametrize(
    "env_id",
    ["FrozenLake-v1", "Taxi-v4", "Blackjack-v1", "MountainCar-v0", "MountainCarContinuous-v0",
     "Acrobot-v1", "CliffWalking-v1"],
)  # fmt: skip
def test_registered_gymnasium_envs_of_every_space_step_and_checkpoint(env_id):
    """Gymnasium's own envs with Discrete / Tuple observations and Discrete / Box actions: built,
    stepped with the policy, their state saved and put back (restart: no get_state)."""
    from rlexp.config.schema import EnvConfig
    from rlexp.envs.factory import make_env
    from rlexp.policies.actor_critic import policy_for_env

    env = make_env(EnvConfig(name=env_id), 2, seed=0)
    pol = policy_for_env(PolicyConfig(), EnvConfig(), env)
    sample = pol.sampling_policy().sampler()
    obs = env.reset()["observation"]
    for _ in range(30):
        nxt = env.step_tensors(sample(obs)[-2])
        obs = env.autoreset_observation(nxt)
    if env_id.startswith("Taxi"):  # info["action_mask"] (issue #48): a TensorDict with the mask
        mask = obs.get("action_mask")
        assert mask.dtype == torch.bool and mask.shape == (2, 6) and mask.any(-1).all()
        obs = obs.get("vector")
    assert obs.dtype == torch.float32 and torch.isfinite(obs).all()
    state = env.env_state()
    env.load_env_state(state)
    assert env.resume_mode.startswith("restarted")
    again = env.reset()["observation"]
    assert (again.get("vector") if env_id.startswith("Taxi") else again).shape == obs.shape
    env.close()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("compile_loss", ["false", "true"])
def test_categorical_ppo_update_on_cuda_matches_cpu(compile_loss):
    """The categorical head and PPO's update on a GPU: the same parameters as on the CPU (float
    tolerance), the sampler's log-probs those of the loss's distribution."""
    from rlexp.algorithms.ppo import make_algorithm

    torch.manual_seed(0)
    envs, steps, nvec = 4, 32, (3, 5)
    cfg = AlgorithmConfig(
        num_epochs=2, mini_batch_size=32, lr=1e-2, entropy_coeff=0.01, compile=compile_loss,
        **PLAIN_PPO,
    )  # fmt: skip
    cpu = _categorical_policy(nvec, n=envs)
    gpu = copy.deepcopy(cpu).cuda()
    obs = torch.randn(envs, steps, 5)
    with torch.no_grad():
        logits, action, log_prob = cpu.sampling_policy().sample(obs)
        g = gpu.sampling_policy().sample(obs.cuda())
        dist = gpu.actor.get_dist(TensorDict({"observation": obs.cuda()}, batch_size=[envs, steps]))
    torch.testing.assert_close(g[2], dist.log_prob(g[1]), rtol=1e-5, atol=1e-5)
    done = torch.zeros(envs, steps, 1, dtype=torch.bool)
    done[1, 9] = True
    batch = TensorDict(
        {
            "observation": obs,
            "action": action,
            "action_log_prob": log_prob,
            "next": {
                "observation": torch.randn(envs, steps, 5),
                "reward": torch.randn(envs, steps, 1),
                "terminated": done,
                "truncated": torch.zeros_like(done),
                "done": done.clone(),
            },
        },
        batch_size=[envs, steps],
    )
    for pol, b in ((cpu, batch), (gpu, batch.to("cuda"))):
        algo = make_algorithm(dataclasses_replace(cfg), pol, total_iterations=10**6)
        torch.manual_seed(5)
        algo.update(b.clone())
    for (name, p), q in zip(cpu.named_parameters(), gpu.parameters(), strict=True):
        torch.testing.assert_close(p, q.cpu(), rtol=1e-3, atol=1e-4, msg=f"{name} differs")


def dataclasses_replace(cfg):
    import dataclasses

    return dataclasses.replace(cfg)


def test_a_get_state_a_checkpoint_cannot_hold_never_fails_a_save(caplog):
    """Mid-run, saving falls back to new episodes on resume (logged once); strict (the config
    check) names the culprit."""
    import toy_envs  # noqa: F401

    from rlexp.envs.gym import GymnasiumEnv

    env = GymnasiumEnv("toy_envs:BadState-v0", num_envs=2)
    env.set_seed(0)
    env.reset()
    with pytest.raises(TypeError, match=r"get_state\(\)\['sim'\] is a object"):
        env.env_state(strict=True)
    with caplog.at_level("WARNING"):
        first, second = env.env_state(), env.env_state()
    assert first["kind"] == second["kind"] == "restart" and env.state_kind == "state"
    assert caplog.text.count("get_state() failed") == 1
    env.load_env_state(first)
    assert env.resume_mode.startswith("restarted")
