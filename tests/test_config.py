"""Every file in conf/ composes and builds; mistakes fail at compose time naming the key."""

from __future__ import annotations

import pytest
import torch
from hydra.errors import ConfigCompositionException
from omegaconf.errors import ConfigKeyError, ValidationError

from conftest import CONF_DIR, compose, run_train
from rlexp.config.schema import GROUP_SCHEMAS, RootConfig
from rlexp.config.validate import ConfigError, to_root_config

GROUP_OPTIONS = [
    (group, path.stem)
    for group in GROUP_SCHEMAS
    for path in sorted((CONF_DIR / group).glob("*.yaml"))
]


def test_every_group_has_options_and_names_its_schema():
    from rlexp.config.schema import VARIANT_SCHEMAS

    for group, (schema_name, _) in GROUP_SCHEMAS.items():
        files = sorted((CONF_DIR / group).glob("*.yaml"))
        assert files, f"conf/{group}/ is empty"
        names = [schema_name, *(n for n, (g, _) in VARIANT_SCHEMAS.items() if g == group)]
        for f in files:
            assert any(f"- {name}\n" in f.read_text() for name in names), (
                f"{f} does not name one of {names} in its defaults"
            )


@pytest.mark.parametrize(
    ("group", "option"), GROUP_OPTIONS, ids=[f"{g}={o}" for g, o in GROUP_OPTIONS]
)
def test_every_conf_file_composes_to_a_typed_config(group, option):
    # An option that needs another choice is composed with it (GRPO's groups are blocks of envs;
    # PPO needs a critic, which the actor-only policies have not).
    needs = {
        "algorithm=grpo": ["env.num_envs=4"],
        "env=gym": ["env.name=Acrobot-v1"],  # any Gymnasium id: the user names it
        "policy=actor_only": ["algorithm=grpo", "env.num_envs=4"],
        "policy=actor_only_256": ["algorithm=grpo", "env.num_envs=4"],
        "policy=sac": ["algorithm=sac"],  # SAC's / TD3's networks are theirs alone
        "policy=td3": ["algorithm=td3"],
    }
    if group in ("sac_zoo", "td3_zoo"):  # an off-policy preset sets its algorithm's keys
        needs[f"{group}={option}"] = [f"algorithm={group.split('_')[0]}"]
    config = to_root_config(compose([f"{group}={option}", *needs.get(f"{group}={option}", [])]))
    assert isinstance(config, RootConfig)


@pytest.mark.parametrize("option", sorted(p.stem for p in (CONF_DIR / "env").glob("*.yaml")))
def test_every_env_builds_with_policy_and_ppo(option):
    from rlexp.algorithms.ppo import make_algorithm
    from rlexp.envs.factory import make_env
    from rlexp.policies.actor_critic import policy_for_env
    from rlexp.policies.inputs import layout_of

    named = ["env.name=Acrobot-v1"] if option == "gym" else []  # env=gym: the user names the id
    config = to_root_config(
        compose([f"env={option}", *named, "env.num_envs=2", "trainer.frames_per_batch=64"])
    )
    env = make_env(config.env, 2, seed=0)
    try:
        policy = policy_for_env(config.policy, config.env, env)
        make_algorithm(config.algorithm, policy, total_iterations=1)
        td = env.reset()
        layout = layout_of(env)
        if layout.structured:  # images: uint8 [2, C, H, W] entries beside the float32 vector
            obs = td["observation"]
            for part in layout.images:
                assert obs[part.image_key].dtype == torch.uint8
                assert obs[part.image_key].shape == (2, *part.shape)
            assert ("vector" in obs.keys()) == (layout.dim > 0)
        else:
            obs_dim = layout.dim
            assert td["observation"].dtype.is_floating_point
            assert td["observation"].shape == (2, obs_dim)
        out = env.rand_step(td)
        assert out["next", "reward"].shape == (2, 1)
    finally:
        env.close()


def test_override_syntax_as_hydra_users_expect():
    config = to_root_config(compose(["env=hopper", "algorithm.clip_epsilon=0.1", "seed=3"]))
    assert config.env.name == "Hopper-v5"
    assert config.algorithm.clip_epsilon == 0.1
    assert config.seed == 3


def test_misspelled_key_fails_at_compose_naming_the_key():
    with pytest.raises((ConfigCompositionException, ConfigKeyError)) as err:
        compose(["algorithm.clip_epsiln=0.1"])
    assert "clip_epsiln" in str(err.value)


def test_misspelled_key_in_a_yaml_file_fails(tmp_path):
    # A group file that misspells a field is rejected against its schema.
    import shutil

    from hydra import compose as hcompose
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    conf = tmp_path / "conf"
    shutil.copytree(CONF_DIR, conf)
    (conf / "algorithm" / "typo.yaml").write_text(
        "defaults:\n  - algorithm_schema\n  - _self_\nclip_epsiln: 0.3\n"
    )
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(conf), version_base="1.3"):
        with pytest.raises(Exception) as err:
            hcompose(config_name="config", overrides=["algorithm=typo"])
    assert "clip_epsiln" in str(err.value)


def test_wrong_type_fails_at_compose_naming_the_key():
    with pytest.raises((ConfigCompositionException, ValidationError)) as err:
        compose(["algorithm.num_epochs=ten"])
    msg = str(err.value)
    assert "num_epochs" in msg and "ten" in msg


def test_cross_field_rule_names_both_keys():
    with pytest.raises(ConfigError) as err:
        to_root_config(compose(["env.num_envs=3", "trainer.frames_per_batch=1000"]))
    assert "trainer.frames_per_batch=1000" in str(err.value) and "env.num_envs=3" in str(err.value)


def test_unknown_gym_env_suggests_the_closest(tmp_path):
    from rlexp.envs.gym import check_gym_id

    with pytest.raises(KeyError) as err:
        check_gym_id("HalfCheeta-v5")
    assert "HalfCheetah-v5" in str(err.value)


def test_bad_override_on_the_command_line_is_one_clear_error(tmp_path):
    proc = run_train(["algorithm.clip_epsiln=0.1"], cwd=tmp_path, check=False, timeout=120)
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [proc.stderr.strip()], "one line, no traceback"
    assert "algorithm.clip_epsiln is not a config key" in proc.stderr
    assert "did you mean algorithm.clip_epsilon?" in proc.stderr
    assert not (tmp_path / "outputs").exists()


def test_activation_names_checked_before_torch_are_the_builders():
    from rlexp.config.validate import ACTIVATIONS
    from rlexp.policies.actor_critic import ACTIVATIONS as BUILT

    assert sorted(ACTIVATIONS) == sorted(BUILT)


def test_cross_field_error_on_the_command_line_exits_2(tmp_path):
    proc = run_train(
        ["env.num_envs=3", "trainer.frames_per_batch=1000"], cwd=tmp_path, check=False, timeout=120
    )
    assert proc.returncode == 2, proc.stderr
    assert "trainer.frames_per_batch=1000" in proc.stderr + proc.stdout
    assert "Traceback" not in proc.stderr


def test_several_loggers_at_once():
    config = to_root_config(compose(["logger=[tensorboard,wandb]"]))
    assert config.logger.tensorboard.enabled and config.logger.wandb.enabled
    config = to_root_config(compose(["logger=none"]))
    assert not config.logger.tensorboard.enabled and not config.logger.wandb.enabled


@pytest.mark.parametrize("name", sorted(p.stem for p in (CONF_DIR / "experiment").glob("*.yaml")))
def test_every_experiment_preset_composes(name):
    config = to_root_config(compose([f"+experiment={name}"]))
    assert isinstance(config, RootConfig)


def test_the_throughput_preset_batches_envs_on_any_gymnasium_task():
    """+experiment=mujoco_throughput over the env chosen on the command line (docs/results.md)."""
    config = to_root_config(compose(["env=hopper", "+experiment=mujoco_throughput"]))
    assert config.env.name == "Hopper-v5"
    assert (config.env.num_envs, config.trainer.frames_per_batch) == (4, 4096)
    assert config.algorithm.mini_batch_size == 128
    assert config.trainer.frames_per_batch // config.algorithm.mini_batch_size == 2048 // 64
