"""``trainer.torch_threads``: ``auto`` resolved from the CPUs this process may use (mocked here),
shared among a sweep's side-by-side jobs; refusals in one line; SAC's gradient steps run with the
resolved count while collection runs with one; the off-policy loop's shortcuts (one foreach soft
update, the collector's iterator) give what TorchRL's own paths give."""

from __future__ import annotations

import copy

import pytest
import torch
from torchrl.data import Bounded

import rlexp.config.rules as rules
import rlexp.config.validate as validate
from conftest import train_here
from rlexp.algorithms.sac import SAC
from rlexp.algorithms.td3 import TD3
from rlexp.config.rules import torch_threads_for
from rlexp.config.schema_base import MLPConfig
from rlexp.config.schema_offpolicy import SACConfig, SACPolicyConfig, TD3Config, TD3PolicyConfig
from rlexp.config.validate import ConfigError, to_root_config
from rlexp.policies.offpolicy import SACPolicy, TD3Policy


@pytest.mark.parametrize(
    ("value", "cpus", "jobs", "expected"),
    [
        ("auto", 2, 1, 2),  # a run alone on this 2-core VM
        ("auto", 16, 3, 5),  # a local sweep of n_jobs=3 on 16 cores: 16 // 3
        ("auto", 2, 4, 1),  # more jobs than cores: never 0
        ("auto", 7, 1, 7),  # SLURM --cpus-per-task=7: the affinity mask
        (3, 16, 4, 3),  # a number is taken as it is
    ],
)
def test_auto_threads_share_the_cpus_among_the_jobs(value, cpus, jobs, expected):
    assert torch_threads_for(value, cpus, jobs) == expected


def _mock_cpus(monkeypatch, n: int) -> None:
    monkeypatch.setattr(rules, "available_cpus", lambda: n)
    monkeypatch.setattr(validate, "available_cpus", lambda: n)


@pytest.mark.parametrize(
    ("value", "message"),
    [
        ("3", "trainer.torch_threads=3 must be auto or in [1, 2]"),
        ("0", "trainer.torch_threads=0 must be auto or in [1, 2]"),
        ("al", "trainer.torch_threads=al must be auto or in [1, 2]"),
    ],
)
def test_more_threads_than_cpus_and_unknown_words_are_refused_in_one_line(
    monkeypatch, value, message
):
    from conftest import compose

    _mock_cpus(monkeypatch, 2)
    with pytest.raises(ConfigError) as err:
        to_root_config(compose(["env=pendulum", "algorithm=sac", f"trainer.torch_threads={value}"]))
    assert str(err.value).startswith(message)
    assert "\n" not in str(err.value)


def test_auto_is_accepted_and_resolved_from_the_cpu_count_and_the_jobs(monkeypatch):
    from conftest import compose
    from rlexp.app import _torch_threads

    _mock_cpus(monkeypatch, 6)
    config = to_root_config(
        compose(["env=pendulum", "algorithm=sac", "trainer.torch_threads=auto"])
    )
    assert config.trainer.torch_threads == "auto"  # config.yaml keeps the word
    assert _torch_threads(config, jobs=1) == 6
    assert _torch_threads(config, jobs=4) == 1
    monkeypatch.setenv("LOCAL_WORLD_SIZE", "2")  # torchrun: two ranks on this node
    assert _torch_threads(config, jobs=1) == 3


def test_sac_gradient_steps_use_the_resolved_threads_and_collection_one(tmp_path, monkeypatch):
    """``auto`` on a (mocked) 2-CPU machine: the update runs 2 torch threads, env steps 1."""
    from rlexp.envs.gym import GymnasiumEnv

    _mock_cpus(monkeypatch, 2)
    seen: dict[str, set[int]] = {"step": set(), "update": set()}
    step, grad = GymnasiumEnv.step_tensors, SAC._gradient_step

    def spy_step(self, action):
        seen["step"].add(torch.get_num_threads())
        return step(self, action)

    def spy_grad(self, batch):
        seen["update"].add(torch.get_num_threads())
        return grad(self, batch)

    monkeypatch.setattr(GymnasiumEnv, "step_tensors", spy_step)
    monkeypatch.setattr(SAC, "_gradient_step", spy_grad)
    train_here(
        [
            "env=pendulum",
            "algorithm=sac",
            "algorithm.learning_starts=20",
            "algorithm.batch_size=8",
            "algorithm.buffer_size=200",
            "trainer.total_frames=40",
            "trainer.eval_every=0",
            "trainer.save_every=0",
            "trainer.torch_threads=auto",
            "trainer.progress=false",
            "logger=none",
        ],  # fmt: skip
        tmp_path / "run",
    )
    assert seen == {"step": {1}, "update": {2}}


def _algo(kind: str):
    torch.manual_seed(3)
    spec = Bounded(torch.tensor([-2.0, -1.0]), torch.tensor([1.0, 3.0]), shape=(2,))
    nets = {"actor": MLPConfig([5, 4], "relu"), "critic": MLPConfig([6], "tanh")}
    if kind == "sac":
        return SAC(SACConfig(tau=0.3, buffer_size=8), SACPolicy(SACPolicyConfig(**nets), 3, 2, spec),
                   10)  # fmt: skip
    return TD3(
        TD3Config(tau=0.3, buffer_size=8), TD3Policy(TD3PolicyConfig(**nets), 3, 2, spec), 10
    )


@pytest.mark.parametrize("kind", ["sac", "td3"])
def test_the_soft_update_is_torchrls_soft_update_bit_for_bit_and_follows_tau_hooks(kind):
    """``_soft_update`` against TorchRL's ``SoftUpdate.step`` from the same (perturbed) state, at
    tau 0.3 and after a hook set tau to 0.07: every target equal, the targets moved."""
    algo = _algo(kind)
    with torch.no_grad():
        for p in algo.loss.parameters():
            p.add_(torch.randn_like(p))
    for tau in (None, 0.07):
        if tau is not None:
            algo.cfg.tau = tau
            algo._applied("tau")
        start = copy.deepcopy(algo.loss.state_dict())
        algo.target_update.step()
        expected = copy.deepcopy(algo.loss.state_dict())
        algo.loss.load_state_dict(start)
        algo._soft_update()
        got = algo.loss.state_dict()
        targets = [k for k in got if k.startswith("target_") and "network_params" in k]
        assert targets and all(torch.equal(got[k], expected[k]) for k in got)
        moved = [k for k in targets if not torch.equal(start[k], got[k])]
        assert len(moved) >= 4  # (weights and biases of the twin Q's targets at least)


def test_the_collectors_rollouts_are_new_tensors_each_time():
    """The fast path's iterator hands out each rollout without TorchRL's clone: no rollout may
    share memory with the next one (the replay buffer and the Trainer keep references)."""
    from rlexp.envs.gym import GymnasiumEnv
    from rlexp.training.collector import RolloutCollector

    env = GymnasiumEnv("Pendulum-v1", num_envs=2)
    env.set_seed(0)
    policy = SACPolicy(SACPolicyConfig(actor=MLPConfig([8], "relu")), 3, 1, env.action_spec)
    collector = RolloutCollector(env, policy.sampling_policy(), frames_per_batch=4,
                                 total_frames=-1, trust_policy=True, track_traj_ids=False,
                                 auto_register_policy_transforms=False)  # fmt: skip
    try:
        rollouts = iter(collector)
        first = next(rollouts)
        kept = first.clone()
        second = next(rollouts)
        ptrs = {t.data_ptr() for t in first.values(True, True)}
        assert not ptrs & {t.data_ptr() for t in second.values(True, True)}
        assert (first == kept).all()  # untouched by the next rollout
        assert first.batch_size == (2, 2) and collector._frames == 8
    finally:
        collector.shutdown()


def test_an_image_policys_rollout_steps_use_the_update_threads_and_eval_one(tmp_path, monkeypatch):
    """A CNN policy's collection step is a convolution over every env's frames: it runs with
    ``trainer.torch_threads`` (3 here, mocked 4 CPUs), as the update does; evaluation keeps one
    thread (the same kernels as ``rlexp eval`` and the eval worker). A vector policy's steps keep
    one thread (``test_train.py``, ``test_sac_gradient_steps_use_the_resolved_threads...``)."""
    import rlexp.policies.encoders as encoders
    import rlexp.training.trainer as trainer_module

    monkeypatch.setenv("RLEXP_ENV_MODULES", "image_envs")
    _mock_cpus(monkeypatch, 4)
    seen: dict[str, set[int]] = {"collect": set(), "eval": set(), "update": set()}
    phase = ["collect"]
    scaled, run_round = encoders.scaled, trainer_module.run_round

    def spy_scaled(image):
        where = "update" if torch.is_grad_enabled() else phase[0]
        seen[where].add(torch.get_num_threads())
        return scaled(image)

    def spy_round(*args, **kwargs):
        phase[0] = "eval"
        try:
            return run_round(*args, **kwargs)
        finally:
            phase[0] = "collect"

    monkeypatch.setattr(encoders, "scaled", spy_scaled)
    monkeypatch.setattr(trainer_module, "run_round", spy_round)
    train_here(
        [
            "env=hopper",
            "env.backend=torchrl",
            "env.name=image_envs:make_image_env",
            "env.num_envs=3",
            "env.num_eval_envs=2",
            "policy=cnn",
            "policy.encoder.channels=[4]",
            "policy.encoder.kernel_sizes=[3]",
            "policy.encoder.strides=[2]",
            "policy.encoder.features_dim=8",
            "trainer.frames_per_batch=24",
            "trainer.total_frames=48",
            "trainer.eval_every=24",
            "trainer.eval_episodes=2",
            "trainer.eval_async=false",
            "trainer.save_every=0",
            "trainer.torch_threads=3",
            "algorithm.mini_batch_size=12",
            "algorithm.num_epochs=1",
            "algorithm.compile=false",
            "trainer.progress=false",
            "logger=none",
        ],  # fmt: skip
        tmp_path / "run",
    )
    assert seen == {"collect": {3}, "eval": {1}, "update": {3}}
