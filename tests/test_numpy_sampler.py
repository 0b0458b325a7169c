"""The numpy collection sampler (rlexp/policies/numpy_sampler.py) against the torch sampler and
TorchRL's distribution: same draws from torch's generator, the same values up to float rounding,
and torch wherever numpy does not apply."""

from __future__ import annotations

import pytest
import torch
from torchrl.data import Bounded, Categorical
from torchrl.modules import IndependentNormal

from rlexp.config.schema import MLPConfig, PolicyConfig
from rlexp.policies.actor_critic import make_policy
from rlexp.policies.numpy_sampler import MAX_ROW_MACS


def _policy(activation: str, hidden: tuple[int, ...], normalize: bool = True):
    torch.manual_seed(3)
    cfg = PolicyConfig(
        actor=MLPConfig(hidden_sizes=list(hidden), activation=activation), init_log_std=-0.7
    )
    pol = make_policy(cfg, 5, 3, Bounded(-1.0, 1.0, shape=(3,)), normalize, clip_observations=2.5)
    if normalize:
        pol.normalizer.update(torch.randn(256, 5) * torch.tensor([3.0, 0.5, 1.0, 8.0, 2.0]) + 1.5)
    return pol


def _draw(pol, obs: torch.Tensor, use_numpy: bool, seed: int = 11):
    sampling = pol.sampling_policy()
    sampling.use_numpy = use_numpy
    torch.manual_seed(seed)
    out = sampling.sampler()(obs)
    return out, torch.randn(4)  # the next draw: the generator advanced alike


@pytest.mark.parametrize("activation", ["tanh", "relu", "elu", "silu"])
@pytest.mark.parametrize("normalize", [True, False])
def test_numpy_draws_equal_the_torch_sampler_up_to_rounding(activation, normalize):
    """loc, scale, action and log-prob within 1e-5 of the torch sampler's for the same seed, the
    same number of random draws taken, and the log-prob equal to IndependentNormal's of the action.

    Catches: another RNG stream or draw count (resume and the TorchRL loop's equality would break),
    a normaliser or clip left out, a wrong activation, the log-density's constant."""
    pol = _policy(activation, (24, 16), normalize)
    obs = torch.randn(4, 5) * 6.0
    (n_loc, n_scale, n_action, n_lp), n_next = _draw(pol, obs, use_numpy=True)
    (t_loc, t_scale, t_action, t_lp), t_next = _draw(pol, obs, use_numpy=False)
    assert torch.equal(n_next, t_next)
    for got, want in ((n_loc, t_loc), (n_scale, t_scale), (n_action, t_action), (n_lp, t_lp)):
        assert got.dtype == want.dtype == torch.float32 and got.shape == want.shape
        torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-5)
    assert not torch.equal(n_action, n_loc)  # it sampled
    torch.testing.assert_close(n_scale[0], torch.full((3,), -0.7).exp())
    reference = IndependentNormal(n_loc, n_scale).log_prob(n_action)
    torch.testing.assert_close(n_lp, reference, rtol=1e-5, atol=1e-4)


def test_too_many_rows_categorical_heads_and_evaluation_stay_torch(monkeypatch):
    """Over MAX_ROW_MACS (OpenBLAS would thread), a categorical head, a float64 policy and the
    deterministic (evaluation) sampler: exactly the torch sampler's output.

    Catches: numpy reaching the evaluation (exported policies would no longer act alike) or heads
    it does not implement."""
    linear_calls = []  # the torch sampler's layers call F.linear; numpy's do not
    linear = torch.nn.functional.linear
    monkeypatch.setattr(
        torch.nn.functional, "linear", lambda *a: linear_calls.append(1) or linear(*a)
    )
    pol = _policy("tanh", (64, 64))
    rows = MAX_ROW_MACS // (64 * 64) + 1
    obs = torch.randn(rows, 5)
    (n_out, _), (t_out, _) = _draw(pol, obs, True), _draw(pol, obs, False)
    assert all(torch.equal(a, b) for a, b in zip(n_out, t_out, strict=True))
    assert len(linear_calls) == 6  # both ran torch
    few = obs[:2]
    _draw(pol, few, True)
    assert len(linear_calls) == 6  # numpy ran

    det = pol.sampling_policy(deterministic=True)
    loc = det.sampler()(few)[2]
    det.use_numpy = False
    assert torch.equal(loc, det.sampler()(few)[2])

    cat = make_policy(PolicyConfig(), 5, 1, Categorical(4, shape=(1,)), nvec=[4])
    (n_cat, _), (t_cat, _) = _draw(cat, few, True), _draw(cat, few, False)
    assert all(torch.equal(a, b) for a, b in zip(n_cat, t_cat, strict=True))

    wide = pol.double()
    (n_64, _), (t_64, _) = _draw(wide, few.double(), True), _draw(wide, few.double(), False)
    assert all(torch.equal(a, b) for a, b in zip(n_64, t_64, strict=True))


def test_a_rollouts_noise_is_one_block_drawn_from_torch_at_its_start():
    """RolloutCollector (Hopper x2, 24 steps per env, twice): each rollout's noise, read back as
    (action - loc) / scale, is ``torch.randn(24, 2, 3)`` drawn from torch's generator as it stood at
    the rollout's start; a restart drops a block's leftovers.

    Catches: blocks out of step with rollouts (a resumed run would draw other noise), noise from
    another generator, env and step axes swapped."""
    from conftest import compose
    from rlexp.config.validate import to_root_config
    from rlexp.envs.factory import make_env
    from rlexp.policies.numpy_sampler import NoiseStream
    from rlexp.training.collector import RolloutCollector

    env = make_env(to_root_config(compose(["env=hopper"])).env, 2, seed=4)
    pol = make_policy(PolicyConfig(init_log_std=-0.4), 11, 3, env.action_spec)
    col = RolloutCollector(env, pol.sampling_policy(), frames_per_batch=48, total_frames=-1)
    try:
        for seed in (5, 6):
            torch.manual_seed(seed)
            want = torch.randn(24, 2, 3).transpose(0, 1)
            torch.manual_seed(seed)
            batch = col.rollout()
            got = (batch["action"] - batch["loc"]) / batch["scale"]
            torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-4)
    finally:
        col.shutdown()

    stream = NoiseStream(3)
    torch.manual_seed(0)
    first = stream.take((2,))
    stream.restart()
    second = stream.take((2,))
    torch.manual_seed(0)
    blocks = torch.randn(2, 3, 2).numpy()
    assert (first == blocks[0, 0]).all() and (second == blocks[1, 0]).all()
