"""SAC / TD3 export: the exported file's action is the policy's deterministic action (tanh of the
mean mapped onto the bounds), the normaliser folded in; evaluating the file equals evaluating its
checkpoint."""

from __future__ import annotations

import pytest
import torch
from torchrl.data import Bounded

from conftest import rlexp_cli, run_train
from rlexp.config.schema_base import MLPConfig
from rlexp.config.schema_offpolicy import SACPolicyConfig, TD3PolicyConfig
from rlexp.deploy.export import DeterministicActor
from rlexp.deploy.policy_eval import evaluate
from rlexp.policies.offpolicy import SACPolicy, TD3Policy


@pytest.mark.parametrize("kind", ["sac", "td3"])
def test_the_exported_actor_is_the_deterministic_action(kind):
    torch.manual_seed(1)
    low, high = torch.tensor([-2.0, 0.5, -1.0]), torch.tensor([1.0, 3.0, 1.0])
    spec = Bounded(low, high, shape=(3,))
    cls, cfg = (SACPolicy, SACPolicyConfig) if kind == "sac" else (TD3Policy, TD3PolicyConfig)
    pcfg = cfg(actor=MLPConfig([16, 16], "relu"), normalize_observations=True)
    policy = cls(pcfg, 5, 3, spec, normalize_observations=True, clip_observations=2.0)
    policy.normalizer.update(torch.randn(64, 5) * 4.0 + 1.0)
    obs = torch.randn(32, 5) * 6.0
    want = policy.deterministic_action(obs)
    sampled = policy.sampling_policy(deterministic=True).sample(obs)[0]
    assert torch.equal(sampled, want)
    assert ((want >= low) & (want <= high)).all()
    actor = DeterministicActor(policy, low, high, clamp_actions=True)
    scripted = torch.jit.script(actor)
    torch.testing.assert_close(scripted(obs), want, atol=1e-6, rtol=1e-6)


def test_eval_of_an_exported_sac_run_equals_eval_of_its_checkpoint(tmp_path):
    run = tmp_path / "run"
    run_train(["algorithm=sac", "env=pendulum", "env.num_envs=2", "trainer.total_frames=200",
               "trainer.eval_every=200", "trainer.eval_episodes=1", "algorithm.learning_starts=100",
               "algorithm.batch_size=16", "policy.actor.hidden_sizes=[16]",
               "policy.critic.hidden_sizes=[16]", "logger=none", f"hydra.run.dir={run}"],
              cwd=tmp_path, timeout=600)  # fmt: skip
    rc, out, err = rlexp_cli("export", run, "--checkpoint", "best")
    assert rc == 0, err
    exported = next((run / "exported").glob("best*.pt"))
    want = evaluate(str(run / "checkpoints" / "best.pt"), 2, None)
    got = evaluate(str(exported), 2, None)
    assert got["mean_return"] == pytest.approx(want["mean_return"], rel=1e-6, abs=1e-6)
