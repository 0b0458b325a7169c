"""PPO's options (docs/ppo.md): reward normalisation against NormalizeReward written out by hand and
against Gymnasium's own, its statistics reduced over ranks and checkpointed bit-exactly, reward
clipping, rsl_rl's adaptive learning rate on crafted minibatches, everything off by default, and
train.py with the options on."""

from __future__ import annotations

import copy
import io
import json

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Bounded

from conftest import PLAIN_PPO, REPO, compose, run_train
from rlexp.algorithms import normalize
from rlexp.algorithms.normalize import RewardNormalizer
from rlexp.algorithms.ppo import PPO, adaptive_learning_rate, gaussian_kl
from rlexp.checkpoints.files import latest_checkpoint, load_checkpoint
from rlexp.config.schema import AlgorithmConfig, PolicyConfig
from rlexp.policies.actor_critic import make_policy

OBS, ACT = 5, 2


def _rewards(envs: int, steps: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Rewards [E, T, 1] on a scale far from 1 and dones [E, T, 1] at assorted steps."""
    gen = torch.Generator().manual_seed(seed)
    reward = torch.randn(envs, steps, 1, generator=gen) * 3.0 + 1.5
    done = torch.rand(envs, steps, 1, generator=gen) < 0.1
    return reward, done


def _normalize_reward_by_hand(rollouts, gamma: float, envs: int) -> list[np.ndarray]:
    """SB3 VecNormalize's reward part / CleanRL's NormalizeReward, step by step in numpy, with
    Gymnasium's RunningMeanStd (mean 0, var 1, count 1e-4; one update per step with all envs)."""
    from gymnasium.wrappers.utils import RunningMeanStd

    rms = RunningMeanStd(shape=())
    returns = np.zeros(envs)
    out = []
    for reward, done in rollouts:
        r, d = reward.squeeze(-1).double().numpy(), done.squeeze(-1).numpy()
        scaled = np.empty_like(r)
        for t in range(r.shape[1]):
            returns = returns * gamma + r[:, t]
            rms.update(returns)
            scaled[:, t] = r[:, t] / np.sqrt(rms.var + 1e-8)
            returns[d[:, t]] = 0.0
        out.append(scaled)
    return out, rms


def test_reward_normalizer_equals_normalize_reward_written_by_hand():
    envs, gamma = 3, 0.9
    rollouts = [_rewards(envs, 40, seed) for seed in (0, 1, 2)]  # returns carry across rollouts
    assert all(d.any() for _, d in rollouts)
    norm = RewardNormalizer(gamma)
    mine = [norm.scale(r, d) for r, d in rollouts]
    expected, rms = _normalize_reward_by_hand(rollouts, gamma, envs)
    for got, want in zip(mine, expected, strict=True):
        assert got.shape == (envs, 40, 1) and got.dtype == torch.float32
        np.testing.assert_allclose(got.squeeze(-1).numpy(), want, rtol=1e-6)
    np.testing.assert_allclose(float(norm.mean), rms.mean, rtol=1e-12)
    np.testing.assert_allclose(float(norm.var), rms.var, rtol=1e-12)
    np.testing.assert_allclose(float(norm.count), rms.count, rtol=1e-12)
    assert not np.allclose(expected[0], rollouts[0][0].squeeze(-1).numpy())  # it did scale


def test_reward_normalizer_equals_gymnasiums_normalize_reward_when_episodes_are_truncated():
    """Gymnasium's vector NormalizeReward (autoreset in the same step) is the same wrapper where
    episodes end by truncation (at a termination it drops the return before adding the reward)."""
    import gymnasium as gym
    from gymnasium.vector import AutoresetMode, SyncVectorEnv
    from gymnasium.wrappers.vector import NormalizeReward

    class Scripted(gym.Env):
        observation_space = gym.spaces.Box(-1.0, 1.0, (1,))
        action_space = gym.spaces.Box(-1.0, 1.0, (1,))

        def __init__(self, rewards, truncated):
            self.rewards, self.truncated, self.t = rewards, truncated, 0

        def reset(self, *, seed=None, options=None):
            return np.zeros(1, np.float32), {}

        def step(self, action):
            self.t += 1
            return (
                np.zeros(1, np.float32),
                float(self.rewards[self.t - 1]),
                False,
                bool(self.truncated[self.t - 1]),
                {},
            )

    envs, steps, gamma = 3, 60, 0.95
    reward, done = _rewards(envs, steps, seed=3)
    venv = SyncVectorEnv(
        [
            lambda i=i: Scripted(reward[i, :, 0].tolist(), done[i, :, 0].tolist())
            for i in range(envs)
        ],
        autoreset_mode=AutoresetMode.SAME_STEP,
    )
    wrapped = NormalizeReward(venv, gamma=gamma)
    wrapped.reset(seed=0)
    theirs = np.stack([wrapped.step(np.zeros((envs, 1), np.float32))[1] for _ in range(steps)], 1)
    norm = RewardNormalizer(gamma)
    mine = torch.cat(
        [norm.scale(reward[:, :30], done[:, :30]), norm.scale(reward[:, 30:], done[:, 30:])], 1
    )
    np.testing.assert_allclose(mine.squeeze(-1).numpy(), theirs, rtol=1e-6)


@pytest.mark.parametrize("envs", [1, 5, normalize.PYTHON_LOOP_MAX_ENVS + 1])
def test_running_returns_are_the_same_bits_on_python_floats_and_on_tensors(envs, monkeypatch):
    """Few envs: the returns run env by env on Python floats; many: step by step on tensors. Both
    do the same float64 operations in the same order, so they agree to the bit (and so a run
    resumes exactly whichever way it took)."""
    reward, done = _rewards(envs, 200, seed=4)
    r, ended = reward.squeeze(-1).double(), done.squeeze(-1)
    start = torch.linspace(-3.0, 3.0, envs, dtype=torch.float64)
    got = normalize.discounted_returns(r, ended, start, 0.99)
    monkeypatch.setattr(normalize, "PYTHON_LOOP_MAX_ENVS", -1)  # the tensor loop, always
    want = normalize.discounted_returns(r, ended, start, 0.99)
    assert ended.any()
    for g, w in zip(got, want, strict=True):
        assert g.dtype == torch.float64 and g.shape == w.shape
        assert torch.equal(g, w)


def test_the_statistics_are_summed_over_ranks():
    """Two ranks with the same rollout end with the statistics of one process with both ranks'
    envs: the per-step sums are reduced (once per rollout), the running returns stay per env."""
    reward, done = _rewards(4, 30, seed=4)
    calls = []

    def two_ranks(stats):
        calls.append(stats.shape)
        return stats * 2

    ranked, single = RewardNormalizer(0.99), RewardNormalizer(0.99)
    for _ in range(2):
        got = ranked.scale(reward, done, reduce_sum=two_ranks)
        want = single.scale(torch.cat([reward, reward]), torch.cat([done, done]))
        torch.testing.assert_close(got, want[:4], rtol=1e-6, atol=0)
    assert calls == [(3, 30), (3, 30)]  # one all-reduce of [count, sum, sum of squares] per step
    for key in ("mean", "var", "count"):
        torch.testing.assert_close(getattr(ranked, key), getattr(single, key), rtol=1e-12, atol=0)
    assert ranked.returns.shape == (4,)


def _policy(seed: int = 0):
    torch.manual_seed(seed)
    pol = make_policy(PolicyConfig(), OBS, ACT, Bounded(-1.0, 1.0, shape=(ACT,)))
    pol.normalizer.update(torch.randn(100, OBS) * 2 + 1)
    return pol


def _rollout(pol, seed: int, envs: int = 2, steps: int = 24, loc_shift: float = 0.0) -> TensorDict:
    """A rollout as the collector writes it (the behaviour Gaussian's ``loc`` and ``scale``
    included); ``loc_shift`` moves the behaviour mean away from the current policy's."""
    gen = torch.Generator().manual_seed(seed)
    reward, done = _rewards(envs, steps, seed)
    terminated = done & (torch.rand(done.shape, generator=gen) < 0.5)
    next_obs = torch.randn(envs, steps, OBS, generator=gen)
    obs = torch.randn(envs, steps, OBS, generator=gen)
    obs[:, 1:] = torch.where(done[:, :-1], obs[:, 1:], next_obs[:, :-1])
    with torch.no_grad():
        loc, scale, action, log_prob = pol.sampling_policy().sample(obs)
    return TensorDict(
        {
            "observation": obs,
            "loc": loc + loc_shift,
            "scale": scale,
            "action": action,
            "action_log_prob": log_prob,
            "next": {
                "observation": next_obs,
                "reward": reward,
                "terminated": terminated,
                "truncated": done & ~terminated,
                "done": done,
            },
        },
        batch_size=[envs, steps],
    )


def _cfg(**kw) -> AlgorithmConfig:
    base = {"num_epochs": 2, "mini_batch_size": 12, "lr": 1e-3, "compile": "false", **PLAIN_PPO}
    return AlgorithmConfig(**{**base, **kw})


def _params(pol) -> list[torch.Tensor]:
    return [p.detach().clone() for p in pol.parameters()]


def test_defaults_are_the_references_settings_and_options_off_leave_the_update_unchanged():
    # CleanRL's / SB3's MuJoCo settings: reward scaling, clipped at 10, LR annealing (docs/results.md)
    defaults = (True, 10.0, True, None)
    cfg = AlgorithmConfig()
    assert (cfg.normalize_rewards, cfg.clip_rewards, cfg.anneal_lr, cfg.desired_kl) == defaults
    composed = compose([]).algorithm
    assert (
        composed.normalize_rewards,
        composed.clip_rewards,
        composed.anneal_lr,
        composed.desired_kl,
    ) == defaults
    pol = _policy()
    algo = PPO(_cfg(), pol, 10)
    assert algo.reward_normalizer is None
    assert set(algo.state_dict()) == {"optimizer", "iteration", "hyperparameters"}
    # The options' code path with no effect (a clip no reward reaches) moves the parameters bit
    # for bit as without it: the caller's batch, GAE and the minibatches are what they were.
    batch = _rollout(pol, seed=7)
    other = copy.deepcopy(pol)
    torch.manual_seed(1)
    algo.update(batch.clone())
    torch.manual_seed(1)
    PPO(_cfg(clip_rewards=1e9), other, 10).update(batch.clone())
    for a, b in zip(_params(pol), _params(other), strict=True):
        assert torch.equal(a, b)


def test_clip_rewards_clips_the_normalised_rewards_and_leaves_the_callers_batch_alone():
    pol = _policy()
    batch = _rollout(pol, seed=5)
    raw = batch["next", "reward"].clone()
    clipped = PPO(_cfg(clip_rewards=2.0), pol, 1).scale_rewards(batch)
    torch.testing.assert_close(clipped["next", "reward"], raw.clamp(-2.0, 2.0), rtol=0, atol=0)
    assert (raw.abs() > 2.0).any()
    algo = PPO(_cfg(normalize_rewards=True, clip_rewards=0.5), pol, 1)
    scaled = algo.scale_rewards(batch)
    expected = RewardNormalizer(algo.cfg.gamma).scale(raw, batch["next", "done"]).clamp(-0.5, 0.5)
    torch.testing.assert_close(scaled["next", "reward"], expected, rtol=0, atol=0)
    assert torch.equal(batch["next", "reward"], raw)  # episode statistics read the env's rewards
    metrics = algo.update(batch)
    assert torch.equal(batch["next", "reward"], raw)
    assert metrics["loss/reward_std"] == pytest.approx(algo.reward_normalizer.std())


def _resume_round_trip(cfg: AlgorithmConfig):
    """Update, save, load into a fresh PPO around a copy of the policy, update both: identical."""
    pol = _policy()
    algo = PPO(cfg, pol, 10)
    torch.manual_seed(10)
    algo.update(_rollout(pol, seed=11))
    buffer = io.BytesIO()  # as a checkpoint stores it: weights_only loadable
    torch.save(algo.state_dict(), buffer)
    buffer.seek(0)
    saved = torch.load(buffer, weights_only=True)
    resumed_pol = copy.deepcopy(pol)
    resumed = PPO(cfg, resumed_pol, 10)
    resumed.load_state_dict(saved)
    second = _rollout(pol, seed=12)
    torch.manual_seed(20)
    a = algo.update(second.clone())
    torch.manual_seed(20)
    b = resumed.update(second.clone())
    assert a == b
    for x, y in zip(_params(pol), _params(resumed_pol), strict=True):
        assert torch.equal(x, y)
    return algo, resumed, saved


def test_reward_statistics_and_running_returns_resume_bit_exact():
    algo, resumed, saved = _resume_round_trip(_cfg(normalize_rewards=True, clip_rewards=5.0))
    assert set(saved["reward_normalizer"]) == {"mean", "var", "count", "returns"}
    assert saved["reward_normalizer"]["returns"].shape == (2,)
    mine, theirs = algo.reward_normalizer.state_dict(), resumed.reward_normalizer.state_dict()
    for key in mine:
        assert torch.equal(mine[key], theirs[key]), key


def test_adaptive_learning_rate_resumes_with_the_rate_it_reached():
    algo, resumed, saved = _resume_round_trip(_cfg(desired_kl=0.01, normalize_rewards=True))
    assert saved["hyperparameters"]["lr"] != 1e-3  # it moved, and the checkpoint carries it
    assert algo.cfg.lr == resumed.cfg.lr


@pytest.mark.parametrize(
    ("lr", "kl", "expected"),
    [
        (1e-3, 0.05, 1e-3 / 1.5),  # above 2 x desired: down
        (1.2e-5, 0.05, 1e-5),  # ... not below 1e-5
        (1e-3, 0.001, 1.5e-3),  # below desired / 2: up
        (8e-3, 0.001, 1e-2),  # ... not above 1e-2
        (1e-3, 0.0, 1e-3),  # KL 0: unchanged
        (1e-3, 0.01, 1e-3),  # within [desired / 2, 2 x desired]: unchanged
        (1e-3, 0.02, 1e-3),
        (1e-3, 0.005, 1e-3),
    ],
)
def test_the_adaptive_rule(lr, kl, expected):
    assert adaptive_learning_rate(lr, kl, desired_kl=0.01) == pytest.approx(expected, rel=1e-12)


def test_gaussian_kl_is_the_analytic_kl_with_rsl_rls_epsilon():
    gen = torch.Generator().manual_seed(0)
    old_loc, loc = torch.randn(8, 3, generator=gen), torch.randn(8, 3, generator=gen)
    old_scale, scale = torch.rand(8, 3, generator=gen) + 0.2, torch.rand(8, 3, generator=gen) + 0.2
    exact = torch.distributions.kl_divergence(
        torch.distributions.Normal(old_loc, old_scale), torch.distributions.Normal(loc, scale)
    )
    epsilon = torch.log1p(1e-5 * old_scale / scale)  # log(s/o + 1e-5) - log(s/o)
    torch.testing.assert_close(
        gaussian_kl(old_loc, old_scale, loc, scale), (exact + epsilon).sum(-1).mean()
    )


def _adapted(lr: float, loc_shift: float, epochs: int = 1, minibatches: int = 1):
    """One update with ``desired_kl=0.01`` on a rollout whose behaviour mean is ``loc_shift`` away
    from the policy's; returns the learning rates the optimiser stepped with and the metrics."""
    pol = _policy()
    batch = _rollout(pol, seed=3, loc_shift=loc_shift)
    cfg = _cfg(desired_kl=0.01, lr=lr, num_epochs=epochs, mini_batch_size=48 // minibatches)
    algo = PPO(cfg, pol, 10)
    stepped, step = [], algo.optimizer.step

    def record(*args, **kwargs):
        stepped.append(algo.optimizer.param_groups[0]["lr"])
        return step(*args, **kwargs)

    algo.optimizer.step = record
    metrics = algo.update(batch)
    assert metrics["loss/learning_rate"] == algo.cfg.lr == algo.hyperparameters()["lr"]
    return stepped, metrics


def test_adaptive_kl_lowers_the_rate_of_the_step_when_the_policy_moved_too_far():
    # behaviour mean 3 away with std 1 per dim: KL ~ 9 >> 0.02, every minibatch divides by 1.5
    stepped, _ = _adapted(1e-3, loc_shift=3.0, epochs=2, minibatches=2)
    assert stepped == pytest.approx([1e-3 / 1.5**k for k in (1, 2, 3, 4)], rel=1e-12)
    stepped, _ = _adapted(1.2e-5, loc_shift=3.0)
    assert stepped == [1e-5]


def test_adaptive_kl_raises_the_rate_when_the_policy_stays_close():
    # behaviour mean 0.01 away: KL ~ 1e-4 + rsl_rl's 2e-5 < 0.005
    stepped, _ = _adapted(1e-3, loc_shift=0.01)
    assert stepped == pytest.approx([1.5e-3], rel=1e-12)
    stepped, _ = _adapted(8e-3, loc_shift=0.01)
    assert stepped == [1e-2]
    stepped, _ = _adapted(1e-3, loc_shift=0.1)  # KL ~ 0.01: within the band, unchanged
    assert stepped == [1e-3]


def test_adaptive_kl_with_lr_annealing_is_refused_naming_both_keys():
    with pytest.raises(
        ValueError, match=r"algorithm\.desired_kl=0\.01 and algorithm\.anneal_lr=true"
    ):
        PPO(_cfg(desired_kl=0.01, anneal_lr=True), _policy(), 10)


# Two ranks, each its own rollout, through the trainer's collectives: the same reward statistics
# and the same learning rate on both (else the parameters drift apart).
_WORKER = """
import sys
import torch
from rlexp.algorithms.ppo import PPO
from rlexp.runtime import distributed
sys.path.insert(0, sys.argv[2])
from test_ppo_options import _cfg, _policy, _rollout

distributed.init_in_job()
rank = distributed.info().rank
pol = _policy()  # the same initial parameters on both ranks
algo = PPO(_cfg(normalize_rewards=True, desired_kl=0.01), pol, 10, grad_sync=distributed.all_reduce_mean_)
batches = [_rollout(pol, seed=100 * rank + i) for i in range(2)]
for batch in batches:
    algo.update(batch.clone())
torch.save(
    {"batches": batches, "normalizer": algo.reward_normalizer.state_dict(), "lr": algo.cfg.lr,
     "params": [p.detach() for p in pol.parameters()]},
    sys.argv[1] + f"/rank{rank}.pt",
)
distributed.shutdown()
"""


def test_two_ranks_share_the_reward_statistics_and_the_learning_rate(tmp_path):
    from test_distributed import run_worker_on_two_ranks

    run_worker_on_two_ranks(_WORKER, [str(tmp_path), str(REPO / "tests")])
    ranks = [torch.load(tmp_path / f"rank{r}.pt", weights_only=False) for r in (0, 1)]
    single = RewardNormalizer(AlgorithmConfig().gamma)  # one process with both ranks' envs
    for i in range(2):
        both = [
            torch.cat([r["batches"][i]["next", key] for r in ranks]) for key in ("reward", "done")
        ]
        single.scale(*both)
    for key in ("mean", "var", "count"):
        a, b = (r["normalizer"][key] for r in ranks)
        assert torch.equal(a, b), key
        torch.testing.assert_close(a, getattr(single, key), rtol=1e-12, atol=0)
    assert not torch.equal(ranks[0]["normalizer"]["returns"], ranks[1]["normalizer"]["returns"])
    assert ranks[0]["lr"] == ranks[1]["lr"] != 1e-3
    for a, b in zip(ranks[0]["params"], ranks[1]["params"], strict=True):
        assert torch.equal(a, b)


def test_train_py_with_the_options_on_adapts_the_learning_rate_and_resumes_bit_exact(tmp_path):
    """Four updates in one run; two, then two more resumed from its checkpoint: the same policy,
    learning rate and reward statistics at the end."""
    options = [
        "env=inverted_pendulum",
        "trainer.frames_per_batch=256",
        "trainer.save_every=512",
        "trainer.eval_every=0",
        "algorithm.num_epochs=2",
        "trainer.progress=false",
        "seed=5",
        "algorithm.normalize_rewards=true",
        "algorithm.clip_rewards=10",
        "algorithm.desired_kl=0.01",
        "algorithm.anneal_lr=false",  # the adaptive rate is the one LR controller
    ]
    whole, broken = tmp_path / "whole", tmp_path / "broken"
    run_train([*options, "trainer.total_frames=1024", f"hydra.run.dir={whole}"], cwd=tmp_path)
    rows = [json.loads(line) for line in (whole / "metrics.jsonl").read_text().splitlines()]
    rates = [r["loss/learning_rate"] for r in rows if "loss/learning_rate" in r]
    assert len(rates) == 4 and all(1e-5 <= lr <= 1e-2 for lr in rates), rates
    assert len(set(rates)) > 1 and rates[0] != 3e-4, rates  # moved by the KL rule
    assert all(r["loss/reward_std"] > 0 for r in rows if "loss/learning_rate" in r)
    # train/ keeps the env's rewards: InvertedPendulum-v5 gives 1 per step but 0 at termination
    episodes = [r for r in rows if "train/episode_return" in r]
    assert episodes
    for r in episodes:
        assert r["train/episode_return"] == pytest.approx(r["train/episode_length"] - 1.0)

    run_train([*options, "trainer.total_frames=512", f"hydra.run.dir={broken}"], cwd=tmp_path)
    proc = run_train(
        [*options, "trainer.total_frames=1024", f"hydra.run.dir={broken}"], cwd=tmp_path
    )
    assert "[resume] continuing from" in proc.stdout + proc.stderr
    a, b = (load_checkpoint(latest_checkpoint(d / "checkpoints")) for d in (whole, broken))
    assert a["global_step"] == b["global_step"] == 1024
    for key, value in a["policy"].items():
        assert torch.equal(value, b["policy"][key]), f"policy.{key} differs after resume"
    assert a["algorithm"]["hyperparameters"] == b["algorithm"]["hyperparameters"]
    assert a["algorithm"]["hyperparameters"]["lr"] == rates[-1]
    for key, value in a["algorithm"]["reward_normalizer"].items():
        assert torch.equal(value, b["algorithm"]["reward_normalizer"][key]), key
    assert a["algorithm"]["reward_normalizer"]["count"] > 1024


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (["algorithm.desired_kl=0.01", "algorithm.anneal_lr=true"], "both set the learning rate"),
        (["algorithm.desired_kl=0.01", "hooks=lr_anneal"], "hooks.lr_anneal (a schedule of lr)"),
    ],
    ids=["anneal_lr", "lr-hook"],
)
def test_two_learning_rate_controllers_are_refused_before_the_run(overrides, message):
    import re

    from conftest import compose
    from rlexp.config.validate import ConfigError, to_root_config

    with pytest.raises(ConfigError, match=re.escape(message)):
        to_root_config(compose(overrides))
