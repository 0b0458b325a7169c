"""env.observation_indices: chosen entries of a Box observation, in the order given, on every backend
that builds its observation from a Gymnasium space (gymnasium, gymnasium_async, envpool), checked
against the unfiltered env's own values; recorded in the layout (checkpoints and exports compare
it); refusals are one line (docs/envs.md "Keeping observation entries")."""

from __future__ import annotations

import runpy

import numpy as np
import pytest
import torch
from gymnasium import spaces

from conftest import compose, run_train
from rlexp.envs.layout_check import check_layout
from rlexp.envs.spaces import UnsupportedSpace, obs_layout

KEEP = (3, 0)  # asymmetric and out of order: the env's entry 3 first, then entry 0


def _make(backend: str, n: int, keep: tuple[int, ...] = ()):
    if backend == "gymnasium":
        from rlexp.envs.gym import GymnasiumEnv

        return GymnasiumEnv("CartPole-v1", n, observation_indices=keep)
    if backend == "gymnasium_async":
        from rlexp.envs.gym_async import AsyncGymnasiumEnv

        return AsyncGymnasiumEnv("CartPole-v1", n, observation_indices=keep)
    pytest.importorskip("envpool")
    from rlexp.envs.envpool_env import EnvPoolEnv

    return EnvPoolEnv("CartPole-v1", n, seed=7, observation_indices=keep)


@pytest.mark.parametrize("backend", ["gymnasium", "gymnasium_async", "envpool"])
def test_kept_entries_are_the_unfiltered_env_s_in_the_given_order_across_episode_ends(backend):
    """Two envs of one seed, one keeping entries [3, 0]: every observation (the reset, each step's
    "next" including a finished episode's final one, and the autoreset one) is the unfiltered
    env's columns 3 then 0."""
    kept, full = _make(backend, 2, KEEP), _make(backend, 2)
    try:
        assert kept.observation_spec["observation"].shape == (2, 2)
        kept.set_seed(7)
        full.set_seed(7)
        a, b = kept.reset()["observation"], full.reset()["observation"]
        np.testing.assert_array_equal(a.numpy(), b.numpy()[:, list(KEEP)])
        ends = 0
        for t in range(40):  # pushing right 3 times in 4: episodes end (the pole falls)
            action = torch.full((2, 1), int(t % 4 != 0), dtype=torch.int64)
            nk, nf = kept.step_action(action), full.step_action(action)
            np.testing.assert_array_equal(
                nk["observation"].numpy(), nf["observation"].numpy()[:, list(KEEP)]
            )
            ends += int(nf["done"].sum())
            a, b = kept.autoreset_observation(nk), full.autoreset_observation(nf)
            np.testing.assert_array_equal(a.numpy(), b.numpy()[:, list(KEEP)])
        assert ends >= 2  # the reset path was taken
        assert kept.obs_layout.record()["parts"][0]["indices"] == [3, 0]
    finally:
        kept.close()
        full.close()


def test_a_multi_dimensional_box_is_indexed_flat_in_c_order():
    space = spaces.Box(-1.0, 1.0, (2, 3), np.float32)
    layout = obs_layout(space, "env.name='X'", indices=(5, 1, 3))
    obs = np.arange(6, dtype=np.float32).reshape(2, 3) * 10
    np.testing.assert_array_equal(layout.encode(obs), [50.0, 10.0, 30.0])
    np.testing.assert_array_equal(
        layout.encode_batch(np.stack([obs, obs + 1])), [[50, 10, 30], [51, 11, 31]]
    )
    assert layout.dim == 3 and layout.parts[0].shape == (3,)


@pytest.mark.parametrize(
    ("space", "keep", "words"),
    [
        (
            spaces.Box(-1.0, 1.0, (4,)),
            (0, 4),
            ["env.observation_indices=[0, 4]", "4 values", "0 to 3"],
        ),
        (spaces.Box(-1.0, 1.0, (2, 3)), (6,), ["6 is not an entry", "6 values", "0 to 5"]),
        (spaces.Dict({"a": spaces.Box(-1, 1, (2,))}), (0,), ["Box observation", "Dict"]),
        (spaces.Box(0, 255, (8, 8, 3), np.uint8), (0,), ["Box observation", "an image"]),
    ],
)
def test_what_cannot_be_kept_is_one_line_naming_the_width(space, keep, words):
    with pytest.raises(UnsupportedSpace) as err:
        obs_layout(space, "env.name='X'", indices=keep)
    msg = str(err.value)
    assert "\n" not in msg
    for word in words:
        assert word in msg, msg


class _Base:
    def __init__(self, layout):
        self.obs_layout = layout


def test_a_checkpoint_of_other_kept_entries_is_refused_naming_both():
    box = spaces.Box(-1.0, 1.0, (4,))
    saved = obs_layout(box, "w", indices=(0, 2)).record()
    check_layout(saved, _Base(obs_layout(box, "w", indices=(0, 2))), "checkpoint 'c'")
    for other in ((2, 0), (1, 3)):
        with pytest.raises(ValueError, match=r"entries \[0, 2\].*entries \[" + str(other[0])):
            check_layout(saved, _Base(obs_layout(box, "w", indices=other)), "checkpoint 'c'")
    with pytest.raises(ValueError, match="observation space changed"):  # made without the option
        check_layout(
            obs_layout(box, "w").record(), _Base(obs_layout(box, "w", indices=(0, 1, 2, 3))), "c"
        )


def test_the_export_helper_keeps_the_same_entries(tmp_path):
    from rlexp.deploy.export_obs import helper_source

    layout = obs_layout(spaces.Box(-1.0, 1.0, (4,)), "w", indices=KEEP).record()
    action = {
        "kind": "discrete",
        "shape": [],
        "dim": 1,
        "dtype": "int64",
        "nvec": [2],
        "start": [0],
    }
    path = tmp_path / "policy_obs.py"
    path.write_text(helper_source(tmp_path / "policy.pt", "CartPole-v1", layout, action))
    helper = runpy.run_path(str(path))
    obs = np.array([0.5, -1.0, 2.0, 7.0], dtype=np.float32)
    np.testing.assert_array_equal(helper["flatten"](obs), [[7.0, 0.5]])
    np.testing.assert_array_equal(
        helper["flatten"](np.stack([obs, -obs]), batch=True), [[7.0, 0.5], [-7.0, -0.5]]
    )


@pytest.mark.parametrize(
    ("option", "name", "keep", "rl_zoo_masked"),
    [
        ("cart_pole_novel", "CartPole-v1", [0, 2], [1, 3]),
        ("pendulum_novel", "Pendulum-v1", [0, 1], [2]),
    ],
)
def test_the_no_velocity_env_options_keep_what_rl_zoo_does_not_mask(
    option, name, keep, rl_zoo_masked
):
    """rl-zoo's MaskVelocityWrapper.velocity_indices (rl_zoo3/wrappers.py, 22e3ff2) zeroes entries
    1, 3 of CartPole-v1 and 2 of Pendulum-v1; the env options keep the others."""
    from rlexp.config.validate import to_root_config

    env = to_root_config(compose([f"env={option}"])).env
    width = {"CartPole-v1": 4, "Pendulum-v1": 3}[name]
    assert env.name == name and env.backend == "gymnasium"
    assert (
        list(env.observation_indices) == keep == [i for i in range(width) if i not in rl_zoo_masked]
    )


@pytest.mark.parametrize(
    ("overrides", "words"),
    [
        (["env.observation_indices=[0,0]"], ["env.observation_indices=[0, 0] must be distinct"]),
        (["env.observation_indices=[-1]"], ["env.observation_indices=[-1] must be distinct"]),
        (
            ["env=cart_pole", "env.observation_indices=[0]"],
            ["env.observation_indices=[0]", "'native'"],
        ),
        (["env.backend=torchrl", "env.observation_indices=[1]"], ["'torchrl'"]),
    ],
)
def test_observation_indices_rules_are_one_line_config_errors(overrides, words):
    from rlexp.config.validate import ConfigError, to_root_config

    with pytest.raises(ConfigError) as err:
        to_root_config(compose(["env=gym_cartpole", *overrides]))
    msg = str(err.value)
    assert "\n" not in msg
    for word in words:
        assert word in msg, msg


def test_an_index_past_the_width_is_exit_2_before_the_run_dir(tmp_path):
    run_dir = tmp_path / "r"
    proc = run_train(
        ["env=cart_pole_novel", "env.observation_indices=[2,4]", f"hydra.run.dir={run_dir}"],
        cwd=tmp_path,
        check=False,
    )
    assert proc.returncode == 2, proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, proc.stderr
    assert "env.observation_indices=[2, 4]" in lines[0] and "4 values" in lines[0], lines[0]
    assert "Traceback" not in proc.stderr and not run_dir.exists()
