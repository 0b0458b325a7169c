"""GRPO's fused minibatch step (``rlexp/algorithms/fused_grpo.py``) against today's path, ``GRPO.loss``
on TensorDict slices + ``guarded_step``: whole updates give the same statistics, gradients,
parameters and Adam moments with non-default settings (group_size 3, kl_coeff > 0, entropy_coeff
!= 0, truncate_at_first_done, masks with zeros), for Gaussian, Discrete and MultiDiscrete heads;
eager bit-equal (the same operations in the same order), compiled within 2e-5; a hyperparameter a hook changes takes effect without
recompiling; what the fused step does not cover keeps today's path and says why, once."""

from __future__ import annotations

import copy
import logging

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Bounded
from torchrl.data import MultiCategorical as MultiCategoricalSpec

from conftest import needs_compiler
from fused_parity import assert_compiled_parity_without_recompiling, assert_same, update_both
from rlexp.algorithms import make_algorithm
from rlexp.algorithms.base import NonFiniteError
from rlexp.config.schema import ActorOnlyConfig, GRPOConfig
from rlexp.config.validate import ConfigError
from rlexp.policies.actor_critic import make_policy

OBS, ENVS, STEPS = 4, 6, 8
#: Nothing at its default: two groups of 3, a KL penalty, an entropy bonus, clipping on.
SETTINGS = dict(
    gamma=0.9,
    group_size=3,
    kl_coeff=0.3,
    entropy_coeff=0.02,
    clip_epsilon=0.13,
    max_grad_norm=0.37,
    epsilon=1e-6,
    lr=3e-3,
    num_epochs=2,
    mini_batch_size=16,
    truncate_at_first_done=True,
    anneal_lr=False,
    compile="false",
)
HEADS = {"gaussian": None, "discrete": (3,), "multi_discrete": (2, 4)}


pytestmark = pytest.mark.usefixtures("one_torch_thread")  # conftest.py: tiny tensors


def _policy(nvec):
    torch.manual_seed(0)
    if nvec is None:
        pol = make_policy(ActorOnlyConfig(), OBS, 2, Bounded(-1.0, 1.0, shape=(2,)))
    else:
        spec = MultiCategoricalSpec(nvec=list(nvec), shape=(len(nvec),), dtype=torch.int64)
        pol = make_policy(ActorOnlyConfig(), OBS, len(nvec), spec, nvec=nvec)
    pol.normalizer.update(torch.randn(64, OBS) * 2 + 1)  # a normaliser that is not the identity
    return pol


def _rollout(pol) -> TensorDict:
    """A rollout [ENVS, STEPS] sampled from ``pol``: log-probs perturbed so that ratios leave the
    clip range; terminations and truncations, so that truncate_at_first_done masks steps."""
    gen = torch.Generator().manual_seed(1)
    obs = torch.randn(ENVS, STEPS, OBS, generator=gen)
    with torch.no_grad():
        sampled = pol.sampling_policy().sample(obs)
    terminated = torch.zeros(ENVS, STEPS, 1, dtype=torch.bool)
    truncated = torch.zeros_like(terminated)
    terminated[0, 2], truncated[1, 5], terminated[4, 0], truncated[4, 6] = True, True, True, True
    return TensorDict(
        {
            "observation": obs,
            "action": sampled[-2],
            "action_log_prob": sampled[-1] + 0.3 * torch.randn(ENVS, STEPS, generator=gen),
            "next": {
                "observation": torch.randn(ENVS, STEPS, OBS, generator=gen),
                "reward": torch.randn(ENVS, STEPS, 1, generator=gen),
                "terminated": terminated,
                "truncated": truncated,
                "done": terminated | truncated,
            },
        },
        batch_size=[ENVS, STEPS],
    )


def _pair(nvec, compile_choice="false", **overrides):
    """(fused learner, reference learner) on equal copies of one policy; the reference eager on
    today's path."""
    pol = _policy(nvec)
    ref = make_algorithm(GRPOConfig(**{**SETTINGS, **overrides}), copy.deepcopy(pol), 1000)
    ref.use_fused_step = False  # today's path: GRPO.loss + guarded_step
    cfg = GRPOConfig(**{**SETTINGS, **overrides, "compile": compile_choice})
    fused = make_algorithm(cfg, pol, 1000)
    assert fused.use_fused_step, "the fused step is the default"
    return fused, ref


@pytest.mark.parametrize("head", list(HEADS))
@pytest.mark.parametrize(
    "overrides",
    [
        {},
        {"kl_coeff": 0.0, "entropy_coeff": -0.01, "truncate_at_first_done": False},
        {"entropy_coeff": 0.0, "max_grad_norm": 0.0, "mini_batch_size": 13},
    ],
    ids=["kl-entropy-truncated", "no_reference", "no_entropy_term-unclipped"],
)
def test_eager_fused_grpo_updates_equal_todays_updates(head, overrides):
    fused, ref = _pair(HEADS[head], **overrides)
    batch = _rollout(fused.policy)
    moved = copy.deepcopy(fused.policy)
    for seed in (11, 12):
        got, expected = update_both(fused, ref, batch, seed)
        assert_same(fused, ref, got, expected, tol=0)  # bit-equal: same ops, same order
    assert 0.0 < got["loss/clip_fraction"] < 1.0, "the comparison must see clipped and unclipped"
    assert ("loss/kl_ref" in got) == (fused.cfg.kl_coeff > 0)
    assert ("loss/entropy_term" in got) == (fused.cfg.entropy_coeff != 0)
    if fused.cfg.truncate_at_first_done:
        assert got["grpo/mask_fraction"] < 1.0, "the masks must have zeros"
    for p, p0 in zip(fused.policy.parameters(), moved.parameters(), strict=True):
        assert (p - p0).abs().max() > 1e-4, "a parameter did not move: the test would be vacuous"


def test_hook_changes_take_effect_as_on_todays_path():
    """clip_epsilon, entropy_coeff (to 0 and back: the term leaves and rejoins the loss),
    kl_coeff, max_grad_norm (0: off) and lr, set between updates as hooks do."""
    fused, ref = _pair(HEADS["multi_discrete"])
    batch = _rollout(fused.policy)
    changes = [
        {"clip_epsilon": 0.3, "kl_coeff": 1.5},
        {"entropy_coeff": 0.0, "max_grad_norm": 0.0, "lr": 1e-3},
        {"entropy_coeff": 0.05, "kl_coeff": 0.0},
    ]
    for seed, change in enumerate(changes):
        for name, value in change.items():
            fused.set_hyperparameter(name, value)
            ref.set_hyperparameter(name, value)
        got, expected = update_both(fused, ref, batch, seed)
        assert_same(fused, ref, got, expected, tol=0)  # bit-equal: same ops, same order
        assert ("loss/entropy_term" in got) == (change.get("entropy_coeff", 1.0) != 0)
        assert got["loss/learning_rate"] == fused.cfg.lr


@needs_compiler
@pytest.mark.parametrize("head", ["gaussian", "multi_discrete"])
def test_compiled_fused_grpo_updates_match_and_a_hook_change_does_not_recompile(head):
    fused, ref = _pair(HEADS[head], compile_choice="true", anneal_lr=True)
    batch = _rollout(fused.policy)
    assert_compiled_parity_without_recompiling(
        fused, ref, batch, {"clip_epsilon": 0.25, "entropy_coeff": 0.0, "kl_coeff": 0.9,
                        "max_grad_norm": 0.11, "lr": 5e-3}
    )  # fmt: skip


def test_compile_auto_uses_ppos_saving_rule_and_true_needs_the_fused_step():
    """auto: eager for a short run, compiled for a long one (PPO's estimate and threshold);
    true: refused at build time where the fused step cannot run (distributed)."""
    short, _ = _pair(None, compile_choice="auto")
    short._decide_step(updates=1_000, mb=64)
    long, _ = _pair(None, compile_choice="auto")
    long._decide_step(updates=1_000_000, mb=64)
    assert short.fused is not None and not short.fused.compiled and not short.compiled
    assert long.fused is not None and long.fused.compiled and long.compiled
    make_algorithm(GRPOConfig(**{**SETTINGS, "compile": "true"}), _policy(None), 10)
    with pytest.raises(ConfigError, match=r"algorithm\.compile=true.*distributed gradient"):
        make_algorithm(
            GRPOConfig(**{**SETTINGS, "compile": "true"}),
            _policy(None),
            10,
            grad_sync=lambda t: None,
        )


def test_what_the_fused_step_does_not_cover_keeps_todays_path_and_says_why_once(caplog):
    pol = _policy(None)
    batch = _rollout(pol)
    distributed = make_algorithm(GRPOConfig(**SETTINGS), pol, 10, grad_sync=lambda tensors: None)
    foreach = make_algorithm(GRPOConfig(**SETTINGS), copy.deepcopy(pol), 10)
    foreach.optimizer = torch.optim.Adam(foreach.params, lr=SETTINGS["lr"], foreach=True)
    with caplog.at_level(logging.INFO, logger="rlexp.algorithms.grpo"):
        for algo in (distributed, foreach):
            for _ in range(2):
                algo.update(batch.clone())
            assert algo.fused is None
    assert caplog.text.count("not fused: distributed gradient averaging") == 1
    assert caplog.text.count("not fused: Adam is not the fused kernel") == 1


def test_the_nan_guard_stops_the_fused_grpo_step_before_it_steps():
    fused, _ = _pair(HEADS["discrete"])
    batch = _rollout(fused.policy)
    batch["next", "reward"][2, 3] = float("nan")
    before = copy.deepcopy(fused.policy.state_dict())
    with pytest.raises(
        NonFiniteError, match=r"^non-finite loss \(loss_objective\) in GRPO update \(epoch 0, mini"
    ):
        fused.update(batch)
    assert fused.fused is not None, "the fused step must be the one that stopped"
    assert not fused.optimizer.state, "Adam stepped"
    for key, value in fused.policy.state_dict().items():
        assert torch.equal(value, before[key]), f"{key} changed"
