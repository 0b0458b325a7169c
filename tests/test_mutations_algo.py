"""Every PPO / GRPO option and the observation normaliser's, set off its default to an asymmetric
value, checked against an independent expectation: the textbook formula in plain torch, a plain-torch
update (``test_ppo_math`` / ``test_grpo_math``'s references), numpy statistics, or literals.

Written so that a bug which hard-codes an option's default, drops it on the way to TorchRL, or swaps
two fields fails here (issue #35). Each test names the mutations it was checked against in its
docstring; the recipe is a copy of the tree with the bug put in, and this file run against it."""

from __future__ import annotations

import copy
import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from test_grpo_math import _reference_grpo_update
from test_grpo_math import _rollout as _grpo_rollout
from test_ppo_math import _reference_ppo_update
from test_ppo_options import _normalize_reward_by_hand, _rewards, _rollout
from torchrl.data import Bounded

from conftest import PLAIN_PPO, compose
from rlexp.algorithms import make_algorithm
from rlexp.algorithms.fused_step import STEP_STATS, FusedPPOStep
from rlexp.config.schema import ActorOnlyConfig, AlgorithmConfig, GRPOConfig, PolicyConfig
from rlexp.policies.actor_critic import make_policy

OBS, ACT = 5, 2  # test_ppo_options' _rollout makes observations of 5 and actions of 2


# -- ClipPPOLoss as configured, one minibatch against the formulas ------------------------------------
def _minibatch(seed: int, n: int = 64, **cfg_kw):
    """A Gaussian policy, the PPO built on it with ``cfg_kw`` and a minibatch whose old log-probs
    are off by ~0.3 (ratios spread over [0.5, 2]), advantages of mean 0.5 and std 2, value targets
    and old values. Returns (policy, algorithm, minibatch, plain-torch pieces)."""
    torch.manual_seed(seed)
    pol = make_policy(PolicyConfig(), OBS, ACT, Bounded(-1.0, 1.0, shape=(n, ACT)))
    with torch.no_grad():
        pol.actor_net.log_std.copy_(torch.tensor([-0.3, 0.2]))
    pol.normalizer.update(torch.randn(100, OBS) * 2 + 1)
    cfg = AlgorithmConfig(compile="false", **{**PLAIN_PPO, **cfg_kw})
    algo = make_algorithm(cfg, pol, total_iterations=1)
    obs = torch.randn(n, OBS)
    with torch.no_grad():
        td = pol.sampling_policy()(TensorDict({"observation": obs}, batch_size=[n]))
        value_now = pol.critic_net(obs)
    old_log_prob = td["action_log_prob"] + 0.3 * torch.randn(n)
    advantage = torch.randn(n, 1) * 2 + 0.5
    value_target = value_now + torch.randn(n, 1) * 1.5  # |V - target| above and below 1
    old_value = value_now + torch.randn(n, 1) * 0.3  # V - V_old above and below clip_value
    batch = TensorDict(
        {
            "observation": obs,
            "action": td["action"],
            "action_log_prob": old_log_prob,
            "advantage": advantage,
            "value_target": value_target,
            "state_value": old_value,
        },
        batch_size=[n],
    )
    with torch.no_grad():  # (the loss's gradients are test_ppo_math's business)
        loc, scale = pol.actor_net(obs)
    dist = torch.distributions.Normal(loc, scale)
    ref = {
        "ratio": torch.exp(dist.log_prob(td["action"]).sum(-1) - old_log_prob),
        "entropy": dist.entropy().sum(-1),
        "value": value_now,
        "adv": advantage.squeeze(-1),
        "target": value_target,
        "old_value": old_value,
    }
    return pol, algo, batch, ref


def _surrogate(ratio, adv, eps):
    """PPO-clip's objective as a loss (Schulman et al. 2017, eq. 7)."""
    return -torch.min(ratio * adv, ratio.clamp(1 - eps, 1 + eps) * adv).mean()


def _normalised(adv):
    return (adv - adv.mean()) / adv.std()


def test_the_loss_uses_the_configured_clip_epsilon_and_coefficients():
    """clip_epsilon 0.07, critic_coeff 0.35, entropy_coeff 0.013 (none the default, all different).

    Catches: ClipPPOLoss built with clip_epsilon=0.2 (issue #35), critic_coeff / entropy_coeff
    hard-coded to their defaults, critic_coeff and entropy_coeff swapped."""
    _, algo, batch, ref = _minibatch(0, clip_epsilon=0.07, critic_coeff=0.35, entropy_coeff=0.013)
    out = algo.loss(batch.clone())
    adv, ratio = _normalised(ref["adv"]), ref["ratio"]
    expected = _surrogate(ratio, adv, 0.07)
    # Non-vacuous: ratios between the two clip ranges, where the clipped term is the minimum, make
    # the default's objective differ from this one by far more than the tolerance.
    between = ((ratio > 1.07) & (ratio < 1.2) & (adv > 0)) | (
        (ratio < 0.93) & (ratio > 0.8) & (adv < 0)
    )
    assert between.sum() >= 3
    assert abs(float(_surrogate(ratio, adv, 0.2) - expected)) > 1e-3
    torch.testing.assert_close(out["loss_objective"], expected, rtol=1e-5, atol=1e-6)
    mse = (ref["value"] - ref["target"]).pow(2).mean()  # TorchRL's "l2" is the plain MSE
    torch.testing.assert_close(out["loss_critic"], 0.35 * mse, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(
        out["loss_entropy"], -0.013 * ref["entropy"].mean(), rtol=1e-5, atol=1e-6
    )


@pytest.mark.parametrize("kind", ["l1", "smooth_l1"])
def test_loss_critic_type_is_the_configured_distance(kind):
    """l1: |V - target|; smooth_l1: Huber with beta 1 (0.5 d^2 below 1, |d| - 0.5 above).

    Catches: loss_critic_type hard-coded to "l2" (or not passed to ClipPPOLoss), l1 and smooth_l1
    swapped."""
    _, algo, batch, ref = _minibatch(1, critic_coeff=0.8, loss_critic_type=kind)
    d = (ref["value"] - ref["target"]).abs()
    assert (d < 1).any() and (d > 1).any()  # both branches of the Huber loss
    distance = d if kind == "l1" else torch.where(d < 1, 0.5 * d.pow(2), d - 0.5)
    out = algo.loss(batch.clone())
    torch.testing.assert_close(out["loss_critic"], 0.8 * distance.mean(), rtol=1e-5, atol=1e-6)


def test_without_advantage_normalisation_the_raw_advantages_weight_the_ratio():
    """normalize_advantage=false: the surrogate of the advantages as given (mean 0.5, std 2).

    Catches: normalize_advantage hard-coded to true (the default) or not passed to ClipPPOLoss."""
    _, algo, batch, ref = _minibatch(2, normalize_advantage=False, clip_epsilon=0.15)
    out = algo.loss(batch.clone())
    expected = _surrogate(ref["ratio"], ref["adv"], 0.15)
    assert abs(float(_surrogate(ref["ratio"], _normalised(ref["adv"]), 0.15) - expected)) > 1e-2
    torch.testing.assert_close(out["loss_objective"], expected, rtol=1e-5, atol=1e-6)


def test_value_clipping_takes_the_larger_of_the_clipped_and_unclipped_errors():
    """clip_value 0.2: V_clip = V_old + clamp(V - V_old, -0.2, 0.2); the critic loss is the mean of
    max((V - target)^2, (V_clip - target)^2) (the PPO2 / CleanRL value clipping).

    Catches: clip_value dropped (None, the default) or not passed to ClipPPOLoss."""
    _, algo, batch, ref = _minibatch(3, clip_value=0.2, critic_coeff=0.6)
    value, old, target = ref["value"], ref["old_value"], ref["target"]
    clipped = old + (value - old).clamp(-0.2, 0.2)
    plain, clip = (value - target).pow(2), (clipped - target).pow(2)
    assert (clip > plain + 1e-3).any() and ((value - old).abs() > 0.2).any()
    expected = 0.6 * torch.maximum(plain, clip).mean()
    assert abs(float(expected - 0.6 * plain.mean())) > 1e-3
    out = algo.loss(batch.clone())
    torch.testing.assert_close(out["loss_critic"], expected, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize(
    ("name", "value"), [("clip_epsilon", 0.05), ("critic_coeff", 1.7), ("entropy_coeff", 0.04)]
)
def test_set_hyperparameter_reaches_the_loss(name, value):
    """A hook's ``set`` lands in ``set_hyperparameter``: the loss computes with the new value.

    Catches: PPO._applied without critic_coeff (a hook's critic_coeff never reaching the loss,
    issue #35), or without clip_epsilon / entropy_coeff."""
    start = {"clip_epsilon": 0.12, "critic_coeff": 0.3, "entropy_coeff": 0.01}
    _, algo, batch, ref = _minibatch(4, **start)
    algo.set_hyperparameter(name, value)
    now = {**start, name: value}
    out = algo.loss(batch.clone())
    mse = (ref["value"] - ref["target"]).pow(2).mean()
    expected = {
        "loss_objective": _surrogate(ref["ratio"], _normalised(ref["adv"]), now["clip_epsilon"]),
        "loss_critic": now["critic_coeff"] * mse,
        "loss_entropy": -now["entropy_coeff"] * ref["entropy"].mean(),
    }
    for key, want in expected.items():
        torch.testing.assert_close(out[key], want, rtol=1e-5, atol=1e-6, msg=key)
    assert algo.hyperparameters()[name] == value


# -- whole updates against the plain-torch references -------------------------------------------------
#: every option the plain-torch PPO implements, off its default, no two alike
PPO_OFF_DEFAULT = {
    "gamma": 0.8,
    "lmbda": 0.6,
    "clip_epsilon": 0.07,
    "entropy_coeff": 0.013,
    "critic_coeff": 0.35,
    "lr": 5e-3,
    "adam_eps": 1e-3,
    "max_grad_norm": 0.15,
    "num_epochs": 3,
    "mini_batch_size": 16,
}


def _ppo_update_against_reference(cfg: AlgorithmConfig, ref_cfg: AlgorithmConfig, reward=None,
                                  set_after_build: dict | None = None):  # fmt: skip
    """One rlexp update (built with ``cfg``, then ``set_hyperparameter`` for ``set_after_build``)
    and the plain-torch PPO with ``ref_cfg`` on the same rollout (``reward``: the rewards the
    reference learns from, when they differ from the rollout's). Returns the metrics."""
    torch.manual_seed(0)
    pol = make_policy(PolicyConfig(), OBS, ACT, Bounded(-1.0, 1.0, shape=(ACT,)))
    pol.normalizer.update(torch.randn(100, OBS) * 2 + 1)
    batch = _rollout(pol, seed=5, envs=2, steps=24)
    with torch.no_grad():  # ratios leave the clip range from the first minibatch on
        batch["action_log_prob"] += 0.2 * torch.randn(batch.shape)
    ref_batch = batch.clone()
    if reward is not None:
        ref_batch["next", "reward"] = reward
    ref_pol, initial = copy.deepcopy(pol), copy.deepcopy(pol)
    algo = make_algorithm(cfg, pol, total_iterations=10)
    for name, value in (set_after_build or {}).items():
        algo.set_hyperparameter(name, value)
    torch.manual_seed(123)
    metrics = algo.update(batch.clone())
    expected = _reference_ppo_update(ref_pol, ref_batch, ref_cfg, seed=123)
    assert metrics["loss/value"] == pytest.approx(expected["value"], rel=1e-4, abs=1e-6)
    assert metrics["loss/policy"] == pytest.approx(expected["policy"], rel=1e-4, abs=1e-6)
    assert metrics["loss/entropy"] == pytest.approx(expected["entropy"], rel=1e-4, abs=1e-6)
    for (name, p), r, p0 in zip(
        pol.named_parameters(), ref_pol.parameters(), initial.parameters(), strict=True
    ):
        torch.testing.assert_close(p, r, rtol=1e-4, atol=1e-5, msg=f"parameter {name} differs")
        # (Adam's eps 1e-3 slows the actor's last layer, whose gradients are small: 10 x atol)
        assert (p - p0).abs().max() > 1e-4, f"{name} did not move: the comparison would be vacuous"
    return metrics


def test_ppo_update_with_every_option_off_its_default_matches_plain_torch_ppo():
    """GAE's gamma and lambda, the clip, both coefficients, Adam's lr and eps, gradient clipping,
    epochs and minibatch size all at once, none at its default, against the hand-written PPO.

    Catches: any of them hard-coded to its default in GAE / ClipPPOLoss / Adam / the guarded step /
    the epoch loop; gamma and lmbda swapped in GAE; adam_eps not passed to Adam."""
    cfg = AlgorithmConfig(compile="false", **{**PLAIN_PPO, **PPO_OFF_DEFAULT})
    metrics = _ppo_update_against_reference(cfg, cfg)
    assert metrics["loss/grad_norm"] > 2 * PPO_OFF_DEFAULT["max_grad_norm"]  # clipping was on


def test_hyperparameters_set_after_the_build_are_the_ones_the_next_update_uses():
    """All of PPO's mutable hyperparameters changed by ``set_hyperparameter`` (what a hook's
    ``control.set`` does before an update) after the learner was built with other values: the
    update is the plain-torch PPO's with the new values.

    Catches: critic_coeff (issue #35), clip_epsilon, entropy_coeff, lr or max_grad_norm set in
    ``self.cfg`` but not pushed to the loss / optimiser, or read once at build time."""
    built = AlgorithmConfig(
        compile="false",
        **{**PLAIN_PPO, **PPO_OFF_DEFAULT, "clip_epsilon": 0.3, "entropy_coeff": 0.0,
           "critic_coeff": 0.9, "lr": 1e-4, "max_grad_norm": 5.0},
    )  # fmt: skip
    new = {"clip_epsilon": 0.07, "entropy_coeff": 0.013, "critic_coeff": 0.35, "lr": 5e-3,
           "max_grad_norm": 0.15}  # fmt: skip
    _ppo_update_against_reference(built, dataclasses.replace(built, **new), set_after_build=new)


@pytest.mark.parametrize(
    ("normalize", "clip"), [(True, None), (False, 0.6), (True, 0.6)], ids=["scale", "clip", "both"]
)
def test_ppo_update_learns_from_the_scaled_and_clipped_rewards(normalize, clip):
    """normalize_rewards / clip_rewards with gamma 0.8: the update is the plain-torch PPO on the
    rewards scaled by NormalizeReward written by hand (Gymnasium's RunningMeanStd, discount 0.8)
    and clamped to +-0.6.

    Catches: the reward normaliser built with gamma 0.99 instead of algorithm.gamma; the scaled
    batch not reaching GAE; clip_rewards hard-coded to 10 (the default) or ignored; the clip
    applied before the scaling."""
    gamma = PPO_OFF_DEFAULT["gamma"]
    raw, done = _rewards(2, 24, seed=5)  # the rollout's rewards and dones (_rollout's seed 5)
    reward = raw
    if normalize:
        scaled, _ = _normalize_reward_by_hand([(raw, done)], gamma, envs=2)
        reward = torch.from_numpy(scaled[0]).float().unsqueeze(-1)
        assert not torch.allclose(reward, raw, atol=0.1)  # it scaled
    if clip is not None:
        assert (reward.abs() > clip).any() and (reward.abs() < clip).any()
        reward = reward.clamp(-clip, clip)
    cfg = AlgorithmConfig(
        compile="false",
        **{**PPO_OFF_DEFAULT, "anneal_lr": False, "normalize_rewards": normalize,
           "clip_rewards": clip},
    )  # fmt: skip
    metrics = _ppo_update_against_reference(cfg, cfg, reward=reward)
    if normalize:
        assert "loss/reward_std" in metrics


def _learning_rates(name: str, anneal: bool, fused: bool = True) -> tuple[list[float], list[float]]:
    """Four updates of a PPO or GRPO with lr 2e-3 over a run of 4 iterations: the learning rate
    each optimiser step took, and the one each update logged (PPO: the fused minibatch step or
    TorchRL's ClipPPOLoss path, ``fused``)."""
    torch.manual_seed(0)
    if name == "ppo":
        pol = make_policy(PolicyConfig(), OBS, ACT, Bounded(-1.0, 1.0, shape=(ACT,)))
        cfg = AlgorithmConfig(
            lr=2e-3, anneal_lr=anneal, normalize_rewards=False, clip_rewards=None, num_epochs=1,
            mini_batch_size=48, compile="false",
        )  # fmt: skip
        batches = [_rollout(pol, seed=i, envs=2, steps=24) for i in range(4)]
    else:
        pol = make_policy(ActorOnlyConfig(), 3, 2, Bounded(-1.0, 1.0, shape=(2,)))
        cfg = GRPOConfig(
            lr=2e-3, anneal_lr=anneal, group_size=2, num_epochs=1, mini_batch_size=16,
            compile="false",
        )  # fmt: skip
        batches = [_grpo_rollout(pol, envs=4, steps=4) for _ in range(4)]
    algo = make_algorithm(cfg, pol, total_iterations=4)
    algo.use_fused_step = fused
    stepped: list[float] = []
    # A step pre-hook: optimizer.step() runs it, and so does the fused step before its Adam
    algo.optimizer.register_step_pre_hook(
        lambda opt, args, kwargs: stepped.append(opt.param_groups[0]["lr"])
    )
    logged = [algo.update(batch)["loss/learning_rate"] for batch in batches]
    return stepped, logged


@pytest.mark.parametrize("name", ["ppo", "grpo", "ppo_clipppoloss"])
@pytest.mark.parametrize("anneal", [True, False])
def test_anneal_lr_decays_linearly_to_zero_over_the_run(name, anneal):
    """anneal_lr with 4 iterations and lr 2e-3: the steps of update k use 2e-3 * (1 - k / 4)
    (CleanRL's schedule); without it, 2e-3 every time.

    Catches: anneal_lr ignored (PPO or GRPO), forced on, or annealing from the second update."""
    want = [2e-3, 1.5e-3, 1e-3, 5e-4] if anneal else [2e-3] * 4
    stepped, logged = _learning_rates(name.split("_")[0], anneal, fused=name == "ppo")
    assert len(stepped) == 4  # one minibatch per update
    assert stepped == pytest.approx(want, rel=1e-12)
    assert logged == pytest.approx(want, rel=1e-12)


def _grpo_against_reference(cfg: GRPOConfig, envs: int = 6, set_after_build: dict | None = None,
                            ref_cfg: GRPOConfig | None = None):  # fmt: skip
    torch.manual_seed(0)
    pol = make_policy(ActorOnlyConfig(), 3, 2, Bounded(-1.0, 1.0, shape=(2,)))
    pol.normalizer.update(torch.randn(100, 3) * 2 + 1)
    initial = copy.deepcopy(pol)
    algo = make_algorithm(cfg, pol, total_iterations=10)
    for name, value in (set_after_build or {}).items():
        algo.set_hyperparameter(name, value)
    batch = _grpo_rollout(pol, envs=envs, steps=8, log_prob_noise=0.3)
    ref_pol, before = copy.deepcopy(pol), copy.deepcopy(pol)
    torch.manual_seed(123)
    metrics = algo.update(batch.clone())
    expected, mask_fraction = _reference_grpo_update(ref_pol, initial, batch, ref_cfg or cfg, 123)
    assert metrics["grpo/mask_fraction"] == pytest.approx(mask_fraction)
    assert metrics["loss/policy"] == pytest.approx(expected["policy"], rel=1e-4, abs=1e-6)
    assert metrics["loss/entropy"] == pytest.approx(expected["entropy"], rel=1e-4, abs=1e-6)
    assert metrics["loss/kl_ref"] == pytest.approx(expected["kl_ref"], rel=1e-4, abs=1e-7)
    for (name, p), r, p0 in zip(
        pol.named_parameters(), ref_pol.parameters(), before.parameters(), strict=True
    ):
        torch.testing.assert_close(p, r, rtol=1e-5, atol=1e-5, msg=f"parameter {name} differs")
        assert (p - p0).abs().max() > 1e-3, f"{name} did not move: the comparison would be vacuous"
    return metrics, mask_fraction


#: every GRPO option the plain-torch GRPO implements, off its default, no two alike
GRPO_OFF_DEFAULT = {
    "gamma": 0.85,
    "group_size": 3,
    "kl_coeff": 0.25,
    "epsilon": 0.3,  # large against the returns' std: a hard-coded 1e-8 changes every advantage
    "clip_epsilon": 0.11,
    "entropy_coeff": 0.02,
    "lr": 7e-3,
    "adam_eps": 1e-3,
    "max_grad_norm": 0.09,
    "num_epochs": 3,
    "mini_batch_size": 16,
    "truncate_at_first_done": False,
}


def test_grpo_update_with_every_option_off_its_default_matches_plain_torch_grpo():
    """Group size, discount, std epsilon, truncation, clip, coefficients, Adam and gradient
    clipping all off their defaults at once, against the hand-written GRPO.

    Catches: any of them hard-coded to its default (clip_epsilon 0.2, max_grad_norm 0.5, adam_eps
    1e-5, epsilon 1e-8, truncate_at_first_done true, group_size 4, ...) or two of them swapped."""
    cfg = GRPOConfig(compile="false", **GRPO_OFF_DEFAULT)
    metrics, mask_fraction = _grpo_against_reference(cfg)
    assert mask_fraction == 1.0  # no truncation: every step counts
    assert metrics["loss/grad_norm"] > 2 * GRPO_OFF_DEFAULT["max_grad_norm"]  # clipping was on


def test_grpo_hyperparameters_set_after_the_build_are_the_ones_the_next_update_uses():
    """GRPO's mutable hyperparameters changed by ``set_hyperparameter`` after the build: the update
    is the plain-torch GRPO's with the new values.

    Catches: any of lr, clip_epsilon, entropy_coeff, max_grad_norm, kl_coeff read once at build
    time instead of from the learner's current values."""
    built = GRPOConfig(
        compile="false",
        **{**GRPO_OFF_DEFAULT, "truncate_at_first_done": True, "lr": 1e-4, "clip_epsilon": 0.3,
           "entropy_coeff": 0.0, "max_grad_norm": 5.0, "kl_coeff": 1.5},
    )  # fmt: skip
    new = {"lr": 7e-3, "clip_epsilon": 0.11, "entropy_coeff": 0.02, "max_grad_norm": 0.09,
           "kl_coeff": 0.25}  # fmt: skip
    _, mask_fraction = _grpo_against_reference(
        built, set_after_build=new, ref_cfg=dataclasses.replace(built, **new)
    )
    assert 0.0 < mask_fraction < 1.0


# -- through the Trainer: hooks, and the observation normaliser's place in the loop -------------------
TINY = [
    "env=inverted_pendulum",
    "trainer.frames_per_batch=256",
    "trainer.eval_every=0",
    "trainer.save_every=0",
    "algorithm.num_epochs=2",
    "algorithm.mini_batch_size=128",
    "algorithm.compile=false",
    "logger=none",
    "trainer.progress=false",
]


def _trainer(tmp_path: Path, overrides: list[str]):
    """A Trainer built as ``train.py`` builds it (the real config wiring), logging nowhere."""
    from rlexp.config.validate import to_root_config
    from rlexp.run.metrics import MetricLogger
    from rlexp.training.build import build

    config = to_root_config(compose([*TINY, *overrides]))
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    objects = build(config, run_dir, "cpu", config.trainer.total_frames)
    return objects.trainer(MetricLogger([]), {}, {}), config


@pytest.mark.parametrize("fused", [True, False], ids=["fused", "clipppoloss"])
def test_a_critic_coeff_schedule_is_the_coefficient_of_the_next_updates_critic_loss(
    tmp_path, monkeypatch, fused
):
    """A schedule hook of critic_coeff from 2.0 to 0.25 over 768 steps: in every minibatch of the
    update after step s, loss_critic = (2.0 - 1.75 s / 768) x mean((V(s) - value_target)^2), V
    evaluated in plain torch on the minibatch; on the fused minibatch step and on TorchRL's
    ClipPPOLoss path.

    Catches: a hook's set("critic_coeff") never reaching the loss (issue #35); hook decisions
    applied after the update instead of before it."""
    trainer, config = _trainer(
        tmp_path,
        ["trainer.total_frames=768", "algorithm.critic_coeff=0.7", "+hooks.vf.func=schedule",
         "+hooks.vf.params.name=critic_coeff", "+hooks.vf.params.start=2.0",
         "+hooks.vf.params.end=0.25", "algorithm.compile=false"],
    )  # fmt: skip
    critic = trainer.policy.critic_net
    seen: list[tuple[int, float]] = []  # (global step, loss_critic / MSE) per minibatch

    def record(obs, value_target, loss_critic):
        with torch.no_grad():
            mse = (critic(obs) - value_target).pow(2).mean()
        seen.append((trainer.global_step, float(loss_critic.detach() / mse)))

    trainer.algorithm.use_fused_step = fused
    handle = None
    if fused:  # the fused step's loss: (total, stats), stats[1] = loss_critic
        fused_loss = FusedPPOStep.loss

        def spy_fused(self, obs, action, old_lp, adv, value_target, *rest):
            total, stats = fused_loss(self, obs, action, old_lp, adv, value_target, *rest)
            record(obs, value_target, stats[STEP_STATS.index("loss_critic")])
            return total, stats

        monkeypatch.setattr(FusedPPOStep, "loss", spy_fused)
    else:
        handle = trainer.algorithm.loss.register_forward_hook(
            lambda module, args, out: record(
                args[0]["observation"], args[0]["value_target"], out["loss_critic"]
            )
        )
    try:
        trainer.train(config.trainer.total_frames)
    finally:
        if handle is not None:
            handle.remove()
        trainer.close()
    assert (trainer.algorithm.fused is not None) == fused
    steps = [256, 512, 768]
    assert [s for s, _ in seen] == [s for s in steps for _ in range(4)]  # 2 epochs x 2 minibatches
    expected = [2.0 - 1.75 * s / 768 for s in steps for _ in range(4)]
    assert [c for _, c in seen] == pytest.approx(expected, rel=1e-5)


def test_the_observation_normaliser_folds_a_rollout_in_after_its_update(tmp_path):
    """ObservationNormalizer's contract: updated once per rollout, after the PPO update. During the
    update of rollout k the statistics are numpy's mean / variance of rollouts 0..k-1 (none: mean
    0, variance 1, count 0); after the run, of all of them; the normalised observation is
    clip((x - mean) / sqrt(var + 1e-8), -1.5, +1.5) with env.clip_observations=1.5.

    Catches: the normaliser updated before the PPO update (issue #35), twice per rollout, or
    never; env.clip_observations not reaching the policy (10, the default)."""
    trainer, config = _trainer(tmp_path, ["trainer.total_frames=768", "env.clip_observations=1.5"])
    norm = trainer.policy.normalizer
    seen, observations = [], []
    update = trainer.algorithm.update

    def spy(batch):
        seen.append((norm.mean.clone(), norm.var.clone(), float(norm.count)))
        observations.append(batch["observation"].reshape(-1, batch["observation"].shape[-1]))
        return update(batch)

    trainer.algorithm.update = spy
    try:
        trainer.train(config.trainer.total_frames)
    finally:
        trainer.close()
    assert len(seen) == 3
    dim = observations[0].shape[-1]
    np.testing.assert_array_equal(seen[0][0].numpy(), np.zeros(dim))
    np.testing.assert_array_equal(seen[0][1].numpy(), np.ones(dim))
    assert seen[0][2] == 0.0
    for k in (1, 2):
        before = torch.cat(observations[:k]).double().numpy()
        np.testing.assert_allclose(seen[k][0].numpy(), before.mean(0), rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(seen[k][1].numpy(), before.var(0), rtol=1e-9, atol=1e-12)
        assert seen[k][2] == 256 * k
    every = torch.cat(observations).double().numpy()
    mean, var = every.mean(0), every.var(0)
    np.testing.assert_allclose(norm.mean.numpy(), mean, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(norm.var.numpy(), var, rtol=1e-9, atol=1e-12)
    assert float(norm.count) == 768
    x = torch.cat(observations)
    z = (x.double().numpy() - mean) / np.sqrt(var + 1e-8)
    assert (np.abs(z) > 1.5).any() and (np.abs(z) < 1.5).any()
    np.testing.assert_allclose(norm(x).numpy(), np.clip(z, -1.5, 1.5), rtol=1e-5, atol=1e-5)


def test_without_observation_normalisation_the_networks_see_the_raw_observations(tmp_path):
    """env.normalize_observations=false: after a run the statistics are untouched and the actor
    and critic compute on the observations as the env gives them, unclipped (large inputs
    included).

    Catches: env.normalize_observations not reaching the policy (normalising anyway, the
    default), the disabled normaliser still folding rollouts in or clipping."""
    trainer, config = _trainer(
        tmp_path, ["trainer.total_frames=256", "env.normalize_observations=false"]
    )
    try:
        trainer.train(config.trainer.total_frames)
    finally:
        trainer.close()
    pol = trainer.policy
    assert float(pol.normalizer.count) == 0.0
    x = torch.randn(32, pol.normalizer.mean.shape[0]) * 30.0  # far beyond any clip
    torch.testing.assert_close(pol.normalizer(x), x, rtol=0, atol=0)
    with torch.no_grad():
        torch.testing.assert_close(pol.critic_net(x), pol.critic_net.mlp(x), rtol=0, atol=0)


@pytest.mark.parametrize(("shift", "rate"), [(0.2, 1e-3), (0.1, 1.5e-3)], ids=["in-band", "below"])
def test_adaptive_lr_compares_the_kl_with_the_configured_target(shift, rate):
    """desired_kl 0.05 (test_ppo_options uses 0.01): a behaviour mean 0.2 away (KL ~0.04) is
    within [0.025, 0.1], the rate stays; 0.1 away (KL ~0.01) is below 0.025, the rate goes up 1.5x.
    With a target of 0.01 both would go the other way.

    Catches: desired_kl hard-coded to 0.01 (or any target outside [0.02, 0.08])."""
    torch.manual_seed(0)
    pol = make_policy(PolicyConfig(), OBS, ACT, Bounded(-1.0, 1.0, shape=(ACT,)))
    batch = _rollout(pol, seed=3, loc_shift=shift)
    with torch.no_grad():  # the KL the rule sees, in plain torch
        loc, scale = pol.actor_net(batch["observation"])
    kl = torch.distributions.kl_divergence(
        torch.distributions.Normal(batch["loc"], batch["scale"]), torch.distributions.Normal(loc, scale)
    ).sum(-1).mean()  # fmt: skip
    assert (0.025 < float(kl) < 0.1) if rate == 1e-3 else (0.0 < float(kl) < 0.02)
    cfg = AlgorithmConfig(
        desired_kl=0.05, lr=1e-3, num_epochs=1, mini_batch_size=48, compile="false", **PLAIN_PPO
    )
    algo = make_algorithm(cfg, pol, total_iterations=10)
    algo.update(batch)
    assert algo.cfg.lr == pytest.approx(rate, rel=1e-12)


def _gaussian_entropy(log_std: float, dims: int) -> float:
    """The entropy of a diagonal Gaussian with every log-std ``log_std``, by hand."""
    return dims * (0.5 + 0.5 * np.log(2 * np.pi) + log_std)


@pytest.mark.parametrize("coeff", [0.0, 0.02])
def test_ppo_logs_the_policys_real_entropy_whatever_the_coefficient(coeff):
    """With ``entropy_coeff=0`` (the default) the entropy is still the policy's, not a 0 filled
    in; the loss term is logged only where the loss has it. lr=0: the policy stays as built, so
    every minibatch sees the hand-computed entropy of log-std -0.7."""
    torch.manual_seed(0)
    pol = make_policy(PolicyConfig(init_log_std=-0.7), OBS, ACT, Bounded(-1.0, 1.0, shape=(ACT,)))
    cfg = AlgorithmConfig(
        lr=0.0, entropy_coeff=coeff, num_epochs=2, mini_batch_size=16, compile="false", **PLAIN_PPO
    )
    algo = make_algorithm(cfg, pol, total_iterations=10)
    metrics = algo.update(_rollout(pol, seed=3, envs=2, steps=24))
    expected = _gaussian_entropy(-0.7, ACT)
    assert metrics["loss/entropy"] == pytest.approx(expected, rel=1e-5)
    if coeff == 0.0:
        assert "loss/entropy_term" not in metrics
    else:
        assert metrics["loss/entropy_term"] == pytest.approx(-coeff * expected, rel=1e-5)
    # a coefficient a hook sets later joins the loss (and the log) from the next update
    algo.set_hyperparameter("entropy_coeff", 0.05)
    metrics = algo.update(_rollout(pol, seed=4, envs=2, steps=24))
    assert metrics["loss/entropy_term"] == pytest.approx(-0.05 * expected, rel=1e-5)


def test_grpo_logs_the_policys_real_entropy_with_entropy_coeff_zero():
    torch.manual_seed(0)
    pol = make_policy(ActorOnlyConfig(init_log_std=0.4), 3, 2, Bounded(-1.0, 1.0, shape=(2,)))
    cfg = GRPOConfig(
        gamma=0.9, group_size=2, kl_coeff=0.0, entropy_coeff=0.0, lr=0.0, num_epochs=1,
        mini_batch_size=12, compile="false",
    )  # fmt: skip
    algo = make_algorithm(cfg, pol, total_iterations=10)
    metrics = algo.update(_grpo_rollout(pol, envs=4, steps=6, log_prob_noise=0.3))
    assert metrics["loss/entropy"] == pytest.approx(_gaussian_entropy(0.4, 2), rel=1e-5)
    assert "loss/entropy_term" not in metrics and "loss/kl_ref" not in metrics
