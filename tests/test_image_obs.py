"""Image observations on the env side (#47, DESIGN47 §1): detection of HWC / CHW / stacked frames and
``env.image_keys``, the layout's records, the TensorDict observation every Gymnasium backend emits
(in-process, worker processes, EnvPool) and a TorchRL env passes through, ``env.frame_stack``
against a stack built by hand across a reset, uint8 kept end to end, and the one-line refusals.

Expected values are built with numpy from the test env's own frames (``gym_image_envs.frame``), never
from rlexp's encoders."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
import torch
from gym_image_envs import frame
from gymnasium import spaces
from tensordict import TensorDict
from torchrl.data import Bounded, Composite, Unbounded

from conftest import REPO, run_train
from rlexp.envs.spaces import UnsupportedSpace, obs_layout

TESTS = Path(__file__).resolve().parent
PYPATH = {"PYTHONPATH": f"{REPO / 'src'}{os.pathsep}{TESTS}"}
HWC = (6, 5, 3)  # ImageEnv's default frame: H=6, W=5, C=3


def chw(f: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(f.transpose(2, 0, 1))


def stacked(frames: list[np.ndarray]) -> np.ndarray:
    """Frames (HWC) as the policy must see them stacked: each CHW, concatenated, oldest first."""
    return np.concatenate([chw(f) for f in frames])


# -- detection ------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("shape", "want_chw", "source", "by_hand"),
    [
        ((6, 5, 3), (3, 6, 5), "hwc", lambda x: x.transpose(2, 0, 1)),
        ((7, 9, 1), (1, 7, 9), "hwc", lambda x: x.transpose(2, 0, 1)),
        ((3, 6, 5), (3, 6, 5), "chw", lambda x: x),
        ((4, 84, 84), (4, 84, 84), "chw", lambda x: x),  # EnvPool's Atari frames
        ((3, 7, 3), (3, 7, 3), "chw", lambda x: x),  # first dim a channel count too: CHW
        (
            (2, 6, 5, 3),
            (6, 6, 5),
            "stack_hwc",
            lambda x: np.concatenate([x[0].transpose(2, 0, 1), x[1].transpose(2, 0, 1)]),
        ),
        ((3, 2, 6, 5), (6, 6, 5), "stack_chw", lambda x: np.concatenate([x[0], x[1], x[2]])),
    ],
)
def test_a_uint8_box_is_an_image_in_its_layout_given_as_chw(shape, want_chw, source, by_hand):
    layout = obs_layout(spaces.Box(0, 255, shape, np.uint8), "env.name='x'")
    (part,) = layout.parts
    assert (part.kind, part.shape, part.source_layout, part.image_key) == (
        "image",
        want_chw,
        source,
        "pixels",
    )
    assert (part.offset, part.size, layout.dim, layout.structured, layout.plain) == (
        -1,
        0,
        0,
        True,
        False,
    )
    x = ((np.arange(int(np.prod(shape))) * 7) % 256).astype(np.uint8).reshape(shape)
    out = layout.encode(x)
    assert set(out) == {"pixels"} and out["pixels"].dtype == np.uint8
    np.testing.assert_array_equal(out["pixels"], by_hand(x))


def test_a_dict_of_images_and_vectors_keeps_the_vector_flat_and_names_nested_images():
    space = spaces.Dict(
        {
            "pos": spaces.Box(-1, 1, (2,), np.float32),
            "cam": spaces.Dict({"front": spaces.Box(0, 255, (6, 5, 3), np.uint8)}),
            "gear": spaces.Discrete(3),
            "wrist": spaces.Box(0, 255, (1, 4, 4), np.uint8),
        }
    )
    layout = obs_layout(space, "w")
    assert layout.dim == 5 and layout.structured  # pos (2) + gear one-hot (3); images not in it
    assert [p.image_key for p in layout.images] == ["cam.front", "wrist"]
    assert layout.record()["parts"] == [
        {
            "key": "cam/front",
            "kind": "image",
            "shape": [3, 6, 5],
            "offset": -1,
            "size": 0,
            "image_key": "cam.front",
            "source_layout": "hwc",
        },
        {"key": "gear", "kind": "discrete", "shape": [], "offset": 0, "size": 3, "nvec": [3],
         "start": [0]},
        {"key": "pos", "kind": "box", "shape": [2], "offset": 3, "size": 2},
        {"key": "wrist", "kind": "image", "shape": [1, 4, 4], "offset": -1, "size": 0,
         "image_key": "wrist", "source_layout": "chw"},
    ]  # fmt: skip
    front = frame((6, 5, 3), 2, 1)
    wrist = frame((1, 4, 4), 5, 0)
    obs = {"pos": np.array([0.5, -0.25]), "cam": {"front": front}, "gear": 2, "wrist": wrist}
    out = layout.encode(obs)
    np.testing.assert_array_equal(out["vector"], np.array([0, 0, 1, 0.5, -0.25], np.float32))
    np.testing.assert_array_equal(out["cam.front"], chw(front))
    np.testing.assert_array_equal(out["wrist"], wrist)
    assert out["vector"].dtype == np.float32 and out["cam.front"].dtype == np.uint8
    np.testing.assert_array_equal(layout.flatten(obs), out["vector"])  # the vector alone


def test_images_inside_a_tuple_are_named_by_index_path():
    space = spaces.Tuple(
        (
            spaces.Box(0, 255, (5, 4, 4), np.uint8),  # RGBA HWC
            spaces.Dict({"cam": spaces.Box(0, 255, (2, 1, 5, 4), np.uint8)}),  # 2 grey CHW frames
            spaces.Box(-1, 1, (3,), np.float32),
        )
    )
    layout = obs_layout(space, "w")
    assert [(p.image_key, p.shape, p.source_layout) for p in layout.images] == [
        ("0", (4, 5, 4), "hwc"),
        ("1.cam", (2, 5, 4), "stack_chw"),
    ]
    assert layout.dim == 3 and [p.key for p in layout.parts] == ["0", "1/cam", "2"]
    a, b = frame((5, 4, 4), 1, 0), frame((2, 1, 5, 4), 2, 0)
    out = layout.encode((a, {"cam": b}, np.array([1, 2, 3], np.float32)))
    np.testing.assert_array_equal(out["0"], a.transpose(2, 0, 1))
    np.testing.assert_array_equal(out["1.cam"], b[:, 0])
    np.testing.assert_array_equal(out["vector"], [1, 2, 3])


def test_image_keys_names_a_grey_image_by_key_path_or_tensordict_key():
    space = spaces.Dict(
        {
            "depth": spaces.Dict({"near": spaces.Box(0, 255, (4, 7), np.uint8)}),
            "pos": spaces.Box(-1, 1, (2,), np.float32),
        }
    )
    assert not obs_layout(space, "w").structured  # [H, W] uint8 alone: a vector part
    for name in ("depth/near", "depth.near"):
        layout = obs_layout(space, "w", image_keys=[name])
        (part,) = layout.images
        assert (part.shape, part.source_layout, part.image_key) == ((1, 4, 7), "hw", "depth.near")
        assert layout.dim == 2
        grey = frame((4, 7), 3, 0)
        out = layout.encode({"depth": {"near": grey}, "pos": np.zeros(2)})
        np.testing.assert_array_equal(out["depth.near"], grey[None])


@pytest.mark.parametrize(
    ("space", "keys", "words"),
    [
        (
            spaces.Dict({"cam": spaces.Box(0, 255, (2, 2, 6, 5, 3), np.uint8)}),
            (),
            ["key 'cam'", "unsupported layout", "(2, 2, 6, 5, 3)", "rank 5"],
        ),
        (
            spaces.Dict({"cam": spaces.Box(0, 1, (6, 5, 3), np.float32)}),
            ("cam",),
            ["env.image_keys", "key 'cam'", "float32", "must be uint8"],
        ),
        (
            spaces.Dict({"cam": spaces.Box(0, 255, (6, 5, 3), np.uint8)}),
            ("camera",),
            ["env.image_keys", "['camera']", "does not have", "'cam'"],
        ),
        (
            spaces.Dict({"vector": spaces.Box(0, 255, (6, 5, 3), np.uint8)}),
            (),
            ["key 'vector'", "flat vector", "rename"],
        ),
    ],
)
def test_images_rlexp_cannot_read_are_one_line_naming_the_key_and_shape(space, keys, words):
    with pytest.raises(UnsupportedSpace) as err:
        obs_layout(space, "env.name='my:Cam-v0'", image_keys=keys)
    msg = str(err.value)
    assert "\n" not in msg and msg.startswith("env.name='my:Cam-v0': ")
    for word in words:
        assert word in msg, msg


def test_the_layout_records_the_frame_stack_and_a_group_only_when_not_policy():
    layout = obs_layout(spaces.Box(0, 255, (3, 6, 5, 3), np.uint8), "w", frame_stack=3)
    record = layout.record()
    assert record["frame_stack"] == 3 and "group" not in record["parts"][0]
    assert "frame_stack" not in obs_layout(spaces.Box(0, 255, (6, 5, 3), np.uint8), "w").record()


# -- the backends ---------------------------------------------------------------------------------
def _step(env, n: int):
    nxt = env.step_action(torch.zeros(n, 1, dtype=torch.int64))
    return nxt, env.autoreset_observation(nxt)


def test_in_process_env_emits_a_tensordict_of_the_vector_and_uint8_chw_images():
    import gym_image_envs  # noqa: F401  (registers the ids)

    from rlexp.envs.gym import GymnasiumEnv

    env = GymnasiumEnv("ImageDict-v0", 2, image_keys=["depth"])
    try:
        spec = env.observation_spec["observation"]
        assert isinstance(spec, Composite) and set(spec.keys()) == {"vector", "cam.front", "depth"}
        assert isinstance(spec["vector"], Unbounded) and spec["vector"].shape == (2, 2)
        assert spec["vector"].dtype == torch.float32
        for key, shape in (("cam.front", (2, 3, 6, 5)), ("depth", (2, 1, 4, 7))):
            assert isinstance(spec[key], Bounded) and spec[key].dtype == torch.uint8
            assert spec[key].shape == shape
            assert spec[key].space.low.min() == 0 and spec[key].space.high.max() == 255
        env.set_seed(0)
        obs = env.reset()["observation"]
        assert isinstance(obs, TensorDict) and obs.batch_size == (2,)
        np.testing.assert_array_equal(obs["cam.front"][1].numpy(), chw(frame(HWC, 0, 0)))
        np.testing.assert_array_equal(obs["depth"][0, 0].numpy(), frame((4, 7), 0, 0))
        for t in (1, 2, 3):  # the episode ends at t=3: "next" holds its last frame
            nxt, after = _step(env, 2)
            o = nxt["observation"]
            assert o["cam.front"].dtype == torch.uint8 and o["depth"].dtype == torch.uint8
            assert o["vector"].dtype == torch.float32
            np.testing.assert_array_equal(o["cam.front"][0].numpy(), chw(frame(HWC, t, 0)))
            np.testing.assert_array_equal(o["vector"][1].numpy(), [t, -t])
        assert nxt["terminated"].all()
        np.testing.assert_array_equal(after["cam.front"][0].numpy(), chw(frame(HWC, 0, 1)))
        np.testing.assert_array_equal(after["vector"].numpy(), np.zeros((2, 2)))
        assert after["cam.front"].dtype == torch.uint8
        state = env.env_state()  # a checkpoint keeps the images uint8, no float copy
        assert state["obs"]["cam.front"].dtype == np.uint8
        assert state["reset_obs"]["depth"].dtype == np.uint8
    finally:
        env.close()


def test_a_plain_box_env_still_emits_one_flat_float32_tensor():
    import gym_image_envs  # noqa: F401

    from rlexp.envs.gym import GymnasiumEnv

    env = GymnasiumEnv("Vector-v0", 2)
    try:
        assert not env.obs_layout.structured
        obs = env.reset()["observation"]
        assert isinstance(obs, torch.Tensor) and obs.shape == (2, 3) and obs.dtype == torch.float32
        assert isinstance(env.observation_spec["observation"], Unbounded)
    finally:
        env.close()


@pytest.mark.parametrize("backend", ["gymnasium", "gymnasium_async"])
def test_frame_stack_against_a_stack_built_by_hand_across_a_reset(backend):
    """env.frame_stack=3 on HWC frames, 3-step episodes: newest last, a reset fills the stack with
    its first frame, the finished copy's "next" keeps its last 3 frames."""
    import gym_image_envs  # noqa: F401

    env = _make(backend, "gym_image_envs:Image-v0", 2, frame_stack=3)
    try:
        assert env.observation_spec["observation", "pixels"].shape == (2, 9, 6, 5)
        assert env.obs_layout.record()["frame_stack"] == 3
        env.set_seed(3)
        f = [frame(HWC, t, 0) for t in range(4)]
        g = [frame(HWC, t, 1) for t in range(2)]
        obs = env.reset()["observation"]["pixels"]
        np.testing.assert_array_equal(obs[0].numpy(), stacked([f[0], f[0], f[0]]))
        want_next = [
            stacked([f[0], f[0], f[1]]),
            stacked([f[0], f[1], f[2]]),
            stacked([f[1], f[2], f[3]]),  # the final observation
            stacked([g[0], g[0], g[1]]),
        ]
        want_after = [*want_next[:2], stacked([g[0], g[0], g[0]]), want_next[3]]
        for i in range(4):
            nxt, after = _step(env, 2)
            assert nxt["observation", "pixels"].dtype == torch.uint8
            for copy in (0, 1):
                np.testing.assert_array_equal(
                    nxt["observation", "pixels"][copy].numpy(), want_next[i]
                )
                np.testing.assert_array_equal(after["pixels"][copy].numpy(), want_after[i])
        assert env.state_kind == "restart"  # the wrapper's frames are not in any env state
    finally:
        env.close()


@pytest.mark.parametrize("backend", ["gymnasium", "gymnasium_async"])
def test_an_image_env_s_state_resumes_exactly_with_its_uint8_observations(backend):
    """env_state() mid-episode (a copy pending its reset included) into a fresh env: the next full
    reset hands back the same uint8 images and vector, and the steps after are the same."""
    import gym_image_envs  # noqa: F401

    a = _make(backend, "gym_image_envs:ImageState-v0", 2)
    b = _make(backend, "gym_image_envs:ImageState-v0", 2)
    try:
        a.set_seed(0)
        a.reset()
        for _ in range(4):  # t=4 ends the episode: the reset observation is pending
            nxt = a.step_action(torch.zeros(2, 1, dtype=torch.int64))
        state = a.env_state()
        assert state["kind"] == "state" and state["obs"]["cam.front"].dtype == np.uint8
        b.set_seed(0)
        b.load_env_state(state)
        now = b.reset()["observation"]
        want = a.autoreset_observation(nxt)
        assert now["cam.front"].dtype == torch.uint8 and (now == want).all()
        np.testing.assert_array_equal(now["cam.front"][1].numpy(), chw(frame(HWC, 0, 1)))
        for _ in range(3):
            na, nb = _step(a, 2), _step(b, 2)
            assert (na[0]["observation"] == nb[0]["observation"]).all()
            assert (na[1] == nb[1]).all()
    finally:
        a.close()
        b.close()


def _make(backend: str, name: str, n: int, **kw):
    if backend == "gymnasium":
        from rlexp.envs.gym import GymnasiumEnv

        return GymnasiumEnv(name, n, **kw)
    from rlexp.envs.gym_async import AsyncGymnasiumEnv

    return AsyncGymnasiumEnv(name, n, **kw)


def test_worker_processes_emit_the_same_tensordict_as_in_process():
    import gym_image_envs  # noqa: F401

    from rlexp.envs.gym import GymnasiumEnv
    from rlexp.envs.gym_async import AsyncGymnasiumEnv

    one = GymnasiumEnv("gym_image_envs:ImageDict-v0", 2)
    many = AsyncGymnasiumEnv("gym_image_envs:ImageDict-v0", 2)
    try:
        assert many.observation_spec == one.observation_spec
        one.set_seed(1), many.set_seed(1)
        a, b = one.reset()["observation"], many.reset()["observation"]
        assert set(b.keys()) == {"vector", "cam.front"}
        assert b["cam.front"].dtype == torch.uint8 and b["cam.front"].shape == (2, 3, 6, 5)
        assert (a == b).all()
        for _ in range(4):  # across an autoreset
            (na, aa), (nb, ab) = _step(one, 2), _step(many, 2)
            assert (na["observation"] == nb["observation"]).all() and (aa == ab).all()
            assert nb["observation", "cam.front"].dtype == torch.uint8
    finally:
        one.close()
        many.close()


def test_envpool_pong_gives_uint8_4x84x84_stacked_frames_newest_last():
    pytest.importorskip("envpool")
    from rlexp.envs.envpool_env import EnvPoolEnv

    env = EnvPoolEnv("Pong-v5", 2, seed=1, num_threads=1)
    try:
        (part,) = env.obs_layout.parts
        assert (part.kind, part.shape, part.source_layout) == ("image", (4, 84, 84), "chw")
        spec = env.observation_spec["observation"]
        assert set(spec.keys()) == {"pixels"} and spec["pixels"].dtype == torch.uint8
        obs = env.reset()["observation"]["pixels"]
        assert obs.shape == (2, 4, 84, 84) and obs.dtype == torch.uint8
        for _ in range(3):
            nxt, after = _step(env, 2)
            new = nxt["observation", "pixels"]
            assert new.dtype == torch.uint8
            assert torch.equal(new[:, :3], obs[:, 1:])  # the stack moved by one frame
            obs = after["pixels"].clone()
    finally:
        env.close()
    stacked2 = EnvPoolEnv("Pong-v5", 2, seed=1, num_threads=1, frame_stack=2)
    try:  # env.frame_stack=2: EnvPool's own stack_num
        assert stacked2.observation_spec["observation", "pixels"].shape == (2, 2, 84, 84)
        assert stacked2.obs_layout.record()["frame_stack"] == 2
    finally:
        stacked2.close()
    for kw, words in (
        ({"name": "Hopper-v5"}, ["env.frame_stack=2", "no stack_num"]),
        ({"name": "Pong-v5", "kwargs": {"stack_num": 3}}, ["env.kwargs.stack_num=3", "disagree"]),
    ):
        with pytest.raises(ValueError) as err:
            EnvPoolEnv(num_envs=1, frame_stack=2, **kw)
        assert "\n" not in str(err.value) and all(w in str(err.value) for w in words), err.value


def test_a_torchrl_env_s_image_entries_pass_through_as_uint8_chw():
    from torchrl.envs import EnvBase

    class Cam(EnvBase):
        """Two copies, a HWC uint8 ``pixels`` [2, 6, 5, 3] and a float ``state`` [2, 2]."""

        def __init__(self):
            super().__init__(batch_size=torch.Size([2]))
            self.observation_spec = Composite(
                pixels=Bounded(0, 255, shape=(2, 6, 5, 3), dtype=torch.uint8),
                state=Unbounded(shape=(2, 2)),
                shape=(2,),
            )
            self.action_spec = Bounded(-1, 1, shape=(2, 1))
            self.reward_spec = Unbounded(shape=(2, 1))
            self.t = 0

        def _obs(self):
            px = torch.stack([torch.from_numpy(frame(HWC, self.t, i)) for i in range(2)])
            return TensorDict(
                {"pixels": px, "state": torch.full((2, 2), float(self.t))}, batch_size=[2]
            )

        def _reset(self, td=None, **kw):
            self.t = 0
            return self._obs().update({"done": torch.zeros(2, 1, dtype=torch.bool)})

        def _step(self, td):
            self.t += 1
            out = self._obs()
            out["reward"] = torch.ones(2, 1)
            out["done"] = out["terminated"] = torch.zeros(2, 1, dtype=torch.bool)
            return out

        def _set_seed(self, seed):
            return seed

    from rlexp.envs.torchrl_env import TorchRLAdapter

    env = TorchRLAdapter(Cam(), "cams:make")
    spec = env.observation_spec["observation"]
    assert spec["pixels"].shape == (2, 3, 6, 5) and spec["pixels"].dtype == torch.uint8
    assert spec["vector"].shape == (2, 2)
    obs = env.reset()["observation"]
    np.testing.assert_array_equal(obs["pixels"][1].numpy(), chw(frame(HWC, 0, 1)))
    nxt = env.step_action(torch.zeros(2, 1))
    o = nxt["observation"]
    assert o["pixels"].dtype == torch.uint8 and o["vector"].dtype == torch.float32
    np.testing.assert_array_equal(o["pixels"][0].numpy(), chw(frame(HWC, 1, 0)))
    np.testing.assert_array_equal(o["vector"].numpy(), np.ones((2, 2)))
    assert env.env_state()["obs"]["pixels"].dtype == torch.uint8


# -- the command line -----------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("args", "words"),
    [
        (
            ["env.name=gym_image_envs:ImageRank5-v0"],
            ["gym_image_envs:ImageRank5-v0", "unsupported layout", "(2, 2, 6, 5, 3)"],
        ),
        (
            ["env.name=gym_image_envs:Vector-v0", "env.frame_stack=4"],
            ["env.frame_stack=4", "has no image"],
        ),
        (["env=cart_pole", "env.frame_stack=4"], ["env.frame_stack=4", "'native'"]),
    ],
)
def test_image_refusals_are_one_line_exit_2_before_the_run_dir(tmp_path, args, words):
    run_dir = tmp_path / "r"
    proc = run_train(
        ["env=gym", f"hydra.run.dir={run_dir}", *args],
        cwd=tmp_path,
        check=False,
        env_extra=PYPATH,
    )
    assert proc.returncode == 2, proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, proc.stderr
    for word in words:
        assert word in lines[0], lines[0]
    assert "Traceback" not in proc.stderr and not run_dir.exists()


def test_a_dict_of_nested_images_and_vectors_trains_from_the_cli_through_workers(tmp_path):
    """End to end: worker processes, env.frame_stack=2, env.image_keys=[depth], a nested image
    key ("cam.front": also a name an nn.ModuleDict cannot take as it is), the CNN policy; the
    checkpoint records the images' layout and the frame stack."""
    from rlexp.checkpoints.files import latest_checkpoint, load_checkpoint

    run_dir = tmp_path / "r"
    args = [
        "env=gym",
        "env.name=gym_image_envs:ImageDict-v0",
        "env.backend=gymnasium_async",
        "env.num_envs=2",
        "env.num_eval_envs=1",
        "env.frame_stack=2",
        "env.image_keys=[depth]",
        "policy=cnn",
        "policy.encoder.kernel_sizes=[2,2,1]",
        "policy.encoder.strides=[1,1,1]",
        "trainer.total_frames=128",
        "trainer.frames_per_batch=64",
        "trainer.eval_every=128",
        "trainer.eval_episodes=1",
        "trainer.save_every=64",
        "algorithm.mini_batch_size=32",
        "algorithm.num_epochs=1",
        f"hydra.run.dir={run_dir}",
    ]
    run_train(args, cwd=tmp_path, env_extra=PYPATH)
    layout = load_checkpoint(latest_checkpoint(run_dir / "checkpoints"))["observation_layout"]
    assert layout["frame_stack"] == 2 and layout["dim"] == 2
    images = {p["image_key"]: p for p in layout["parts"] if p["kind"] == "image"}
    assert images["cam.front"]["shape"] == [6, 6, 5]  # 2 frames x 3 channels, H 6, W 5
    assert images["cam.front"]["source_layout"] == "stack_hwc"
    assert images["depth"]["shape"] == [2, 4, 7]  # 2 grey [4, 7] frames


@pytest.mark.parametrize(
    ("overrides", "words"),
    [
        (["env.frame_stack=-1"], ["env.frame_stack=-1 must be 0 to 64"]),
        (["env.frame_stack=65"], ["env.frame_stack=65 must be 0 to 64"]),
        (['env.image_keys=[""]'], ["env.image_keys=['']", "a list of observation keys"]),
        (["env=cart_pole", "env.image_keys=[cam]"], ["env.image_keys", "'native'"]),
        (["env.backend=torchrl", "env.frame_stack=2"], ["env.frame_stack=2", "'torchrl'"]),
    ],
)
def test_frame_stack_and_image_keys_rules_are_one_line_config_errors(overrides, words):
    from conftest import compose
    from rlexp.config.validate import ConfigError, to_root_config

    with pytest.raises(ConfigError) as err:
        to_root_config(compose(["env=gym", "env.name=gym_image_envs:Image-v0", *overrides]))
    msg = str(err.value)
    assert "\n" not in msg
    for word in words:
        assert word in msg, msg


def test_envpool_dict_observations_encode_each_copy_as_one_env_would():
    """EnvPool tasks whose observation is a Dict of batched leaves (MiniGrid: a 7x7x3 image, a
    Discrete direction, a 96-byte mission; DMC: named float64 vectors) used to be refused. Each
    copy is now encoded as one env's observation is: the vector in the Dict's key order (the
    direction one-hot, then the mission's bytes as floats), the image HWC -> CHW uint8; values
    against the raw pool's by hand, at reset and after steps with different actions per copy."""
    pytest.importorskip("envpool")
    import envpool

    from rlexp.envs.envpool_env import EnvPoolEnv

    env = EnvPoolEnv("MiniGrid-Empty-5x5-v0", 3, seed=5, num_threads=1)
    raw = envpool.make_gymnasium("MiniGrid-Empty-5x5-v0", num_envs=3, seed=5, num_threads=1)
    try:
        got = [(p.key, p.kind, p.offset, p.size) for p in env.obs_layout.parts]
        assert got == [("direction", "discrete", 0, 4), ("image", "image", -1, 0),
                       ("mission", "box", 4, 96)]  # fmt: skip
        assert env.obs_layout.images[0].shape == (3, 7, 7)

        def by_hand(o):
            vector = np.concatenate(
                [np.eye(4, dtype=np.float32)[o["direction"]], o["mission"].astype(np.float32)], 1
            )
            return vector, o["image"].transpose(0, 3, 1, 2)

        def check(obs, o):
            vector, image = by_hand(o)
            assert obs["vector"].dtype == torch.float32 and obs["image"].dtype == torch.uint8
            np.testing.assert_array_equal(obs["vector"].numpy(), vector)
            np.testing.assert_array_equal(obs["image"].numpy(), image)

        check(env.reset()["observation"], raw.reset()[0])
        for actions in ([2, 1, 0], [1, 1, 2], [0, 2, 2]):
            nxt = env.step_tensors(torch.tensor(actions).unsqueeze(-1))
            o, _, term, trunc, _ = raw.step(np.array(actions))
            assert not (term | trunc).any()  # (no copy finished: the raw pool needs no reset)
            check(nxt["observation"], o)
    finally:
        env.close()
        raw.close()
    dmc = EnvPoolEnv("CheetahRun-v1", 2, seed=3, num_threads=1)
    raw = envpool.make_gymnasium("CheetahRun-v1", num_envs=2, seed=3, num_threads=1)
    try:  # a Dict of named vectors: one float32 vector, position (8) then velocity (9)
        assert [(p.key, p.offset, p.size) for p in dmc.obs_layout.parts] == [
            ("position", 0, 8), ("velocity", 8, 9)
        ]  # fmt: skip
        o = raw.reset()[0]
        want = np.concatenate([o["position"], o["velocity"]], 1).astype(np.float32)
        np.testing.assert_array_equal(dmc.reset()["observation"].numpy(), want)
    finally:
        dmc.close()
        raw.close()


def test_an_envpool_dict_task_trains_with_an_actor_group_of_its_keys(tmp_path):
    """End to end on EnvPool's MiniGrid: the actor reads the image and the direction only, the
    critic everything; a small CNN on the 7x7 image; the checkpoint records the Dict's layout."""
    pytest.importorskip("envpool")
    from rlexp.checkpoints.files import latest_checkpoint, load_checkpoint

    run_dir = tmp_path / "r"
    args = [
        "env=pong",
        "env.name=MiniGrid-Empty-5x5-v0",
        "~env.kwargs.episodic_life",
        "~env.kwargs.reward_clip",
        "env.num_envs=3",
        "env.num_eval_envs=1",
        "policy=cnn",
        "policy.encoder.channels=[4,8]",
        "policy.encoder.kernel_sizes=[3,2]",
        "policy.encoder.strides=[1,1]",
        "policy.actor.observations=[image,direction]",
        "trainer.total_frames=96",
        "trainer.frames_per_batch=48",
        "trainer.eval_every=96",
        "trainer.eval_episodes=1",
        "trainer.save_every=48",
        "algorithm.mini_batch_size=24",
        "algorithm.num_epochs=1",
        f"hydra.run.dir={run_dir}",
    ]
    run_train(args, cwd=tmp_path)
    ckpt = load_checkpoint(latest_checkpoint(run_dir / "checkpoints"))
    parts = {p["key"]: p for p in ckpt["observation_layout"]["parts"]}
    assert parts["image"]["shape"] == [3, 7, 7] and parts["image"]["source_layout"] == "hwc"
    assert (parts["direction"]["size"], parts["mission"]["size"]) == (4, 96)
    weights = ckpt["policy"]  # linear heads on [512 image features, the selected vector]
    assert weights["actor_net.mlp.0.weight"].shape == (7, 512 + 4)  # image, direction: no mission
    assert weights["critic_net.mlp.0.weight"].shape == (1, 512 + 4 + 96)  # everything
