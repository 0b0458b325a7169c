"""Box action bounds other than [-1, 1] (#45 item 6): one warning per env naming the bounds and
``env.rescale_actions``; with ``env.rescale_actions=true`` the policy acts in [-1, 1] and the env
gets ``low + (a + 1) * (high - low) / 2`` (clipped to [-1, 1] first); refused where it cannot
apply, in one line naming the key."""

from __future__ import annotations

import logging

import numpy as np
import pytest
import torch
import toy_envs  # registers toy_envs:Throttle-v0

from conftest import compose
from rlexp.config.schema import EnvConfig
from rlexp.config.validate import ConfigError, to_root_config
from rlexp.envs import adapter
from rlexp.envs.factory import make_env

THROTTLE = "toy_envs:Throttle-v0"  # actions in [0, 5] x [-3, 1]


def _received(env) -> np.ndarray:
    return np.stack([e.unwrapped.received[-1] for e in env._envs])


def test_rescaled_actions_reach_the_env_mapped_onto_its_bounds():
    env = make_env(EnvConfig(name=THROTTLE, num_envs=3, rescale_actions=True), 3, seed=1)
    try:
        space = env.action_spec.space  # what the policy sees: [-1, 1]
        assert space.low.tolist() == [[-1.0, -1.0]] * 3 and space.high.tolist() == [[1.0, 1.0]] * 3
        env.reset()
        env.step_action(torch.tensor([[-1.0, 1.0], [0.0, -0.5], [3.0, -7.0]]))
        # hand-computed: [0, 5] x [-3, 1]; the last row is clipped to [1, -1] first
        assert _received(env).tolist() == [[0.0, 1.0], [2.5, -2.0], [5.0, -3.0]]
    finally:
        env.close()


def test_without_rescaling_the_env_gets_the_policy_s_action_clipped():
    env = make_env(EnvConfig(name=THROTTLE, num_envs=2), 2, seed=1)
    try:
        assert env.action_spec.space.low[0].tolist() == [0.0, -3.0]
        env.reset()
        env.step_action(torch.tensor([[-1.0, 0.5], [7.0, -4.0]]))
        assert _received(env).tolist() == [[0.0, 0.5], [5.0, -3.0]]
    finally:
        env.close()


def _warnings(caplog, *configs: EnvConfig) -> list[str]:
    """What the run's builder logs for envs of ``configs`` (``warn_action_bounds``, as build())."""
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="rlexp.envs.adapter"):
        for cfg in configs:
            env = make_env(cfg, 1, seed=0)
            env.warn_action_bounds()
            env.close()
    return [r.getMessage() for r in caplog.records]


def test_bounds_other_than_unit_are_warned_about_once(caplog, monkeypatch):
    monkeypatch.setattr(adapter, "_BOUNDS_WARNED", set())
    lines = _warnings(
        caplog,
        EnvConfig(name=THROTTLE),
        EnvConfig(name=THROTTLE),  # once per env id and process
        EnvConfig(name="Hopper-v5"),  # [-1, 1]: nothing to say
        EnvConfig(name=THROTTLE, rescale_actions=True),
    )
    assert len(lines) == 1, lines
    assert "env.name='toy_envs:Throttle-v0'" in lines[0]
    assert "low=[0.0, -3.0] high=[5.0, 1.0]" in lines[0] and "not symmetric" in lines[0]
    assert "env.rescale_actions=true" in lines[0]
    [line] = _warnings(caplog, EnvConfig(name="Pendulum-v1"))  # symmetric, not unit
    assert "[-2, 2] are not [-1, 1]" in line
    monkeypatch.setattr(adapter, "_BOUNDS_WARNED", set())
    assert _warnings(caplog, EnvConfig(name=THROTTLE, rescale_actions=True)) == []


def test_rescaling_is_refused_where_it_cannot_apply():
    with pytest.raises(ValueError, match=r"^env.rescale_actions=true \(env.name='CartPole-v1'\)"):
        make_env(EnvConfig(name="CartPole-v1", rescale_actions=True), 1, seed=0)
    with pytest.raises(ConfigError) as err:
        to_root_config(compose(["env=cart_pole", "env.rescale_actions=true"]))
    assert str(err.value).startswith("env.rescale_actions=true maps") and "native" in str(err.value)


class _Pump(toy_envs.Throttle):
    action_space = toy_envs.spaces.Box(0.0, 5.0, (2,), np.float32)


def test_the_docs_warning_line_is_what_users_get(caplog, monkeypatch):
    from conftest import REPO

    documented = next(
        line
        for line in (REPO / "docs" / "envs.md").read_text().splitlines()
        if line.startswith("env.name='my_pkg.envs:Pump-v0': the action bounds")
    )
    import gymnasium as gym

    if "Pump-v0" not in gym.registry:
        gym.register("Pump-v0", entry_point=_Pump, max_episode_steps=5)
    monkeypatch.setattr(adapter, "_BOUNDS_WARNED", set())
    [line] = _warnings(caplog, EnvConfig(name="Pump-v0"))
    assert line == documented.replace("my_pkg.envs:Pump-v0", "Pump-v0")


@pytest.mark.parametrize("backend", ["gymnasium_async", "envpool"])
def test_the_vector_backends_rescale_as_the_env_would_by_hand(backend):
    """Pendulum-v1's torque in [-2, 2]: a rescaled env given ``a`` steps as the plain env of the
    same backend given ``2 * a`` (clipped to [-1, 1] first), observation for observation."""
    if backend == "envpool":
        pytest.importorskip("envpool")
    actions = torch.tensor([[0.5], [-1.0], [3.0]])  # the last clips to 1 -> torque 2
    by_hand = torch.tensor([[1.0], [-2.0], [2.0]])
    seen = []
    for rescale, given in ((True, actions), (False, by_hand)):
        cfg = EnvConfig(name="Pendulum-v1", backend=backend, num_envs=3, rescale_actions=rescale)
        env = make_env(cfg, 3, seed=4)
        try:
            env.reset()
            seen.append(env.step_action(given)["observation"].clone())
        finally:
            env.close()
    torch.testing.assert_close(seen[0], seen[1], rtol=0, atol=0)
