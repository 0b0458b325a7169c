"""trainer.nan_guard: a NaN or Inf in the env's rewards, the PPO loss or the gradients stops the run
(NonFiniteError; ``python train.py`` exits 3 with status.json "failed") before an optimiser step,
and the message names what was non-finite. (Observations: tests/test_lifecycle.py.)"""

from __future__ import annotations

import copy
import json

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Bounded

from conftest import PLAIN_PPO, run_train
from rlexp.algorithms.ppo import NonFiniteError, make_algorithm
from rlexp.config.schema import AlgorithmConfig, PolicyConfig
from rlexp.policies.actor_critic import make_policy

OBS_DIM, ACT_DIM, ENVS, STEPS = 3, 2, 2, 8


def _policy_and_batch(reward: float = 1.0):
    torch.manual_seed(0)
    pol = make_policy(PolicyConfig(), OBS_DIM, ACT_DIM, Bounded(-1.0, 1.0, shape=(ACT_DIM,)))
    obs = torch.randn(ENVS, STEPS, OBS_DIM)
    next_obs = torch.cat([obs[:, 1:], torch.randn(ENVS, 1, OBS_DIM)], dim=1)
    with torch.no_grad():
        _, _, action, log_prob = pol.sampling_policy().sample(obs)
    done = torch.zeros(ENVS, STEPS, 1, dtype=torch.bool)
    batch = TensorDict(
        {
            "observation": obs,
            "action": action,
            "action_log_prob": log_prob,
            "next": {
                "observation": next_obs,
                "reward": torch.full((ENVS, STEPS, 1), reward),
                "terminated": done,
                "truncated": done,
                "done": done,
            },
        },
        batch_size=[ENVS, STEPS],
    )
    return pol, batch


def _algorithm(pol, **cfg):
    cfg = AlgorithmConfig(
        num_epochs=1, mini_batch_size=ENVS * STEPS, compile="false", **{**PLAIN_PPO, **cfg}
    )
    return make_algorithm(cfg, pol, total_iterations=10)


def _assert_nothing_changed(pol, before, algo):
    for (name, p), p0 in zip(pol.named_parameters(), before.parameters(), strict=True):
        assert torch.equal(p, p0), f"{name} changed: an optimiser step was taken after the NaN"
    assert not algo.optimizer.state, "Adam's moments were updated with the non-finite gradient"


def test_a_finite_update_passes_the_guard():
    """The in-process setup below is sound: with ordinary rewards the update runs and moves."""
    pol, batch = _policy_and_batch()
    before = copy.deepcopy(pol)
    _algorithm(pol).update(batch)
    assert any(
        not torch.equal(p, p0) for p, p0 in zip(pol.parameters(), before.parameters(), strict=True)
    )


def test_non_finite_loss_stops_the_update_before_the_step():
    # Rewards of 1e30 are finite, but the squared value error overflows float32.
    pol, batch = _policy_and_batch(reward=1e30)
    before = copy.deepcopy(pol)
    algo = _algorithm(pol)
    with pytest.raises(NonFiniteError) as info:
        algo.update(batch)
    assert str(info.value) == "non-finite loss (loss_critic) in PPO update (epoch 0, minibatch 0)"
    _assert_nothing_changed(pol, before, algo)


@pytest.mark.parametrize("max_grad_norm", [0.5, 0.0], ids=["clipped", "unclipped"])
def test_non_finite_gradient_names_the_parameter(max_grad_norm):
    """A finite loss whose gradient is NaN (here: a hook on one weight) stops the update; the message
    names the parameter, which clipping by the NaN norm must not smear over all the others."""
    pol, batch = _policy_and_batch()
    before = copy.deepcopy(pol)
    algo = _algorithm(pol, max_grad_norm=max_grad_norm)
    name, param = next((n, p) for n, p in pol.named_parameters() if n.startswith("critic"))
    param.register_hook(lambda grad: torch.full_like(grad, float("nan")))
    with pytest.raises(NonFiniteError) as info:
        algo.update(batch)
    assert str(info.value) == (f"non-finite gradient ({name}) in PPO update (epoch 0, minibatch 0)")
    _assert_nothing_changed(pol, before, algo)


def test_gradient_too_large_for_its_norm_is_named_as_the_norm():
    pol, batch = _policy_and_batch()
    algo = _algorithm(pol)
    for p in pol.parameters():
        p.register_hook(lambda grad: grad * 1e30)  # finite, but the squares overflow
    with pytest.raises(
        NonFiniteError,
        match=r"^non-finite gradient norm \(the gradients are finite, their norm overflows\) in PPO",
    ):
        algo.update(batch)


@pytest.mark.parametrize(
    ("peer", "what"),
    [("loss", "loss on another rank"), ("gradient", "gradient ({}) after averaging over ranks")],
)
def test_a_peers_non_finite_loss_or_gradient_stops_this_rank_too(peer, what):
    """Distributed, the loss travels with the gradients through the all-reduce (``grad_sync``): a
    rank whose own loss and gradients are finite stops when a peer's were not, instead of stepping
    on and leaving that peer blocked. Here ``grad_sync`` averages with a made-up peer."""
    pol, batch = _policy_and_batch()
    before = copy.deepcopy(pol)
    cfg = AlgorithmConfig(num_epochs=1, mini_batch_size=ENVS * STEPS, compile="false", **PLAIN_PPO)
    synced: list[list[torch.Tensor]] = []

    def grad_sync(tensors: list[torch.Tensor]) -> None:
        synced.append(tensors)
        for t in tensors:
            t.div_(2)  # the mean with a peer whose values were zero...
        # ...except its loss (the last tensor, after the parameters' gradients) or first gradient
        tensors[-1 if peer == "loss" else 0].fill_(float("nan"))

    algo = make_algorithm(cfg, pol, total_iterations=10, grad_sync=grad_sync)
    with pytest.raises(NonFiniteError) as info:
        algo.update(batch)
    assert len(synced[0]) == len(list(pol.parameters())) + 1
    first = next(name for name, _ in pol.named_parameters())
    assert (
        str(info.value) == f"non-finite {what.format(first)} in PPO update (epoch 0, minibatch 0)"
    )
    _assert_nothing_changed(pol, before, algo)


def test_nan_guard_off_lets_the_update_through():
    pol, batch = _policy_and_batch(reward=1e30)
    cfg = AlgorithmConfig(num_epochs=1, mini_batch_size=ENVS * STEPS, compile="false", **PLAIN_PPO)
    make_algorithm(cfg, pol, total_iterations=10, nan_guard=False).update(batch)


# -- the command line: exit 3, status.json "failed" with the reason --------------------------------
BASE = [
    # Swimmer-v5 takes its reward weights as gymnasium.make kwargs: 1e300 (finite in float64) makes an
    # infinite float32 reward; -1e30 a finite one whose squared value error overflows. Observations
    # stay finite either way.
    "env=swimmer",
    "trainer.total_frames=512",
    "trainer.frames_per_batch=256",
    "trainer.eval_every=0",
    "trainer.save_every=0",
    "algorithm.num_epochs=1",
    "algorithm.normalize_rewards=false",  # raw rewards: scaled and clipped ones never overflow
    "algorithm.clip_rewards=null",
]


@pytest.mark.parametrize(
    ("weight", "reason"),
    [
        ("1e300", "non-finite next/reward from the env at step 256"),
        ("-1e30", "non-finite loss (loss_critic) in PPO update (epoch 0, minibatch 0) at step 256"),
    ],
    ids=["reward", "loss"],
)
def test_train_py_exits_3_with_the_reason_in_status_json(tmp_path, weight, reason):
    run_dir = tmp_path / "run"
    proc = run_train(
        [*BASE, f"+env.kwargs.ctrl_cost_weight={weight}", f"hydra.run.dir={run_dir}"],
        cwd=tmp_path,
        check=False,
    )
    out = proc.stdout + proc.stderr
    assert proc.returncode == 3, out
    status = json.loads((run_dir / "status.json").read_text())
    assert status["state"] == "failed" and status["reason"].startswith(reason), status
    said = [line for line in out.splitlines() if "non-finite" in line]
    assert said and all(reason in line for line in said), said
    assert not [line for line in said if "None" in line], f"the message says None: {said}"
    assert "Traceback" not in out
    assert not list(run_dir.glob("checkpoints/*.pt")), "a checkpoint was saved after the NaN"
