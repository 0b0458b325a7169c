"""The fused minibatch step (``rlexp/algorithms/fused_step.py``) against today's path, TorchRL's
``ClipPPOLoss`` + ``guarded_step``: same losses, gradients, statistics and updated parameters with
non-default settings, for Gaussian and categorical heads; eager to float rounding, compiled within
float tolerance; a hyperparameter a hook changes takes effect without recompiling."""

from __future__ import annotations

import copy
import logging

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Bounded
from torchrl.data import MultiCategorical as MultiCategoricalSpec

from conftest import PLAIN_PPO, needs_compiler
from fused_parity import assert_compiled_parity_without_recompiling, assert_same, update_both
from rlexp.algorithms.base import NonFiniteError
from rlexp.algorithms.fused_step import MINIBATCH_KEYS, STEP_STATS, FusedPPOStep
from rlexp.algorithms.ppo import LOSS_KEYS, make_algorithm
from rlexp.config.schema import AlgorithmConfig, PolicyConfig
from rlexp.policies.actor_critic import make_policy

OBS, ENVS, STEPS = 5, 2, 48
#: Nothing at its default: asymmetric coefficients, value clipping, large steps.
SETTINGS = dict(
    gamma=0.9,
    lmbda=0.8,
    clip_epsilon=0.13,
    entropy_coeff=0.02,
    critic_coeff=0.7,
    max_grad_norm=0.37,
    clip_value=0.2,
    lr=3e-3,
    num_epochs=2,
    mini_batch_size=16,
    compile="false",
    **PLAIN_PPO,
)
HEADS = {"gaussian": None, "categorical": (3,), "multi_categorical": (2, 4)}


pytestmark = pytest.mark.usefixtures("one_torch_thread")  # conftest.py: tiny tensors


def _policy(nvec):
    torch.manual_seed(0)
    if nvec is None:
        return make_policy(PolicyConfig(), OBS, 2, Bounded(-1.0, 1.0, shape=(2,)))
    spec = MultiCategoricalSpec(nvec=list(nvec), shape=(len(nvec),), dtype=torch.int64)
    return make_policy(PolicyConfig(), OBS, len(nvec), spec, nvec=nvec)


def _rollout(pol) -> TensorDict:
    """A rollout [ENVS, STEPS] sampled from ``pol``, log-probs perturbed so that ratios leave the
    clip range, an episode end in each env."""
    gen = torch.Generator().manual_seed(1)
    obs = torch.randn(ENVS, STEPS, OBS, generator=gen)
    with torch.no_grad():
        sampled = pol.sampling_policy().sample(obs)
    action, log_prob = sampled[-2], sampled[-1]
    done = torch.zeros(ENVS, STEPS, 1, dtype=torch.bool)
    done[0, 20], done[1, 33] = True, True
    return TensorDict(
        {
            "observation": obs,
            "action": action,
            "action_log_prob": log_prob + 0.3 * torch.randn(ENVS, STEPS, generator=gen),
            **dict(zip(pol.actor_net.dist_keys, sampled[:-2], strict=True)),
            "next": {
                "observation": torch.randn(ENVS, STEPS, OBS, generator=gen),
                "reward": torch.randn(ENVS, STEPS, 1, generator=gen),
                "terminated": done,
                "truncated": torch.zeros_like(done),
                "done": done,
            },
        },
        batch_size=[ENVS, STEPS],
    )


def _pair(nvec, compile_choice="false", **overrides):
    """(fused learner, reference learner) on equal copies of one policy; the reference eager."""
    pol = _policy(nvec)
    cfg = AlgorithmConfig(**{**SETTINGS, **overrides})
    ref = make_algorithm(cfg, copy.deepcopy(pol), total_iterations=1_000_000)
    ref.use_fused_step = False  # today's path: ClipPPOLoss + guarded_step
    fused = make_algorithm(
        AlgorithmConfig(**{**SETTINGS, **overrides, "compile": compile_choice}),
        pol,
        total_iterations=1_000_000,
    )
    assert fused.use_fused_step, "the fused step is the default"
    return fused, ref


@pytest.mark.parametrize("head", list(HEADS))
@pytest.mark.parametrize(
    "overrides",
    [
        {"loss_critic_type": "smooth_l1"},
        {"loss_critic_type": "l1", "normalize_advantage": False, "clip_value": None},
    ],
    ids=["smooth_l1-clip_value", "l1-raw_advantage"],
)
def test_eager_fused_updates_equal_clipppoloss_updates(head, overrides):
    fused, ref = _pair(HEADS[head], **overrides)
    batch = _rollout(fused.policy)
    moved = copy.deepcopy(fused.policy)
    for seed in (11, 12):
        got, expected = update_both(fused, ref, batch, seed)
        assert_same(fused, ref, got, expected, tol=1e-6)
    assert 0.0 < got["loss/clip_fraction"] < 1.0, "the comparison must see clipped and unclipped"
    for p, p0 in zip(fused.policy.parameters(), moved.parameters(), strict=True):
        assert (p - p0).abs().max() > 1e-4, "a parameter did not move: the test would be vacuous"


@pytest.mark.parametrize("head", list(HEADS))
def test_fused_loss_and_gradients_equal_clipppoloss_on_one_minibatch(head):
    fused, ref = _pair(HEADS[head])
    batch = _rollout(fused.policy)
    ref.compute_advantages(batch)
    flat = batch.reshape(-1)[:24]
    step = FusedPPOStep(fused, compiled=False)
    data = [flat.get(k) for k in MINIBATCH_KEYS]
    data[2] = data[2].reshape(-1)
    hyper = torch.tensor([0.13, 0.02, 0.7, 0.37])
    total, stats = step.loss(*data, hyper)
    grads = torch.autograd.grad(total, fused.params)
    out = ref.loss(flat.clone())
    ref_grads = torch.autograd.grad(sum(out[k] for k in LOSS_KEYS), ref.params)
    for key, value in zip([k for k in STEP_STATS if k != "grad_norm"], stats, strict=True):
        torch.testing.assert_close(value, out[key].detach(), rtol=1e-6, atol=1e-7, msg=key)
    for g, r in zip(grads, ref_grads, strict=True):
        torch.testing.assert_close(g, r, rtol=1e-6, atol=1e-7)


def test_hook_changes_take_effect_as_in_the_reference():
    """clip_epsilon, critic_coeff, max_grad_norm (0: off), entropy_coeff (0: the term leaves the
    loss and loss/entropy_term the metrics) and lr, set between updates as hooks do."""
    fused, ref = _pair(HEADS["gaussian"], anneal_lr=True)
    batch = _rollout(fused.policy)
    changes = [
        {"clip_epsilon": 0.3, "critic_coeff": 0.2},
        {"max_grad_norm": 0.0, "entropy_coeff": 0.0, "lr": 1e-3},
    ]
    for seed, change in enumerate(changes):
        for name, value in change.items():
            fused.set_hyperparameter(name, value)
            ref.set_hyperparameter(name, value)
        got, expected = update_both(fused, ref, batch, seed)
        assert_same(fused, ref, got, expected, tol=1e-6)
    assert "loss/entropy_term" not in got


@needs_compiler
@pytest.mark.parametrize("head", ["gaussian", "multi_categorical"])
def test_compiled_fused_updates_match_and_a_hook_change_does_not_recompile(head):
    fused, ref = _pair(HEADS[head], compile_choice="true", anneal_lr=True)
    assert not ref.compiled
    batch = _rollout(fused.policy)
    assert_compiled_parity_without_recompiling(
        fused, ref, batch, {"clip_epsilon": 0.25, "entropy_coeff": 0.0, "critic_coeff": 1.3,
                        "max_grad_norm": 0.11, "lr": 5e-3}
    )  # fmt: skip


def test_what_the_fused_step_does_not_cover_keeps_todays_path_and_says_why(caplog):
    pol = _policy(None)
    batch = _rollout(pol)
    distributed = make_algorithm(
        AlgorithmConfig(**SETTINGS), pol, 10, grad_sync=lambda tensors: None
    )
    adaptive = make_algorithm(
        AlgorithmConfig(**{**SETTINGS, "desired_kl": 0.01}), copy.deepcopy(pol), 10
    )
    with caplog.at_level(logging.INFO, logger="rlexp.algorithms.ppo"):
        for algo in (distributed, adaptive):
            algo.update(batch.clone())
            assert algo.fused is None
    assert "not fused: distributed gradient averaging" in caplog.text
    assert "not fused: algorithm.desired_kl" in caplog.text


def test_the_nan_guard_stops_the_fused_step_before_it_steps():
    fused, _ = _pair(HEADS["gaussian"])
    batch = _rollout(fused.policy)
    batch["next", "reward"][:] = float("nan")
    before = copy.deepcopy(fused.policy.state_dict())
    with pytest.raises(
        NonFiniteError, match=r"non-finite loss \(loss_objective.*epoch 0, minibatch 0"
    ):
        fused.update(batch)
    for key, value in fused.policy.state_dict().items():
        assert torch.equal(value, before[key]), f"{key} changed"
