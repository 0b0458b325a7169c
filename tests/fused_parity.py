"""What the fused-step parity tests (test_fast_update.py: PPO against ClipPPOLoss;
test_fast_update_grpo.py: GRPO against its TensorDict path) share: one update of each learner from
the same random state, and the comparison of everything an update leaves behind."""

from __future__ import annotations

import pytest
import torch


def update_both(fused, ref, batch, seed):
    """One update of the fused learner and of the reference, each from ``seed``; their metrics."""
    torch.manual_seed(seed)
    got = fused.update(batch.clone())
    torch.manual_seed(seed)
    expected = ref.update(batch.clone())
    return got, expected


def assert_same(fused, ref, got, expected, tol):
    """Statistics, parameters, the last step's (clipped) gradients and Adam's state, within
    ``tol`` (0: bit-equal); the fused learner ran the fused step, the reference did not."""
    assert fused.fused is not None and ref.fused is None
    assert got.keys() == expected.keys()
    for key in expected:
        assert got[key] == pytest.approx(expected[key], rel=tol, abs=tol), key
    named = dict(ref.policy.named_parameters())
    for name, p in fused.policy.named_parameters():
        torch.testing.assert_close(p, named[name], rtol=tol, atol=tol, msg=name)
        # the last minibatch's gradients, clipped: what the step applied
        torch.testing.assert_close(p.grad, named[name].grad, rtol=10 * tol, atol=tol, msg=name)
    ours, theirs = fused.optimizer.state_dict()["state"], ref.optimizer.state_dict()["state"]
    assert ours.keys() == theirs.keys()
    for i in theirs:
        for key in ("step", "exp_avg", "exp_avg_sq"):
            torch.testing.assert_close(ours[i][key], theirs[i][key], rtol=tol, atol=tol)


def assert_compiled_parity_without_recompiling(fused, ref, batch, changes: dict[str, float]):
    """A compiled fused update matches the reference within 2e-5; after ``changes`` of mutable
    hyperparameters on both, the next update matches too, and nothing recompiled."""
    from torch._dynamo.utils import counters

    got, expected = update_both(fused, ref, batch, seed=5)
    assert fused.fused.compiled
    assert_same(fused, ref, got, expected, tol=2e-5)
    graphs = counters["stats"]["unique_graphs"]
    for name, value in changes.items():
        fused.set_hyperparameter(name, value)
        ref.set_hyperparameter(name, value)
    got, expected = update_both(fused, ref, batch, seed=6)  # the annealed lr moved too
    assert_same(fused, ref, got, expected, tol=2e-5)
    assert counters["stats"]["unique_graphs"] == graphs, "a hyperparameter change recompiled"
