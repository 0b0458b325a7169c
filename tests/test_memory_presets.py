"""The recurrent presets against rl-zoo's ``hyperparams/ppo_lstm.yml`` entries as that file writes
them (DLR-RM/rl-baselines3-zoo 22e3ff2), translated by hand: a key the preset drops or mistranslates
fails here; and the MLP baseline differs from its LSTM preset in the policy alone."""

from __future__ import annotations

import pytest

from conftest import CONF_DIR, compose
from rlexp.config.validate import ConfigError, to_root_config

#: rl-zoo's entries: n_envs, n_steps, batch_size (PendulumNoVel: RecurrentPPO's default 128),
#: gae_lambda, gamma, n_epochs, ent_coef, learning_rate (lin_: annealed), n_timesteps.
ZOO = {
    "cart_pole_novel_lstm": (8, 32, 256, 0.8, 0.98, 20, 0.0, (1e-3, True), 100_000),
    "pendulum_novel_lstm": (4, 1024, 128, 0.95, 0.9, 10, 0.0, (1e-3, False), 100_000),
}


@pytest.mark.parametrize("preset", sorted(ZOO))
def test_the_recurrent_preset_is_rl_zoo_s_entry(preset):
    c = to_root_config(compose([f"+experiment={preset}"]))
    n_envs, n_steps, batch, lam, gamma, epochs, ent, (lr, lin), steps = ZOO[preset]
    a, p = c.algorithm, c.policy
    assert c.env.num_envs == n_envs and c.trainer.frames_per_batch == n_envs * n_steps
    assert (a.mini_batch_size, a.lmbda, a.gamma, a.num_epochs, a.entropy_coeff) == (
        batch, lam, gamma, epochs, ent
    )  # fmt: skip
    assert (a.lr, a.anneal_lr, a.clip_epsilon) == (lr, lin, 0.2)
    assert abs(c.trainer.total_frames - steps) <= n_envs * n_steps  # whole rollouts
    # normalize: True (VecNormalize: observations, and rewards clipped at 10)
    assert c.env.normalize_observations and a.normalize_rewards and a.clip_rewards == 10.0
    # lstm_hidden_size=64, enable_critic_lstm=True, n_lstm_layers 1
    assert (p.memory.type, p.memory.hidden_size, p.memory.num_layers, p.memory.shared) == (
        "lstm", 64, 1, False
    )  # fmt: skip
    # net_arch=dict(pi=[64], vf=[64]), activation_fn=nn.ReLU, ortho_init=False
    assert (p.actor.hidden_sizes, p.critic.hidden_sizes) == ([64], [64])
    assert (p.actor.activation, p.critic.activation, p.ortho_init) == ("relu", "relu", False)
    # RecurrentPPO's sequences: an env's n_steps (CartPole), a minibatch's 128 steps (Pendulum)
    assert a.sequence_length == min(n_steps, batch)


def test_the_mlp_baseline_differs_from_the_lstm_preset_in_the_policy_alone():
    lstm = to_root_config(compose(["+experiment=cart_pole_novel_lstm"]))
    mlp = to_root_config(compose(["+experiment=cart_pole_novel_ppo"]))
    assert mlp.policy.memory.type == "none" and mlp.policy.actor.hidden_sizes == [64, 64]
    assert mlp.env == lstm.env and mlp.trainer == lstm.trainer
    assert {**vars(mlp.algorithm), "sequence_length": 0} == {
        **vars(lstm.algorithm),
        "sequence_length": 0,
    }


# -- a preset for a velocity-hidden task is not the full task's (same env id, other entries) -------
@pytest.mark.parametrize(
    "overrides, kept",
    [
        (["+experiment=cart_pole_novel_lstm", "env=gym_cartpole"], "None"),
        (["+experiment=cart_pole_novel_lstm", "env.observation_indices=[2,0]"], "[2, 0]"),
        (["+experiment=cartpole_ppo", "env=cart_pole_novel"], "[0, 2]"),
        (["+experiment=pendulum_novel_lstm", "env=pendulum"], "None"),
        (["-m", "+experiment=cart_pole_novel_lstm", "env=cart_pole_novel,gym_cartpole"], "None"),
    ],
)
def test_a_preset_for_other_observation_entries_is_refused(overrides, kept, tmp_path):
    from rlexp.launch.precheck import precheck

    with pytest.raises(ConfigError) as err:
        precheck([*overrides, "trainer.total_frames=256", f"hydra.run.dir={tmp_path / 'r'}",
                  f"hydra.sweep.dir={tmp_path / 's'}"], CONF_DIR)  # fmt: skip
    msg = str(err.value)
    assert "\n" not in msg and f"this run has env.observation_indices={kept}" in msg, msg
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize(
    "overrides",
    [
        ["+experiment=cart_pole_novel_lstm"],
        ["+experiment=cart_pole_novel_ppo"],
        ["+experiment=cartpole_ppo"],
        ["-m", "+experiment=cart_pole_novel_lstm", "seed=1,2"],
    ],
)
def test_a_preset_on_its_own_observation_entries_passes(overrides, tmp_path):
    from rlexp.launch.precheck import precheck

    precheck([*overrides, "trainer.total_frames=256", f"hydra.run.dir={tmp_path / 'r'}",
              f"hydra.sweep.dir={tmp_path / 's'}"], CONF_DIR)  # fmt: skip
