"""The native batched MuJoCo tasks: specs, resets, flags, reward terms, auto-reset, seeding, resume."""

from __future__ import annotations

import copy
import math

import mujoco
import numpy as np
import pytest
import torch
from torchrl.envs.utils import check_env_specs

from rlexp.envs.native import (
    EVENTS,
    OBSERVATIONS,
    REWARDS,
    TASKS,
    default_task_config,
    make_native_env,
)
from rlexp.envs.native.kinematics import quat_to_mat


def push_env(n: int = 4, seed: int = 0, **kw):
    return make_native_env(default_task_config("push_cube"), n, seed, **kw)


def cart_env(n: int = 4, seed: int = 0, **kw):
    return make_native_env(default_task_config("cart_pole"), n, seed, **kw)


def place(env, env_id: int, cube=None, goal=None, arm=None) -> None:
    """Put the cube / goal / arm of one env where a test wants them, at rest."""
    ids = np.array([env_id])
    if arm is not None:
        env.set_robot_state(ids, np.asarray(arm, float)[None])
    if cube is not None:
        env.set_object_pose("cube", ids, np.asarray(cube, float)[None], np.array([[1.0, 0, 0, 0]]))
    if goal is not None:
        env.set_target("goal_pose", ids, np.asarray(goal, float)[None])


def mujoco_data(env, env_id: int) -> mujoco.MjData:
    """An independent MjData holding env ``env_id``'s state, forwarded by MuJoCo itself."""
    d = mujoco.MjData(env.model)
    mujoco.mj_setState(env.model, d, env._state[env_id], mujoco.mjtState.mjSTATE_FULLPHYSICS)
    d.ctrl[:] = env._ctrl[env_id]
    mujoco.mj_forward(env.model, d)
    return d


# --- specs and layout ------------------------------------------------------------------------------


@pytest.mark.parametrize("task", ["push_cube", "cart_pole"])
def test_check_env_specs(task):
    env = make_native_env(default_task_config(task), 3, seed=0)
    check_env_specs(env)
    td = env.reset()
    assert td["observation"].dtype == torch.float32 and td["observation"].shape == (3, env.obs_dim)
    out = env.rand_step(td)["next"]
    assert out["reward"].shape == (3, 1) and out["reward"].dtype == torch.float32
    for key in ("done", "terminated", "truncated"):
        assert out[key].shape == (3, 1) and out[key].dtype == torch.bool
    assert set(out["rewards"].keys()) == set(default_task_config(task).rewards)
    assert out["metrics", "success"].shape == (3, 1)


def test_push_cube_observation_layout_sorted_and_sized():
    env = push_env(2)
    names = [name for name, *_ in env.observation_layout]
    assert names == [
        "object/cube_pos",
        "object/goal_pos",
        "robot/ee_pos",
        "robot/qf",
        "robot/qpos",
        "robot/qvel",
        "privileged/cube_to_goal",  # the critic group, after the policy's (#47)
        "privileged/cube_vel",
    ]
    sizes = {name: stop - start for name, start, stop, _ in env.observation_layout}
    assert sizes == {
        "object/cube_pos": 16,
        "object/goal_pos": 3,
        "robot/ee_pos": 16,
        "robot/qf": 6,
        "robot/qpos": 6,
        "robot/qvel": 6,
        "privileged/cube_to_goal": 3,
        "privileged/cube_vel": 3,
    }
    assert env.obs_dim == 59 and env.action_spec.shape == (2, 6)
    assert [n for n, *_ in cart_env(1).observation_layout] == [
        "robot/qf",
        "robot/qpos",
        "robot/qvel",
    ]


def test_observation_values_match_mujoco():
    env = push_env(3, seed=1)
    env.reset()
    env.rand_step(env.reset())
    rng = np.random.default_rng(0)
    place(env, 1, arm=env.robot_init_qpos + rng.uniform(-0.5, 0.5, 6))
    env.qvel[1, :6] = rng.uniform(-1, 1, 6)
    env._ctrl[1] += rng.uniform(-0.05, 0.05, 6)
    obs = torch.from_numpy(env._observe()[0])[1].double().numpy()
    d = mujoco_data(env, 1)
    lay = {name: (start, stop) for name, start, stop, _ in env.observation_layout}
    site = env.model.site("ee_site").id
    ee = np.eye(4)
    ee[:3, :3] = d.site_xmat[site].reshape(3, 3)
    ee[:3, 3] = d.site_xpos[site]
    np.testing.assert_allclose(obs[slice(*lay["robot/ee_pos"])], ee.ravel(), atol=1e-6)
    np.testing.assert_allclose(
        obs[slice(*lay["robot/qf"])], d.qfrc_actuator[:6], rtol=1e-5, atol=1e-4
    )
    low, high = env.model.jnt_range[:6, 0], env.model.jnt_range[:6, 1]
    np.testing.assert_allclose(
        obs[slice(*lay["robot/qpos"])], (d.qpos[:6] - low) / (high - low), atol=1e-6
    )
    np.testing.assert_allclose(obs[slice(*lay["robot/qvel"])], d.qvel[:6], atol=1e-6)
    cube = np.eye(4)
    cube[:3, :3] = d.xmat[env.model.body("cube").id].reshape(3, 3)
    cube[:3, 3] = d.xpos[env.model.body("cube").id]
    np.testing.assert_allclose(obs[slice(*lay["object/cube_pos"])], cube.ravel(), atol=1e-6)
    np.testing.assert_allclose(
        obs[slice(*lay["object/goal_pos"])], env.target("goal_pose")[1], atol=1e-6
    )


def test_quat_to_mat_matches_mujoco():
    q = np.random.default_rng(0).normal(size=(5, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    for i in range(5):
        m = np.zeros(9)
        mujoco.mju_quat2Mat(m, q[i])
        np.testing.assert_allclose(quat_to_mat(q[i : i + 1])[0], m.reshape(3, 3), atol=1e-12)


# --- reset ranges -----------------------------------------------------------------------------------


def test_push_cube_reset_ranges():
    env = push_env(256, seed=3)
    env.reset()
    cube, quat = env.object_pose("cube")
    goal = env.target("goal_pose")
    assert np.all(np.abs(cube[:, 0] - (-0.6)) <= 0.2) and np.all(np.abs(cube[:, 1] - (-0.4)) <= 0.2)
    np.testing.assert_allclose(cube[:, 2], 0.05)
    np.testing.assert_allclose(quat, np.tile([1.0, 0, 0, 0], (256, 1)))
    assert np.all(np.abs(goal[:, :2]) <= 0.3) and np.allclose(goal[:, 2], 0.05)
    # the draws really spread over the ranges
    assert (
        np.ptp(cube[:, 0]) > 0.35
        and np.ptp(cube[:, 1]) > 0.35
        and np.ptp(goal[:, :2], axis=0).min() > 0.5
    )
    np.testing.assert_allclose(env.robot_qpos(), np.tile(env.robot_init_qpos, (256, 1)))
    assert np.all(env.qvel == 0) and np.all(env.episode_step == 0)


def test_cart_pole_reset_range():
    env = cart_env(128, seed=3)
    env.reset()
    q = env.robot_qpos()
    assert np.all(np.abs(q - np.array([-0.2, 0.07])) <= 0.05 + 1e-12)
    assert np.ptp(q[:, 0]) > 0.08


def test_scene_init_qpos_override_and_unknown_key():
    cfg = default_task_config("push_cube")
    cfg.scene = {"init_qpos": [0.0, -1.57, 1.57, -1.57, -1.57, 0.0], "cube_mass": 1.0}
    env = make_native_env(cfg, 2, seed=0)
    env.reset()
    np.testing.assert_allclose(env.robot_qpos()[0], [0.0, -1.57, 1.57, -1.57, -1.57, 0.0])
    assert env.model.body_mass[env.model.body("cube").id] == pytest.approx(1.0)
    cfg.scene = {"cube_mas": 1.0}
    with pytest.raises(KeyError, match="cube_mas.*did you mean 'cube_mass'"):
        make_native_env(cfg, 1, seed=0)


# --- reward terms against hand computations ------------------------------------------------------


def test_push_cube_reward_terms_by_hand():
    env = push_env(2)
    env.reset()
    place(env, 0, cube=[-0.2, -0.3, 0.05], goal=[0.1, 0.1, 0.05])
    ee = mujoco_data(env, 0).site_xpos[env.model.site("ee_site").id]
    # reaching: point 0.03 behind the cube (away from the goal, direction (0.6, 0.8)) and 0.015 up
    behind = np.array([-0.2 - 0.03 * 0.6, -0.3 - 0.03 * 0.8, 0.05 + 0.015])
    expected = 1 - math.tanh(8.0 * float(np.linalg.norm(ee - behind)))
    params = default_task_config("push_cube").rewards
    assert REWARDS.get("reaching_behind_object")(env, **params["reaching_reward"].params)[
        0
    ] == pytest.approx(expected, abs=1e-5)
    # cube-goal distance in xy is 0.5: exp(-0.25 / (2 * 0.12^2))
    got = REWARDS.get("distance_to_target")(env, **params["goal_distance_reward"].params)[0]
    assert got == pytest.approx(math.exp(-0.25 / 0.0288), rel=1e-9)
    # success: not yet; then within 0.1 in xy (z ignored)
    assert not env.task_spec.success(env)[0]
    place(env, 0, cube=[0.16, 0.1, 0.3])
    assert env.task_spec.success(env)[0]
    env.success[:] = env.task_spec.success(env)  # success_reward reports the step's success flag
    assert REWARDS.get("success_reward")(env).tolist() == [1.0, 0.0]
    place(env, 0, cube=[0.1, 0.21, 0.05])
    assert not env.task_spec.success(env)[0]


def test_step_reports_weighted_terms_and_their_sum():
    env = push_env(4, seed=2)
    td = env.reset()
    weights = {k: t.weight for k, t in default_task_config("push_cube").rewards.items()}
    a1 = torch.tensor([[0.5, -0.5, 0.2, 0.0, 0.1, -0.3]]).repeat(4, 1)
    a2 = torch.tensor([[0.1, -0.5, 0.6, 0.3, 0.1, 1.7]]).repeat(4, 1)  # 1.7 is clipped to 1
    out1 = env.step(td.set("action", a1))["next"]
    assert torch.all(out1["rewards", "action_penalty"] == 0)  # first step of the episode
    out2 = env.step(out1.clone().set("action", a2))["next"]
    delta = np.array([0.4, 0.0, 0.4, 0.3, 0.0, 1.3])
    np.testing.assert_allclose(
        out2["rewards", "action_penalty"].numpy()[:, 0], -0.01 * np.linalg.norm(delta), rtol=1e-6
    )
    # every term at the post-step state, weighted; the reward is their sum
    cfg = default_task_config("push_cube")
    total = np.zeros(4)
    for key, term in cfg.rewards.items():
        if key == "action_penalty":
            value = out2["rewards", key].numpy()[:, 0]
        else:
            value = weights[key] * REWARDS.get(term.func)(env, **term.params)
            np.testing.assert_allclose(
                out2["rewards", key].numpy()[:, 0], value, rtol=1e-6, atol=1e-7
            )
        total += value
    np.testing.assert_allclose(out2["reward"].numpy()[:, 0], total, rtol=1e-5, atol=1e-6)


def test_cart_pole_reward_terms_by_hand():
    env = cart_env(2)
    env.reset()
    env.set_robot_state(np.array([0]), np.array([[0.3, 0.2]]), np.array([[1.5, -2.0]]))
    cfg = default_task_config("cart_pole").rewards
    assert REWARDS.get("upright_reward")(env, **cfg["upright"].params)[0] == pytest.approx(
        math.cos(0.2)
    )
    # the file's velocity penalty is on part "hand" = the pole hinge only: -|qvel_pole|
    assert REWARDS.get("joint_velocity_penalty")(env, **cfg["velocity_penalty"].params)[
        0
    ] == pytest.approx(-2.0)
    assert REWARDS.get("joint_velocity_penalty")(env)[0] == pytest.approx(-math.hypot(1.5, 2.0))


# --- success, termination, truncation -------------------------------------------------------------


def test_push_cube_success_terminates_and_auto_resets():
    env = push_env(3, seed=4)
    td = env.reset()
    place(env, 1, cube=[0.0, 0.0, 0.05], goal=[0.03, 0.04, 0.05])  # 0.05 from the goal
    td.set("action", torch.zeros(3, 6))
    out, td_next = env.step_and_maybe_reset(td)
    nxt = out["next"]
    assert nxt["terminated"][:, 0].tolist() == [False, True, False]
    assert nxt["truncated"].sum() == 0 and nxt["done"][:, 0].tolist() == [False, True, False]
    assert nxt["metrics", "success"][:, 0].tolist() == [0.0, 1.0, 0.0]
    assert nxt["rewards", "success_bonus"][1, 0] == 10.0
    # "next" holds the true final observation; the root of the following step the reset one
    lay = {name: (start, stop) for name, start, stop, _ in env.observation_layout}
    final_cube = nxt["observation"][1, slice(*lay["object/cube_pos"])].reshape(4, 4)[:3, 3]
    assert torch.allclose(final_cube, torch.tensor([0.0, 0.0, 0.05]), atol=5e-3)
    reset_cube = td_next["observation"][1, slice(*lay["object/cube_pos"])].reshape(4, 4)[:3, 3]
    assert abs(reset_cube[0] + 0.6) <= 0.2 and abs(reset_cube[1] + 0.4) <= 0.2
    assert torch.equal(td_next["observation"][[0, 2]], nxt["observation"][[0, 2]])
    assert env.episode_step.tolist() == [1, 0, 1]


def test_auto_reset_happens_in_step_and_reset_does_not_step_physics():
    env = push_env(2, seed=5)
    td = env.reset()
    place(env, 0, cube=[0.0, 0.0, 0.05], goal=[0.0, 0.0, 0.05])
    out = env.step(td.set("action", torch.zeros(2, 6)))
    state_after_step = env._state.copy()
    assert env.episode_step.tolist() == [0, 1]  # env 0 already reset inside step()
    from torchrl.envs.utils import step_mdp

    nxt = step_mdp(out)
    assert env.any_done(nxt)
    reset_td = env.reset(nxt, select_reset_only=True)
    np.testing.assert_array_equal(env._state, state_after_step)  # no physics, no second draw
    assert not reset_td["done"].any()
    # a masked reset of an env that did not finish resets it now
    mask = torch.tensor([[False], [True]])
    env.reset(env.current_tensordict().set("_reset", mask))
    assert env.episode_step.tolist() == [0, 0]
    assert not np.array_equal(env._state[1], state_after_step[1])


def test_time_limit_truncates_and_cube_fall_truncates():
    env = push_env(2, seed=6, max_episode_steps=5)
    td = env.reset()
    zero = torch.zeros(2, 6)
    for i in range(5):
        out, td = env.step_and_maybe_reset(td.set("action", zero))
        nxt = out["next"]
        assert bool(nxt["truncated"].all()) == (i == 4)
        assert not nxt["terminated"].any()
    assert env.episode_step.tolist() == [0, 0]
    assert not env.task_spec.truncated(env).any()
    env.model.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_CONTACT  # let the cube fall through
    place(env, 0, cube=[-0.6, -0.4, -0.2])
    out, td = env.step_and_maybe_reset(td.set("action", zero))
    assert out["next", "truncated"][:, 0].tolist() == [True, False]
    assert out["next", "terminated"][:, 0].tolist() == [False, False]


def test_cart_pole_terminates_when_pole_falls_or_cart_leaves_track():
    env = cart_env(3, seed=0)
    td = env.reset()
    env.set_robot_state(np.array([0]), np.array([[0.0, 0.45]]))  # past the 0.4 rad limit
    env.set_robot_state(np.array([1]), np.array([[1.85, 0.0]]))  # past the 1.8 m track limit
    out = env.step(td.set("action", torch.zeros(3, 1)))["next"]
    assert out["terminated"][:, 0].tolist() == [True, True, False]
    assert out["metrics", "success"].sum() == 0


def test_cart_pole_success_is_surviving_the_time_limit():
    env = cart_env(2, seed=0, max_episode_steps=3)
    td = env.reset()
    for _ in range(3):
        out, td = env.step_and_maybe_reset(td.set("action", torch.zeros(2, 1)))
    assert out["next", "truncated"].all() and out["next", "metrics", "success"].sum() == 2


# --- determinism and exact resume ----------------------------------------------------------------


def _rollout(env, td, steps: int, seed: int):
    gen = torch.Generator().manual_seed(seed)
    obs, rewards = [], []
    for _ in range(steps):
        td.set("action", torch.rand(env.action_spec.shape, generator=gen) * 2 - 1)
        out, td = env.step_and_maybe_reset(td)
        obs.append(out["next", "observation"].clone())
        rewards.append(out["next", "reward"].clone())
    return torch.stack(obs), torch.stack(rewards), td


def test_same_seed_same_trajectories():
    a, b, c = (
        push_env(4, seed=11, max_episode_steps=20),
        push_env(4, seed=11, max_episode_steps=20),
        push_env(4, seed=12, max_episode_steps=20),
    )
    oa, ra, _ = _rollout(a, a.reset(), 50, seed=0)
    ob, rb, _ = _rollout(b, b.reset(), 50, seed=0)
    oc, _, _ = _rollout(c, c.reset(), 50, seed=0)
    assert torch.equal(oa, ob) and torch.equal(ra, rb)
    assert not torch.equal(oa, oc)


def test_set_seed_reseeds():
    env = cart_env(4, seed=1)
    env.set_seed(7)
    first = env.reset()["observation"].clone()
    env.set_seed(7)
    assert torch.equal(env.reset()["observation"], first)


@pytest.mark.parametrize("task", ["push_cube", "cart_pole"])
def test_state_dict_resume_is_bit_identical(task):
    cfg = default_task_config(task)
    env = make_native_env(cfg, 4, seed=21, max_episode_steps=15)
    _, _, td = _rollout(env, env.reset(), 23, seed=1)
    saved = copy.deepcopy(env.state_dict())
    saved_td = td.clone()
    o1, r1, _ = _rollout(env, td, 30, seed=2)

    other = make_native_env(cfg, 4, seed=999, max_episode_steps=15)
    other.reset()
    other.load_state_dict(saved)
    assert torch.equal(other.current_tensordict()["observation"], saved_td["observation"])
    o2, r2, _ = _rollout(other, saved_td, 30, seed=2)
    assert torch.equal(o1, o2) and torch.equal(r1, r2)


def test_state_dict_is_plain_data():
    sd = push_env(2).state_dict()
    for key in ("qpos", "qvel", "act", "ctrl", "time", "episode_step", "prev_action"):
        assert isinstance(sd[key], np.ndarray)
    assert isinstance(sd["rng"], dict) and isinstance(sd["targets"]["goal_pose"], np.ndarray)
    with pytest.raises(ValueError, match="cart_pole"):
        cart_env(2).load_state_dict(sd)


# --- collectors -------------------------------------------------------------------------------------


def test_collector_keeps_rewards_and_metrics():
    from torchrl.collectors import Collector

    env = push_env(4, seed=0, max_episode_steps=10)
    collector = Collector(env, policy=None, frames_per_batch=80, total_frames=160)
    for batch in collector:
        assert batch.shape == (4, 20)
        assert ("next", "rewards", "goal_distance_reward") in batch.keys(True)
        assert ("next", "metrics", "success") in batch.keys(True)
        assert batch["next", "truncated"].sum() == 8  # two 10-step episodes per env
        # after a truncation the next root observation is a fresh episode's, not the final one
        t = 9
        assert not torch.equal(batch["observation"][:, t + 1], batch["next", "observation"][:, t])
    collector.shutdown()


# --- configuration errors -------------------------------------------------------------------------


def test_unknown_reward_func_names_key_and_suggests():
    cfg = default_task_config("push_cube")
    cfg.rewards["goal_distance_reward"].func = "distance_to_targt"
    with pytest.raises(KeyError) as err:
        make_native_env(cfg, 1, seed=0)
    msg = str(err.value)
    assert "unknown reward func 'distance_to_targt' in rewards.goal_distance_reward" in msg
    assert "choose from [" in msg and "did you mean 'distance_to_target'?" in msg


@pytest.mark.parametrize(
    ("section", "key", "field", "value", "pattern"),
    [
        (
            "events",
            "randomize_goal",
            "func",
            "randomize_target",
            "unknown event func 'randomize_target' in events.randomize_goal",
        ),
        (
            "observations",
            "cube_pos",
            "func",
            "get_rigid_object",
            "unknown observation func 'get_rigid_object' in observations.cube_pos",
        ),
        (
            "actions",
            "delta_qpos",
            "func",
            "DeltaQpos",
            "unknown action term 'DeltaQpos' in actions.delta_qpos.*DeltaQposTerm",
        ),
        (
            "events",
            "randomize_goal",
            "mode",
            "rest",
            "unknown mode 'rest' in events.randomize_goal.mode.*'reset'",
        ),
    ],
)
def test_unknown_term_names(section, key, field, value, pattern):
    cfg = default_task_config("push_cube")
    setattr(getattr(cfg, section)[key], field, value)
    with pytest.raises((KeyError, ValueError), match=pattern):
        make_native_env(cfg, 1, seed=0)


def test_bad_params_and_unknown_task():
    cfg = default_task_config("push_cube")
    cfg.rewards["goal_distance_reward"].params["sigm"] = 0.1
    with pytest.raises(TypeError, match=r"rewards.goal_distance_reward.params.*'sigm'"):
        make_native_env(cfg, 1, seed=0)
    cfg = default_task_config("push_cube")
    cfg.task = "push_cub"
    with pytest.raises(KeyError, match="unknown native task 'push_cub'.*did you mean 'push_cube'"):
        make_native_env(cfg, 1, seed=0)
    cfg = default_task_config("push_cube")
    cfg.rewards["goal_distance_reward"].params["target_pose_key"] = "goal"
    with pytest.raises(
        KeyError, match="rewards.goal_distance_reward: target pose 'goal' is not stored"
    ):
        make_native_env(cfg, 1, seed=0)


def test_registries_hold_the_task_files_names():
    assert {"push_cube", "cart_pole"} <= set(TASKS)
    assert {
        "normalize_robot_joint_data",
        "get_robot_eef_pose",
        "get_rigid_object_pose",
        "target_position",
    } <= set(OBSERVATIONS)
    assert {
        "reaching_behind_object",
        "distance_to_target",
        "action_smoothness_penalty",
        "success_reward",
        "joint_velocity_penalty",
    } <= set(REWARDS)
    assert {"randomize_rigid_object_pose", "randomize_target_pose"} <= set(EVENTS)
