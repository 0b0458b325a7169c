"""Observation groups from every non-Gymnasium source (#47): rsl_rl 3.x TensorDict groups, rsl_rl
2.x ``extras["observations"]``, TorchRL EnvBase entries, the native tasks' term groups (push_cube's
privileged critic group against MuJoCo's own state), and the native camera term's image entry.

Each source: its parts (keys, groups, offsets) and the flat vector's values against values built
here by hand, the ``policy`` group first; the default selection (the actor reads ``policy``, the
critic every group); one-line refusals.
"""

from __future__ import annotations

import gymnasium as gym
import mujoco
import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from rlexp.config.native_task import NativeTaskConfig, ObservationTermConfig
from rlexp.config.schema import EnvConfig, PolicyConfig
from rlexp.envs.native import NativeEnv
from rlexp.envs.native.tasks import default_task_config
from rlexp.envs.torchrl_env import TorchRLAdapter
from rlexp.envs.vecenv import VecEnvAdapter
from rlexp.policies.actor_critic import policy_for_env

N = 2


def _parts(env) -> list[tuple[str, str, int, int]]:
    return [(p.key, p.group, p.offset, p.size) for p in env.obs_layout.parts]


def _default_reads(env) -> tuple[list[str], list[str]]:
    """The keys the default actor and critic read of ``env``."""
    policy = policy_for_env(PolicyConfig(), EnvConfig(normalize_observations=False), env)
    return (
        [p["key"] for p in policy.actor_input_parts],
        [p["key"] for p in policy.critic_input_parts],
    )


# --------------------------------------------------------------------------- rsl_rl VecEnvs


class GroupsVecEnv:
    """An rsl_rl VecEnv whose observations are known numbers: at step t, env i's ``policy`` group
    is [t, i, 10 + i], ``aux`` {"b": [100 + t], "a": [[200 + i, 201], [202, 203]]} (a group of terms),
    ``critic`` [-t, -i, 7.5, 0.25 * t] (``form``: ``v3`` a TensorDict of the groups, given out of
    order; ``v2`` rsl_rl 2.x: the policy tensor, ``critic`` in ``extras["observations"]``)."""

    num_envs, num_actions, device = N, 1, "cpu"

    def __init__(self, form: str = "v3", final_policy_only: bool = False) -> None:
        self.form, self.t, self.final_policy_only = form, 0, final_policy_only

    def groups(self, t: int) -> dict[str, torch.Tensor]:
        i = torch.arange(N, dtype=torch.float32)
        tt = torch.full((N,), float(t))
        out = {
            "critic": torch.stack([-tt, -i, torch.full((N,), 7.5), 0.25 * tt], -1),
            "policy": torch.stack([tt, i, 10 + i], -1),
        }
        if self.form == "v3":
            a = torch.tensor([[0.0, 201], [202, 203]]).expand(N, 2, 2).clone()
            a[:, 0, 0] = 200 + i
            out["aux"] = TensorDict({"b": (100 + tt)[:, None], "a": a}, batch_size=[N])
        return out

    def form_obs(self, t: int):
        g = self.groups(t)
        if self.form == "v3":
            return TensorDict(g, batch_size=[N])
        return g["policy"], {"observations": {"critic": g["critic"]}}

    def get_observations(self):
        return self.form_obs(self.t)

    def step(self, actions):
        self.t += 1
        dones = torch.tensor([self.t == 2, False])  # env 0 times out at t == 2, then t restarts
        extras = {"time_outs": dones.clone()}
        final = self.form_obs(self.t)
        if self.final_policy_only:  # rsl_rl 2.x hands over the policy's final observation only
            final = final[0]
        extras["final_observation"] = final
        obs = self.form_obs(self.t)
        if self.form == "v2":
            obs, more = obs
            extras.update(more)
        return obs, torch.zeros(N), dones, extras


def _v3_row(t: int, i: int) -> list[float]:
    return [t, i, 10 + i] + [200 + i, 201, 202, 203, 100 + t] + [-t, -i, 7.5, 0.25 * t]


def test_rsl_rl_3_groups_each_a_part_policy_first_others_by_name():
    env = VecEnvAdapter(GroupsVecEnv("v3"), "groups")
    assert _parts(env) == [
        ("policy", "policy", 0, 3),
        ("aux/a", "aux", 3, 4),  # a group of terms: a part per term, its name sorted
        ("aux/b", "aux", 7, 1),
        ("critic", "critic", 8, 4),
    ]
    assert env.obs_dim == 12 and env.obs_layout.parts[1].shape == (2, 2)
    want = torch.tensor([_v3_row(0, i) for i in range(N)])
    torch.testing.assert_close(env.reset()["observation"], want, rtol=0, atol=0)
    env.step_action(torch.zeros(N, 1))
    out = env.step_action(torch.zeros(N, 1))  # t = 2: env 0's time-out, its final observation
    want = torch.tensor([_v3_row(2, i) for i in range(N)])
    torch.testing.assert_close(out["observation"], want, rtol=0, atol=0)
    actor, critic = _default_reads(env)
    assert actor == ["policy"] and critic == ["policy", "aux/a", "aux/b", "critic"]


def test_rsl_rl_2_extras_critic_is_a_critic_part_after_the_policy_s():
    env = VecEnvAdapter(GroupsVecEnv("v2"), "v2")
    assert _parts(env) == [("", "policy", 0, 3), ("critic", "critic", 3, 4)]
    row = lambda t, i: [t, i, 10 + i, -t, -i, 7.5, 0.25 * t]  # noqa: E731
    torch.testing.assert_close(
        env.reset()["observation"], torch.tensor([row(0, i) for i in range(N)]), rtol=0, atol=0
    )
    out = env.step_action(torch.zeros(N, 1))
    torch.testing.assert_close(
        out["observation"], torch.tensor([row(1, i) for i in range(N)]), rtol=0, atol=0
    )
    actor, critic = _default_reads(env)
    assert actor == [""] and critic == ["", "critic"]


def test_a_final_observation_without_the_critic_group_keeps_the_stand_in_s_columns():
    """rsl_rl 2.x's final observation is the policy's tensor: the time-out's "next" takes the
    policy columns from it and the critic columns from the observation acted on (the stand-in)."""
    env = VecEnvAdapter(GroupsVecEnv("v2", final_policy_only=True), "v2")
    env.reset()
    env.step_action(torch.zeros(N, 1))  # t = 1: acted on next
    nxt = env.step_action(torch.zeros(N, 1))["observation"]  # t = 2, env 0 done
    assert nxt[0].tolist() == [2, 0, 10, -1, -0, 7.5, 0.25]  # policy of t=2, critic of t=1
    assert nxt[1].tolist() == [2, 1, 11, -2, -1, 7.5, 0.5]


def test_a_vecenv_group_that_disappears_is_one_line():
    raw = GroupsVecEnv("v3")
    env = VecEnvAdapter(raw, "groups")
    env.reset()
    raw.form = "v2"  # now the groups are (policy, extras critic): "aux" is gone
    with pytest.raises(ValueError) as err:
        env.step_action(torch.zeros(N, 1))
    msg = str(err.value)
    assert "\n" not in msg and "'aux/a'" in msg and "groups" in msg


def test_a_vecenv_image_group_is_one_line():
    class Pixels(GroupsVecEnv):
        def form_obs(self, t):
            g = {**self.groups(t), "camera": torch.zeros(N, 3, 8, 6, dtype=torch.uint8)}
            return TensorDict(g, batch_size=[N])

    with pytest.raises(TypeError) as err:
        VecEnvAdapter(Pixels("v3"), "px")
    msg = str(err.value)
    assert "\n" not in msg and "'camera' group is a uint8 image [2, 3, 8, 6]" in msg


# --------------------------------------------------------------------------- TorchRL EnvBase


class EntriesEnv(EnvBase):
    """A TorchRL env whose observation entries are known numbers (``declared``: Isaac Lab's
    ``policy`` / ``critic`` / ``height`` top-level groups; else plain entries, one named
    ``critic``): entry values [k + 10 * i + 0.5 * t] for the entry's k-th value."""

    def __init__(self, declared: bool) -> None:
        super().__init__(batch_size=torch.Size([N]))
        self.t, self.declared = 0, declared

        def box(*shape: int) -> Unbounded:
            return Unbounded(shape=(N, *shape), dtype=torch.float32)

        if declared:
            obs = {
                "policy": box(3),
                "critic": Composite(vel=box(2), contact=box(1), shape=(N,)),
                "height": box(2),
            }
        else:
            obs = {
                "pos": box(2),
                "arm": Composite(q=box(2), dq=box(1), shape=(N,)),
                "critic": box(1),
                "goal": box(1),
            }
        self.observation_spec = Composite(**obs, shape=(N,))
        self.action_spec = Unbounded(shape=(N, 1))
        self.reward_spec = Unbounded(shape=(N, 1))
        self.done_spec = Composite(done=Categorical(2, (N, 1), dtype=torch.bool), shape=(N,))

    def _values(self) -> TensorDict:
        out = TensorDict({}, batch_size=[N])
        for key in self.observation_spec.keys(True, True):
            k = self.observation_spec[key].shape[-1]
            i = torch.arange(N, dtype=torch.float32)[:, None]
            out.set(key, torch.arange(k, dtype=torch.float32) + 10 * i + 0.5 * self.t)
        out.set("done", torch.zeros(N, 1, dtype=torch.bool))
        return out

    def _reset(self, td=None):
        self.t = 0
        return self._values()

    def _step(self, td):
        self.t += 1
        out = self._values()
        out.set("reward", torch.zeros(N, 1))
        return out

    def _set_seed(self, seed):
        return seed


def _entry(k: int, i: int, t: int) -> list[float]:
    return [j + 10 * i + 0.5 * t for j in range(k)]


def test_torchrl_entries_are_parts_a_critic_entry_its_own_group_nested_keys_addressable():
    env = TorchRLAdapter(EntriesEnv(declared=False), "entries")
    assert _parts(env) == [
        ("arm/dq", "policy", 0, 1),
        ("arm/q", "policy", 1, 2),
        ("goal", "policy", 3, 1),
        ("pos", "policy", 4, 2),
        ("critic", "critic", 6, 1),  # named like a group: its own, after the policy's
    ]
    env.reset()
    out = env.step_action(torch.zeros(N, 1))
    want = torch.tensor(
        [_entry(1, i, 1) + _entry(2, i, 1) + _entry(1, i, 1) + _entry(2, i, 1) + _entry(1, i, 1)
         for i in range(N)]
    )  # fmt: skip
    torch.testing.assert_close(out["observation"], want, rtol=0, atol=0)
    cfg = PolicyConfig()
    cfg.actor.observations = ["arm/q", "goal"]  # a nested key as "a/b"
    cfg.critic.observations = ["arm"]  # every entry under "arm"
    policy = policy_for_env(cfg, EnvConfig(normalize_observations=False), env)
    assert [p["key"] for p in policy.actor_input_parts] == ["arm/q", "goal"]
    assert [p["key"] for p in policy.critic_input_parts] == ["arm/dq", "arm/q"]


def test_torchrl_env_with_a_policy_entry_makes_every_top_level_entry_a_group():
    env = TorchRLAdapter(EntriesEnv(declared=True), "isaac-like")
    assert _parts(env) == [
        ("policy", "policy", 0, 3),
        ("critic/contact", "critic", 3, 1),
        ("critic/vel", "critic", 4, 2),
        ("height", "height", 6, 2),
    ]
    want = torch.tensor(
        [_entry(3, i, 0) + _entry(1, i, 0) + _entry(2, i, 0) + _entry(2, i, 0) for i in range(N)]
    )
    torch.testing.assert_close(env.reset()["observation"], want, rtol=0, atol=0)
    actor, critic = _default_reads(env)
    assert actor == ["policy"] and critic == ["policy", "critic/contact", "critic/vel", "height"]


# --------------------------------------------------------------------------- Gymnasium Dicts


class GroupedDict(gym.Env):
    """A Gymnasium env whose Dict names its groups by top-level key, as Isaac Lab's ``policy`` /
    ``critic`` dicts do (``declared``), or with a ``critic`` key beside plain keys."""

    def __init__(self, declared: bool = True) -> None:
        box = lambda n: gym.spaces.Box(-np.inf, np.inf, (n,), np.float32)  # noqa: E731
        top = {"policy": gym.spaces.Dict({"q": box(3), "cam": gym.spaces.Box(0, 255, (36, 36, 3),
               np.uint8)}), "critic": box(2), "teacher": box(1)}  # fmt: skip
        if not declared:
            top = {"joints": box(3), "critic": box(2), "goal": box(1)}
        self.observation_space = gym.spaces.Dict(top)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return self.observation_space.sample(), {}

    def step(self, action):
        return self.observation_space.sample(), 0.0, False, False, {}


@pytest.mark.parametrize("declared", [True, False])
def test_a_gymnasium_dict_s_top_level_keys_are_groups_as_isaac_lab_names_them(declared):
    """With a top-level ``policy`` key every top-level key is a group (``teacher`` too); without
    one a ``critic`` key is still its own group and the rest is the policy's. The default actor
    then reads the policy group only, the critic everything; the vector keeps the Dict's sorted
    key order. Catches: the privileged ``critic`` entries read by the deployed actor."""
    from rlexp.envs.gym import GymnasiumEnv

    name = f"GroupedDict{int(declared)}-v0"
    gym.register(name, entry_point=GroupedDict, kwargs={"declared": declared})
    env = GymnasiumEnv(name, num_envs=2)
    try:
        if declared:
            assert _parts(env) == [
                ("critic", "critic", 0, 2),
                ("policy/cam", "policy", -1, 0),
                ("policy/q", "policy", 2, 3),
                ("teacher", "teacher", 5, 1),
            ]
            assert _default_reads(env) == (
                ["policy/cam", "policy/q"],
                ["critic", "policy/cam", "policy/q", "teacher"],
            )
        else:
            assert _parts(env) == [
                ("critic", "critic", 0, 2),
                ("goal", "policy", 2, 1),
                ("joints", "policy", 3, 3),
            ]
            assert _default_reads(env) == (["goal", "joints"], ["critic", "goal", "joints"])
    finally:
        env.close()
        gym.registry.pop(name, None)


# --------------------------------------------------------------------------- native tasks


def _cube_dof(model: mujoco.MjModel) -> tuple[int, int]:
    """The cube's free joint: (qpos address, dof address), read from MuJoCo's model."""
    joint = model.body("cube").jntadr[0]
    return int(model.jnt_qposadr[joint]), int(model.jnt_dofadr[joint])


def test_push_cube_critic_group_is_the_cube_s_velocity_and_offset_to_the_goal():
    env = NativeEnv(default_task_config("push_cube"), 3)
    env.set_seed(4)
    env.reset()
    qa, da = _cube_dof(env.model)
    # give the cubes a shove (world-frame linear velocities) and let physics move them
    env.qvel[:, da : da + 3] = [[0.3, -0.2, 0.0], [-0.4, 0.1, 0.5], [0.0, 0.0, 0.0]]
    env._v.version += 1
    out = env.step_action(torch.zeros(3, 6))
    obs = out["observation"].double().numpy()
    parts = {p.key: p for p in env.obs_layout.parts}
    assert [p.key for p in env.obs_layout.parts if p.group == "critic"] == [
        "privileged/cube_to_goal",
        "privileged/cube_vel",
    ]
    assert max(p.offset + p.size for p in env.obs_layout.parts if p.group == "policy") == 53
    data = mujoco.MjData(env.model)
    for i in range(3):
        mujoco.mj_setState(env.model, data, env._state[i], mujoco.mjtState.mjSTATE_FULLPHYSICS)
        vel, pos = data.qvel[da : da + 3], data.qpos[qa : qa + 3]
        goal = env._targets["goal_pose"][i]
        v, g = parts["privileged/cube_vel"], parts["privileged/cube_to_goal"]
        np.testing.assert_allclose(obs[i, v.offset : v.offset + 3], vel, rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(obs[i, g.offset : g.offset + 3], goal - pos, atol=1e-6)
    assert abs(obs[0, parts["privileged/cube_vel"].offset]) > 0.05  # it did move
    actor, critic = _default_reads(env)
    assert "privileged/cube_vel" not in actor and len(actor) == 6
    assert critic[-2:] == ["privileged/cube_to_goal", "privileged/cube_vel"]


def test_a_native_task_without_groups_keeps_its_layout():
    env = NativeEnv(default_task_config("cart_pole"), 2)
    assert _parts(env) == [
        ("robot/qf", "policy", 0, 2),
        ("robot/qpos", "policy", 2, 2),
        ("robot/qvel", "policy", 4, 2),
    ]
    assert env.obs_layout.record() == {
        "space": "native",
        "dim": 6,
        "order": env.obs_layout.record()["order"],
        "parts": [{"key": k, "kind": "box", "shape": [2], "offset": o, "size": 2}
                  for k, o in (("robot/qf", 0), ("robot/qpos", 2), ("robot/qvel", 4))],
    }  # fmt: skip


def _with_terms(task: str, **terms: ObservationTermConfig) -> NativeTaskConfig:
    cfg = default_task_config(task)
    cfg.observations = {**cfg.observations, **terms}
    return cfg


@pytest.mark.parametrize(
    "term, words",
    [
        (
            ObservationTermConfig("get_robot_joint_velocity", name="x/v", group="critic/x"),
            ["observations.bad.group='critic/x'", "observation group name"],
        ),
        (
            ObservationTermConfig("get_robot_joint_velocity", name="x/v", group=""),
            ["observations.bad.group=''"],
        ),
        (
            ObservationTermConfig(
                "normalize_robot_joint_data", "modify", "robot/qpos", group="critic"
            ),  # fmt: skip
            ["observations.bad.group='critic'", "'robot/qpos'", "group 'policy'"],
        ),
        (  # a group named like another group's entries: selecting "robot" would mean both
            ObservationTermConfig("get_robot_joint_velocity", name="x/v", group="robot"),
            ["observations.bad.group='robot'", "'robot/q", "group 'policy'"],
        ),
        (  # an entry under the name of another group
            {
                "bad": ObservationTermConfig("get_robot_joint_velocity", name="critic/v"),
                "crit": ObservationTermConfig(
                    "get_robot_joint_velocity", "add", "w", group="critic"
                ),
            },
            ["observations.crit.group='critic'", "'critic/v' (group 'policy')"],
        ),
        (
            ObservationTermConfig("camera_image", name="cam/rgb", params={"width": 4}),
            ["observations.bad.params.width=4", "integer >= 8"],
        ),
        (
            ObservationTermConfig("camera_image", name="cam/rgb", params={"camera": "nope"}),
            ["observations.bad: params.camera='nope'", "its cameras: []"],
        ),
        (
            ObservationTermConfig("camera_image", name="c/r", params={"camera": "x", "fovy": 40}),
            ["params.camera='x'", "leave out eye, target and fovy"],
        ),
        (
            ObservationTermConfig("camera_image", name="cam/rgb", params={"height": 64.5}),
            ["observations.bad.params.height=64.5"],
        ),
    ],
)
def test_bad_groups_and_camera_sizes_are_one_line(term, words):
    with pytest.raises((ValueError, TypeError)) as err:
        terms = term if isinstance(term, dict) else {"bad": term}
        NativeEnv(_with_terms("cart_pole", **terms), 1)
    msg = str(err.value)
    assert "\n" not in msg and all(w in msg for w in words), msg


# --------------------------------------------------------------------------- the camera term


def _camera_env(n: int) -> NativeEnv:
    cam = ObservationTermConfig(
        "camera_image",
        name="camera/top",
        params={"width": 24, "height": 16, "eye": [-0.6, -0.4, 1.2], "target": [-0.6, -0.39, 0.0]},
    )
    return NativeEnv(_with_terms("push_cube", camera=cam), n)


def _render_or_skip(make):
    try:
        return make()
    except RuntimeError as exc:
        if "offscreen rendering failed" in str(exc):
            pytest.skip(f"no OpenGL backend: {exc}")
        raise


def test_the_camera_term_is_a_uint8_chw_image_entry_that_sees_the_cube_move():
    env = _render_or_skip(lambda: _camera_env(2))
    image = [p for p in env.obs_layout.parts if p.kind == "image"]
    assert [(p.key, p.image_key, p.shape, p.group) for p in image] == [
        ("camera/top", "camera.top", (3, 16, 24), "policy")
    ]
    assert env.obs_layout.dim == env.obs_dim == 59  # the image is not in the vector
    spec = env.observation_spec["observation"]
    assert spec["camera.top"].dtype == torch.uint8 and spec["camera.top"].shape == (2, 3, 16, 24)
    obs = env.reset()["observation"]
    img, vec = obs["camera.top"], obs["vector"]
    assert img.dtype == torch.uint8 and img.shape == (2, 3, 16, 24) and vec.shape == (2, 59)
    assert int(img.max()) > int(img.min())  # not a blank frame
    # the same frame MuJoCo's renderer gives for env 1, HWC -> CHW
    frame = env.render(1, 24, 16, eye=(-0.6, -0.4, 1.2), target=(-0.6, -0.39, 0.0), effects=False)
    assert torch.equal(img[1], torch.from_numpy(frame).permute(2, 0, 1))
    # move env 0's cube out of the picture: env 0's image changes, env 1's does not
    pos, quat = env.object_pose("cube")
    env.set_object_pose("cube", np.array([0]), pos[0:1] + [0.0, 0.5, 0.0], quat[0:1].copy())
    out = env.step_action(torch.zeros(2, 6))["observation"]["camera.top"]
    assert (out[0] != img[0]).sum() > 20
    torch.testing.assert_close(out[1].float(), img[1].float(), atol=40, rtol=0)
    # resume: the images come back with the state
    sd = env.state_dict()
    again = _camera_env(2)
    again.load_env_state(sd)
    assert torch.equal(again.reset()["observation"]["camera.top"], env._current()["camera.top"])


def test_a_named_model_camera_rides_on_the_arm():
    """camera: wrist (push_cube.xml's camera on the wrist link): the frames are MuJoCo's own from
    that camera (mujoco.Renderer here, the env's state and goal marker), and they change when only
    the arm moves."""
    cam = ObservationTermConfig(
        "camera_image", name="camera/wrist", params={"width": 20, "height": 12, "camera": "wrist"}
    )
    env = _render_or_skip(lambda: NativeEnv(_with_terms("push_cube", camera=cam), 2))
    env.set_seed(3)
    img = env.reset()["observation"]["camera.wrist"]
    assert img.dtype == torch.uint8 and img.shape == (2, 3, 12, 20)
    data, model = mujoco.MjData(env.model), env.model
    mujoco.mj_setState(model, data, env._state[1], mujoco.mjtState.mjSTATE_FULLPHYSICS)
    data.mocap_pos[model.body("goal").mocapid[0]] = env._targets["goal_pose"][1]
    mujoco.mj_forward(model, data)
    with mujoco.Renderer(model, height=12, width=20) as renderer:
        renderer.update_scene(data, camera="wrist")
        for flag in ("mjRND_SHADOW", "mjRND_REFLECTION", "mjRND_SKYBOX"):
            renderer.scene.flags[getattr(mujoco.mjtRndFlag, flag)] = False
        want = renderer.render()
    assert torch.equal(img[1], torch.from_numpy(want).permute(2, 0, 1))
    env.qpos[0, 0] += 0.6  # env 0's shoulder turns; the cube and the goal stay
    env._v.version += 1
    out = env.step_action(torch.zeros(2, 6))["observation"]["camera.wrist"]
    assert (out[0] != img[0]).sum() > 20


def test_the_pixels_preset_composes_and_refuses_overlap_in_one_line():
    """+experiment=push_cube_pixels: the camera term, the actor on joints + image, a state critic;
    algorithm.overlap=true (a forked collector cannot render) is one line at the config check."""
    from conftest import compose
    from rlexp.config.validate import ConfigError, to_root_config

    cfg = to_root_config(compose(["+experiment=push_cube_pixels"]))
    assert cfg.env.native.observations["camera"].func == "camera_image"
    assert cfg.policy.actor.observations == ["robot", "camera"]
    with pytest.raises(ConfigError) as err:
        to_root_config(compose(["+experiment=push_cube_pixels", "algorithm.overlap=true"]))
    msg = str(err.value)
    assert "\n" not in msg and "env.native.observations.camera" in msg and "overlap=false" in msg


def test_the_pixels_preset_trains_the_actor_on_joints_and_image_the_critic_on_state(tmp_path):
    """+experiment=push_cube_pixels trains end to end (tiny budget, through the CLI): the checkpoint
    records the image and the critic group; the actor's MLP reads the 34 robot values + the CNN's
    128 features, the critic's the 59 state values (policy group + critic group), no image."""
    from conftest import only_run_dir, run_train

    _render_or_skip(lambda: _camera_env(1))
    run_train(
        ["+experiment=push_cube_pixels", "env.num_envs=2", "env.num_eval_envs=1",
         "env.max_episode_steps=20", "trainer.total_frames=128", "trainer.frames_per_batch=64",
         "trainer.eval_every=128", "trainer.eval_episodes=1", "trainer.save_every=128",
         "algorithm.mini_batch_size=32", "algorithm.num_epochs=1"],
        cwd=tmp_path,
    )  # fmt: skip
    ckpt = only_run_dir(tmp_path) / "checkpoints" / "best.pt"
    saved = torch.load(ckpt, map_location="cpu", weights_only=False)
    parts = {p["key"]: p for p in saved["observation_layout"]["parts"]}
    assert parts["camera/top"]["kind"] == "image" and parts["camera/top"]["shape"] == [3, 64, 64]
    assert parts["privileged/cube_vel"]["group"] == "critic" and "group" not in parts["robot/qf"]
    assert saved["observation_layout"]["dim"] == 59
    weights = saved["policy"]
    assert weights["actor_net.mlp.0.weight"].shape[1] == 6 + 6 + 6 + 16 + 128
    assert weights["critic_net.mlp.0.weight"].shape[1] == 59
    image = saved["pending_observation"]["camera.top"]
    assert image.dtype == torch.uint8 and tuple(image.shape) == (2, 3, 64, 64)


def test_a_term_s_group_is_written_to_json_in_the_rlexp_section(tmp_path, monkeypatch):
    """The users' task format has no group: train_config.json's rlexp section carries it (the
    task file's terms are written without it), and the pair loads back to the same config."""
    import json

    from conftest import compose
    from rlexp.config.json_format import (
        load_json_experiment,
        to_json_experiment,
        write_json_experiment,
    )
    from rlexp.config.validate import to_root_config
    from rlexp.launch.json_entry import compose_json_experiment

    monkeypatch.chdir(tmp_path)
    config = to_root_config(
        compose(["env=push_cube", "env.native.observations.robot_ee_pos.group=privileged"])
    )
    train, gym = to_json_experiment(config)
    assert all("group" not in t for t in gym["env"]["observations"].values())
    assert '"privileged"' in json.dumps(train["rlexp"])
    write_json_experiment(config, tmp_path)
    again = compose_json_experiment(load_json_experiment(tmp_path / "train_config.json"))
    terms = again.env.native.observations
    assert terms["robot_ee_pos"].group == "privileged" and terms["cube_vel"].group == "critic"
    assert terms["robot_qpos"].group == "policy"
    assert again == config
