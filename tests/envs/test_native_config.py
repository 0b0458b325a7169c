"""conf/env/{push_cube,cart_pole}.yaml compose, build, and carry the users' task-file terms."""

from __future__ import annotations

import json
from dataclasses import asdict

import pytest

from conftest import SHARED, compose
from rlexp.config.validate import to_root_config
from rlexp.envs.native import default_task_config, make_native_env


@pytest.mark.parametrize(
    ("name", "num_envs", "steps"), [("push_cube", 64, 100), ("cart_pole", 64, 500)]
)
def test_yaml_composes_to_the_default_task_config(name, num_envs, steps):
    config = to_root_config(compose([f"env={name}"]))
    env_cfg = config.env
    assert (env_cfg.backend, env_cfg.name, env_cfg.num_envs, env_cfg.max_episode_steps) == (
        "native",
        name,
        num_envs,
        steps,
    )
    assert asdict(env_cfg.native) == asdict(default_task_config(name))
    env = make_native_env(env_cfg.native, 2, seed=0, max_episode_steps=env_cfg.max_episode_steps)
    assert env.max_episode_steps == steps


@pytest.mark.parametrize("name", ["push_cube", "cart_pole"])
def test_task_file_terms_are_mirrored(name):
    path = SHARED / "seed-configs" / name / "gym_config.json"
    if not path.exists():
        pytest.skip(f"users' task file not present at {path}")
    file_env = json.loads(path.read_text())["env"]
    ours = asdict(default_task_config(name))
    for section in ("events", "observations", "rewards", "actions"):
        for key, term in file_env[section].items():
            assert key in ours[section], f"{section}.{key} missing"
            for field, value in term.items():
                assert ours[section][key][field] == value, f"{section}.{key}.{field}"
    assert file_env["extensions"].items() <= ours["extensions"].items()


def test_yaml_typo_in_term_name_fails_with_suggestion():
    config = to_root_config(
        compose(["env=push_cube", "env.native.rewards.goal_distance_reward.func=distance_to_targt"])
    )
    with pytest.raises(KeyError, match="did you mean 'distance_to_target'"):
        make_native_env(config.env.native, 1, seed=0)
