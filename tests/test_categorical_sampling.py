"""Categorical sampling against the softmax, where a wrong sampler shows (issue #44 item 1).

A freshly initialised policy's logits are near zero: every action about equally likely, so a sampler
drawing from the wrong distribution (the Gumbel noise's sign flipped draws [2, 0, -1] as
0.868 / 0.110 / 0.022 instead of the softmax's 0.844 / 0.114 / 0.042) looks right there. Here the
actor's last layer is zeroed and its bias set to peaked, asymmetric logits, different per component,
and each sampling path draws 40,000 actions from one fixed seed: the joint counts over all components
must pass a chi-square test against the product of the softmaxes worked out in numpy (a false failure
has probability 1e-6, and the seed makes it deterministic); the Gumbel sign flip gives a statistic
near 400 for Discrete(3), a p-value near 1e-90.

Paths: the collection sampler (``CategoricalActorNet.sampler``: one ``Categorical`` block for equal
``nvec``, split blocks otherwise) and TorchRL's ``ProbabilisticActor`` over ``MultiCategorical``
(the loss's distribution; ``torch.distributions.Categorical`` per component) for Discrete,
MultiDiscrete (equal and unequal sizes) and MultiBinary; the deterministic sampler's mode. The
numpy collection sampler (policies/numpy_sampler.py) is Gaussian only: a categorical head never
takes it (tests/test_numpy_sampler.py)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch
from scipy.stats import chisquare
from tensordict import TensorDict
from torchrl.data import MultiCategorical as MultiCategoricalSpec
from torchrl.envs.utils import ExplorationType, set_exploration_type

from rlexp.config.schema import MLPConfig, PolicyConfig
from rlexp.policies.actor_critic import make_policy

DRAWS = 40_000
#: The false-failure probability of each chi-square test.
ALPHA = 1e-6

#: (case, nvec, logits per component): Discrete, MultiDiscrete of equal and of unequal sizes,
#: MultiBinary. Peaked and asymmetric; a component's logits differ from every other's.
CASES = [
    ("discrete", (3,), [[2.0, 0.0, -1.0]]),
    ("multi_discrete_equal", (3, 3), [[2.0, 0.0, -1.0], [-1.0, 1.5, 0.25]]),
    ("multi_discrete_unequal", (3, 4), [[2.0, 0.0, -1.0], [-2.0, 0.5, 1.25, 0.0]]),
    ("multi_binary", (2, 2, 2), [[1.5, -0.5], [-1.0, 0.5], [0.0, 2.0]]),
]

#: Each case's most likely action, read off the logits above.
MODES = {(3,): [0], (3, 3): [0, 1], (3, 4): [0, 2], (2, 2, 2): [0, 1, 1]}


def _softmax(z: list[float]) -> np.ndarray:
    e = np.exp(np.array(z, dtype=np.float64) - max(z))
    return e / e.sum()


def _joint(logits: list[list[float]]) -> dict[tuple[int, ...], float]:
    """Every joint action's probability: the product of its components' softmax probabilities."""
    probs = [_softmax(z) for z in logits]
    return {
        combo: float(np.prod([p[i] for p, i in zip(probs, combo, strict=True)]))
        for combo in itertools.product(*(range(len(p)) for p in probs))
    }


def _policy(nvec: tuple[int, ...], logits: list[list[float]]):
    """A categorical policy whose logits are ``logits`` whatever the observation."""
    spec = MultiCategoricalSpec(nvec=list(nvec), shape=(len(nvec),), dtype=torch.int64)
    cfg = PolicyConfig(actor=MLPConfig(hidden_sizes=[8]))
    pol = make_policy(cfg, 4, len(nvec), spec, normalize_observations=False, nvec=nvec)
    last = pol.actor_net.mlp[-1]
    with torch.no_grad():
        last.weight.zero_()
        last.bias.copy_(torch.tensor([x for z in logits for x in z]))
    return pol


def _assert_softmax_frequencies(actions: torch.Tensor, logits: list[list[float]]) -> None:
    """Chi-square of the joint counts of ``actions`` [DRAWS, K] against the softmax product."""
    joint = _joint(logits)
    assert actions.shape == (DRAWS, len(logits)) and actions.dtype == torch.int64
    counts = dict.fromkeys(joint, 0)
    for row, n in zip(*np.unique(actions.numpy(), axis=0, return_counts=True), strict=True):
        key = tuple(int(x) for x in row)
        assert key in counts, f"action {key} is outside the action space"
        counts[key] = int(n)
    observed = np.array([counts[k] for k in joint], dtype=np.float64)
    expected = np.array([joint[k] for k in joint]) * DRAWS
    stat, p = chisquare(observed, expected)
    assert p > ALPHA, (
        f"the draws do not follow the softmax (chi2={stat:.1f}, p={p:.2g}): counts "
        f"{dict(zip(joint, observed.astype(int).tolist(), strict=True))}, expected "
        f"{dict(zip(joint, np.round(expected).astype(int).tolist(), strict=True))}"
    )


@pytest.mark.parametrize(("nvec", "logits"), [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_the_collection_sampler_draws_from_the_softmax_of_peaked_logits(nvec, logits):
    pol = _policy(nvec, logits)
    obs = torch.randn(DRAWS, 4)
    torch.manual_seed(20260)
    with torch.no_grad():
        out_logits, action, log_prob = pol.sampling_policy().sample(obs)
    flat = torch.tensor([x for z in logits for x in z])
    assert torch.equal(out_logits, flat.expand(DRAWS, -1))
    _assert_softmax_frequencies(action, logits)
    # Each action's log-probability: the log of its joint probability worked out above.
    joint = _joint(logits)
    want = torch.tensor([np.log(joint[tuple(a)]) for a in action[:200].tolist()])
    torch.testing.assert_close(log_prob[:200].double(), want, rtol=0, atol=1e-5)


@pytest.mark.parametrize(("nvec", "logits"), [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_the_loss_distribution_samples_from_the_softmax_of_peaked_logits(nvec, logits):
    """TorchRL's ``ProbabilisticActor`` (exploration: random) over ``MultiCategorical``."""
    pol = _policy(nvec, logits)
    td = TensorDict({"observation": torch.randn(DRAWS, 4)}, batch_size=[DRAWS])
    torch.manual_seed(7)
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        out = pol.actor(td)
    _assert_softmax_frequencies(out["action"], logits)
    joint = _joint(logits)
    want = torch.tensor([np.log(joint[tuple(a)]) for a in out["action"][:200].tolist()])
    torch.testing.assert_close(out["action_log_prob"][:200].double(), want, rtol=0, atol=1e-5)


@pytest.mark.parametrize(("nvec", "logits"), [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_the_deterministic_sampler_takes_each_components_most_likely_value(nvec, logits):
    pol = _policy(nvec, logits)
    mode = MODES[nvec]
    _, action, log_prob = pol.sampling_policy(deterministic=True).sample(torch.randn(5, 4))
    assert action.tolist() == [mode] * 5
    torch.testing.assert_close(
        log_prob.double(),
        torch.full((5,), np.log(_joint(logits)[tuple(mode)]), dtype=torch.float64),
        rtol=0,
        atol=1e-5,
    )


def test_the_chi_square_bound_separates_the_softmax_from_the_flipped_gumbel_sampler():
    """The bound's power, shown on the issue's numbers: 40,000 draws whose frequencies are the
    flipped sampler's 0.868 / 0.110 / 0.022 fail the test that the softmax's own frequencies pass.
    (The flipped sampler's frequencies are computed here by numerical integration, not assumed.)"""
    z = np.array([2.0, 0.0, -1.0])
    # argmax(z - G), G ~ Gumbel(0, 1) i.i.d.: P(i) = integral of f(g_i) prod_{j!=i} P(G_j > g_i+z_j-z_i)
    g = np.linspace(-8.0, 30.0, 400_001)
    pdf, sf = np.exp(-g - np.exp(-g)), lambda x: 1.0 - np.exp(-np.exp(-x))
    flipped = np.array(
        [
            np.trapezoid(pdf * np.prod([sf(g + z[j] - z[i]) for j in range(3) if j != i], 0), g)
            for i in range(3)
        ]
    )
    np.testing.assert_allclose(flipped, [0.868, 0.110, 0.022], atol=1.5e-3)
    softmax = _softmax(list(z))
    np.testing.assert_allclose(softmax, [0.844, 0.114, 0.042], atol=1e-3)
    assert chisquare(flipped * DRAWS, softmax * DRAWS).pvalue < 1e-50
    assert chisquare(np.round(softmax * DRAWS), softmax * DRAWS).pvalue > ALPHA
