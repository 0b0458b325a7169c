"""Exports of grouped and image policies (#47 items 2 and 4): the file takes only the actor's inputs
(its vector parts and uint8 images), the metadata lists them and is checked as data, the numpy
helper builds them from the env's raw observation, and outside rlexp (TorchScript and ONNX) the file
acts as rlexp's deterministic policy does; ``rlexp eval`` of an export never reads what only the
critic read (a deployment env without the privileged state evaluates it)."""

from __future__ import annotations

import json
import os
import pickle
import subprocess
import sys
import textwrap
from collections.abc import Iterator
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch

from conftest import REPO, train_side_by_side
from conftest import rlexp_cli as _cli
from rlexp.deploy.policy_eval import evaluate, metadata_path

TESTS = Path(__file__).parent
TINY = [
    "env.num_envs=2",
    "env.num_eval_envs=2",
    "trainer.total_frames=256",
    "trainer.frames_per_batch=128",
    "trainer.eval_every=128",
    "trainer.eval_episodes=2",
    "trainer.save_every=128",
    "algorithm.num_epochs=1",
    "algorithm.mini_batch_size=64",
    "trainer.progress=false",
]
RUNS = {
    # the actor reads what a robot measures; the critic (default: every part) the privileged state
    "grouped": [
        "env=gym",
        "env.name=export_envs:Privileged-v0",
        "policy.actor.observations=[joints,phase]",
        "policy.actor.hidden_sizes=[16,16]",
        "seed=3",
    ],
    # Nature CNN (SB3 / CleanRL defaults) on the HWC camera, beside the speed vector; the critic
    # also reads the CHW depth image (its own encoder: shared only where both read an image)
    "image": [
        "env=gym",
        "env.name=export_envs:Pixels-v0",
        "policy=cnn",
        "policy.actor.observations=[camera,speed]",
        "seed=2",
    ],
    # push_cube's default asymmetric critic: its privileged group (cube velocity, cube-to-goal)
    "native": ["env=push_cube", "env.num_envs=4", "seed=4"],
}
FORMATS = {"torchscript": ".pt", "onnx": ".onnx"}
ENV_VARS = {"RLEXP_ENV_MODULES": "export_envs"}


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> Iterator[dict[str, Path]]:
    """The two tiny runs, each exported in both formats (its last checkpoint)."""
    root = tmp_path_factory.mktemp("export_groups")
    dirs = {name: root / name for name in RUNS}
    extra = {"PYTHONPATH": os.pathsep.join([str(REPO / "src"), str(TESTS)]), **ENV_VARS}
    train_side_by_side({n: [*TINY, *RUNS[n]] for n in RUNS}, dirs, root, extra)
    old = os.environ.get("RLEXP_ENV_MODULES")
    os.environ["RLEXP_ENV_MODULES"] = "export_envs"
    try:
        for run_dir in dirs.values():
            for fmt, suffix in FORMATS.items():
                rc, _, err = _cli(
                    "export", run_dir, "--format", fmt, "--out", run_dir / f"p{suffix}"
                )
                assert rc == 0, err
        yield {"root": root, **dirs}
    finally:
        if old is None:
            os.environ.pop("RLEXP_ENV_MODULES")
        else:
            os.environ["RLEXP_ENV_MODULES"] = old


def _meta(path: Path) -> dict:
    return json.loads(metadata_path(path).read_text())


def test_the_metadata_lists_only_the_actor_s_inputs(runs):
    grouped = _meta(runs["grouped"] / "p.pt")
    [vector] = grouped["inputs"]
    # joints [3] and phase Discrete(3, start=1) one-hot [3]; privileged [2] is the critic's only
    assert (vector["name"], vector["kind"], vector["dtype"]) == ("observation", "vector", "float32")
    assert vector["shape"] == ["batch", 6] and vector["groups"] == ["policy"]
    assert [(p["key"], p["input_offset"]) for p in vector["parts"]] == [("joints", 0), ("phase", 3)]
    assert grouped["observation_dim"] == 8 and grouped["input_shape"] == ["batch", 6]
    assert grouped["actor_observations"] == ["joints", "phase"]
    assert grouped["critic_observations"] == ["joints", "phase", "privileged"]

    image = _meta(runs["image"] / "p.onnx")
    assert [(i["name"], i["kind"], i["dtype"], i["shape"]) for i in image["inputs"]] == [
        ("observation", "vector", "float32", ["batch", 2]),
        ("camera", "image", "uint8", ["batch", 3, 36, 36]),  # HWC [36, 36, 3] given as CHW
    ]
    assert image["inputs"][1]["parts"][0]["source_layout"] == "hwc"
    assert image["critic_observations"] == ["camera", "depth", "speed"]
    assert "depth" not in json.dumps(image["inputs"])


def test_a_native_task_s_privileged_group_is_not_an_input(runs, monkeypatch):
    """push_cube: 59 values in the env's vector, of which the privileged group's 6 (cube velocity
    [3], cube-to-goal [3]) only the critic reads; the file takes the other 53, names them, and
    evaluates as its checkpoint."""
    meta = _meta(runs["native"] / "p.pt")
    [vector] = meta["inputs"]
    assert meta["observation_dim"] == 59 and vector["shape"] == ["batch", 53]
    assert vector["groups"] == ["policy"] and len(meta["observation_names"]) == 53
    assert not any(n.startswith("privileged/") for n in meta["observation_names"])
    assert meta["critic_observations"][-2:] == ["privileged/cube_to_goal", "privileged/cube_vel"]
    want = evaluate(str(runs["native"]), 2, None)
    for suffix in FORMATS.values():
        got = evaluate(str(runs["native"] / f"p{suffix}"), 2, None)
        assert got["mean_return"] == pytest.approx(want["mean_return"], rel=1e-5, abs=1e-6)


def _raw_observations(env_id: str, n: int, drop: str | None = None) -> list:
    """Raw observations of ``env_id`` (random actions, seeded), as the env gives them; ``drop``: a
    key removed (what a deployment does not have)."""
    import export_envs  # noqa: F401  (registers the ids)

    env = gym.make(env_id)
    env.action_space.seed(1)
    obs, _ = env.reset(seed=11)
    seen = []
    for _ in range(n):
        seen.append({k: v for k, v in obs.items() if k != drop})
        obs, _, term, trunc, _ = env.step(env.action_space.sample())
        if term or trunc:
            obs, _ = env.reset()
    env.close()
    return seen


def _rlexp_actions(run_dir: Path, observations: list) -> np.ndarray:
    """rlexp's own deterministic policy (the checkpoint's, in process) on ``observations``: the
    values the env takes (Box: clipped to the bounds; Discrete: plus its start)."""
    from tensordict import TensorDict

    from rlexp.deploy.policy_eval import open_source, typed_config
    from rlexp.envs.factory import make_env

    source = open_source(run_dir)
    config = typed_config(source.config, str(run_dir))
    env = make_env(config.env, 1, seed=0)
    try:
        encoded = [env.obs_layout.encode(o) for o in observations]
        if isinstance(encoded[0], dict):
            obs = TensorDict(
                {k: torch.from_numpy(np.stack([e[k] for e in encoded])) for k in encoded[0]},
                batch_size=[len(encoded)],
            )
        else:
            obs = torch.from_numpy(np.stack(encoded))
        policy = source.build(config, env)
        with torch.no_grad():
            action = policy(TensorDict({"observation": obs}, batch_size=[len(encoded)]))["action"]
        coding = env.action_coding
        if coding.categorical:
            return (action + torch.tensor(coding.start)).numpy()
        return torch.clamp(
            action, env.action_spec.space.low[0], env.action_spec.space.high[0]
        ).numpy()
    finally:
        env.close()


#: Runs in a fresh interpreter where ``import rlexp`` fails: the helper builds the inputs from the
#: raw observations, TorchScript and onnxruntime act on them.
_OUTSIDE = textwrap.dedent(
    """
    import pickle, runpy, sys
    sys.path = [p for p in sys.path if not p.rstrip("/").endswith("/src")]
    class NoRlexp:
        def find_spec(self, name, path=None, target=None):
            if name == "rlexp" or name.startswith("rlexp."):
                raise ModuleNotFoundError(f"No module named {name!r}")
    sys.meta_path.insert(0, NoRlexp())
    import numpy as np, onnxruntime as ort, torch
    job = pickle.load(open(sys.argv[1], "rb"))
    out = {}
    for fmt, (file, helper) in job["files"].items():
        h = runpy.run_path(helper)
        one = [h["inputs"](o) for o in job["observations"]]
        xs = {k: np.concatenate([x[k] for x in one]) for k in one[0]}
        batched = h["inputs"]({k: np.stack([o[k] for o in job["observations"]])
                               for k in job["observations"][0]}, batch=True)
        assert all(np.array_equal(xs[k], batched[k]) for k in xs)
        if fmt == "torchscript":
            module = torch.jit.load(file)
            y = module(*[torch.from_numpy(v) for v in xs.values()]).numpy()
        else:
            session = ort.InferenceSession(file, providers=["CPUExecutionProvider"])
            assert [i.name for i in session.get_inputs()] == list(xs)
            y = session.run(["action"], xs)[0]
        out[fmt] = (y, {k: (v.dtype.str, v.shape) for k, v in xs.items()},
                    [h["env_action"](row) for row in y])
    assert not any(m == "rlexp" or m.startswith("rlexp.") for m in sys.modules)
    pickle.dump(out, open(sys.argv[2], "wb"))
    """
)


def _outside_rlexp(run_dir: Path, observations: list, tmp_path: Path) -> dict:
    files = {}
    for fmt, suffix in FORMATS.items():
        path = run_dir / f"p{suffix}"
        files[fmt] = (str(path), str(path.parent / _meta(path)["observation_helper"]))
    job, result = tmp_path / "job.pkl", tmp_path / "result.pkl"
    job.write_bytes(pickle.dumps({"files": files, "observations": observations}))
    (tmp_path / "outside.py").write_text(_OUTSIDE)
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    proc = subprocess.run(
        [sys.executable, "-I", "outside.py", str(job), str(result)],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return pickle.loads(result.read_bytes())


def test_a_grouped_export_acts_as_rlexp_outside_rlexp_without_the_privileged_state(runs, tmp_path):
    """The deployment's observations have no ``privileged`` key at all; rlexp's policy is given
    the full ones (the critic's part with values the actor must ignore)."""
    full = _raw_observations("export_envs:Privileged-v0", 24)
    want = _rlexp_actions(runs["grouped"], full)
    deployed = [{k: v for k, v in o.items() if k != "privileged"} for o in full]
    got = _outside_rlexp(runs["grouped"], deployed, tmp_path)
    assert not np.allclose(want, want[:1])  # the observations give different actions
    for fmt, (y, inputs, env_actions) in got.items():
        assert inputs == {"observation": ("<f4", (24, 6))}, fmt
        np.testing.assert_allclose(y, want, atol=1e-5, rtol=0, err_msg=fmt)
        assert env_actions[0].dtype == np.float64 and env_actions[0].shape == (2,)


def test_an_image_export_takes_uint8_and_acts_as_rlexp_outside_rlexp(runs, tmp_path):
    observations = _raw_observations("export_envs:Pixels-v0", 24)
    want = _rlexp_actions(runs["image"], observations)
    got = _outside_rlexp(runs["image"], observations, tmp_path)
    for fmt, (y, inputs, env_actions) in got.items():
        assert inputs == {"observation": ("<f4", (24, 2)), "camera": ("|u1", (24, 3, 36, 36))}
        assert y.dtype == np.int64 and y.shape == (24, 1), fmt
        np.testing.assert_array_equal(y, want, err_msg=fmt)
        assert set(np.unique(y)) <= {-1, 0, 1} and all(isinstance(a, int) for a in env_actions)
    # the helper's camera input is the raw HWC frame moved to CHW (numpy by hand)
    helper = runs["image"] / _meta(runs["image"] / "p.pt")["observation_helper"]
    import runpy

    camera = runpy.run_path(str(helper))["inputs"](observations[0])["camera"]
    np.testing.assert_array_equal(camera[0], observations[0]["camera"].transpose(2, 0, 1))


def test_eval_of_a_grouped_export_needs_no_critic_observation(runs, monkeypatch):
    """Evaluated on an env that has no privileged state (the deployment's), the export gives the
    numbers of its checkpoint on the training env; the checkpoint itself cannot be built there."""
    import export_envs

    monkeypatch.setenv("RLEXP_ENV_MODULES", "export_envs")
    want = evaluate(str(runs["grouped"]), 3, None)
    monkeypatch.setattr(export_envs, "PRIVILEGED", False)
    for suffix in FORMATS.values():
        got = evaluate(str(runs["grouped"] / f"p{suffix}"), 3, None)
        assert got["mean_return"] == pytest.approx(want["mean_return"], rel=1e-5, abs=1e-5)
        assert got["episodes"] == 3
    with pytest.raises(ValueError, match="observation"):
        evaluate(str(runs["grouped"]), 3, None)


def test_eval_of_an_image_run_s_checkpoint_and_exports_agree(runs, monkeypatch):
    monkeypatch.setenv("RLEXP_ENV_MODULES", "export_envs")
    want = evaluate(str(runs["image"]), 4, None)
    for suffix in FORMATS.values():
        got = evaluate(str(runs["image"] / f"p{suffix}"), 4, None)
        assert got["mean_return"] == want["mean_return"] and got["episodes"] == 4


@pytest.mark.parametrize(
    ("field", "value", "words"),
    [
        ("dtype", "float64", "inputs[1].dtype='float64' is not 'uint8'"),
        ("name", "__import__('os')", "inputs[1].name="),
        ("shape", ["batch", 3, 36], "inputs[1].shape="),
        ("kind", "code", "inputs[1].kind='code' is not one of ['vector', 'image', 'action_mask']"),
        (
            "parts",
            [
                {
                    "key": "camera",
                    "kind": "image",
                    "shape": [3, 36, 36],
                    "offset": -1,
                    "size": 0,
                    "image_key": "camera",
                    "source_layout": "bgr",
                }
            ],
            "inputs[1].parts=",
        ),
    ],  # fmt: skip
)
def test_a_tampered_inputs_field_is_one_line(runs, tmp_path, field, value, words):
    import shutil

    path = tmp_path / "p.pt"
    shutil.copy(runs["image"] / "p.pt", path)
    meta = _meta(runs["image"] / "p.pt")
    meta["inputs"][1][field] = value
    metadata_path(path).write_text(json.dumps(meta))
    rc, _, err = _cli("eval", path)
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert rc == 2 and len(lines) == 1, err
    assert words in lines[0] and "export metadata is data" in lines[0], lines[0]


def test_an_actor_of_two_images_and_no_vector_exports_with_named_uint8_inputs(tmp_path):
    """No training: the actor reads the camera and the depth image (no vector), the critic the
    speed too; both files against the policy's own deterministic action on a TensorDict."""
    import export_envs  # noqa: F401
    from tensordict import TensorDict

    from conftest import compose
    from rlexp.config.validate import to_root_config
    from rlexp.deploy.export_actor import DeterministicActor, exported_module, input_records
    from rlexp.deploy.export_meta import check_inputs
    from rlexp.envs.factory import make_env
    from rlexp.policies.actor_critic import policy_for_env

    overrides = ["env=gym", "env.name=export_envs:Pixels-v0", "policy=cnn"]
    overrides += ["policy.actor.observations=[camera,depth]", "policy.encoder.features_dim=24"]
    config = to_root_config(compose(overrides))
    env = make_env(config.env, 1, 0)
    torch.manual_seed(5)
    policy = policy_for_env(config.policy, config.env, env).eval()
    env.close()
    with torch.no_grad():  # (orthogonal init's 0.01 gain: every image would pick one action)
        policy.actor_net.mlp[-1].weight.normal_(0.0, 1.0)
    actor = DeterministicActor(policy, torch.zeros(1), torch.zeros(1), False, [-1])
    records = input_records(actor, policy)
    check_inputs(records, "test")
    assert [(r["name"], r["shape"]) for r in records] == [
        ("camera", ["batch", 3, 36, 36]),
        ("depth", ["batch", 1, 36, 36]),
    ]
    gen = torch.Generator().manual_seed(4)
    camera = torch.randint(0, 256, (9, 3, 36, 36), generator=gen, dtype=torch.uint8)
    depth = torch.randint(0, 256, (9, 1, 36, 36), generator=gen, dtype=torch.uint8)
    speed = torch.randn(9, 2, generator=gen)
    td = TensorDict({"vector": speed, "camera": camera, "depth": depth}, batch_size=[9])
    with torch.no_grad():
        want = policy.sampling_policy(deterministic=True).sample(td)[1] - 1  # start -1
    assert len(set(want[:, 0].tolist())) > 1
    scripted = exported_module(actor, torchscript=True)
    torch.jit.save(scripted, str(tmp_path / "a.pt"))
    loaded = torch.jit.load(str(tmp_path / "a.pt"))
    torch.testing.assert_close(loaded(camera, depth), want, atol=0, rtol=0)
    torch.testing.assert_close(loaded(camera[:1], depth[:1]), want[:1], atol=0, rtol=0)
    import onnxruntime as ort

    from rlexp.deploy.export import _write_onnx

    _write_onnx(actor, tmp_path / "a.onnx")
    session = ort.InferenceSession(str(tmp_path / "a.onnx"), providers=["CPUExecutionProvider"])
    assert [(i.name, i.type) for i in session.get_inputs()] == [
        ("camera", "tensor(uint8)"),
        ("depth", "tensor(uint8)"),
    ]
    got = session.run(["action"], {"camera": camera.numpy(), "depth": depth.numpy()})[0]
    np.testing.assert_array_equal(got, want.numpy())


def test_the_helper_stacks_frames_and_builds_images_as_rlexp_s_env_does(tmp_path):
    """No training: env.frame_stack=3 over a Dict of a nested HWC image, a grey [H, W] image
    (env.image_keys) and a vector; the helper's FrameStack + inputs on the raw env's observations
    (episodes of 3 steps: resets refill the stack) equal the observation rlexp's env emits."""
    import runpy

    import gym_image_envs  # noqa: F401  (registers the ids)

    from conftest import compose
    from rlexp.config.validate import to_root_config
    from rlexp.deploy.export_actor import DeterministicActor, input_records
    from rlexp.deploy.export_obs import helper_name, helper_source
    from rlexp.envs.factory import make_env
    from rlexp.policies.actor_critic import policy_for_env

    overrides = ["env=gym", "env.name=gym_image_envs:ImageDict-v0", "env.frame_stack=3"]
    overrides += ["env.image_keys=[depth]", "policy=cnn", "policy.encoder.kernel_sizes=[2,2,1]"]
    overrides += ["policy.encoder.strides=[1,1,1]"]
    config = to_root_config(compose(overrides))
    env = make_env(config.env, 1, 0)
    try:
        policy = policy_for_env(config.policy, config.env, env)
        inputs = input_records(
            DeterministicActor(policy, torch.zeros(1), torch.zeros(1), False), policy
        )
        assert [(i["name"], i["shape"]) for i in inputs] == [
            ("observation", ["batch", 2]),
            ("cam_front", ["batch", 9, 6, 5]),  # 3 frames x 3 channels
            ("depth", ["batch", 3, 4, 7]),  # 3 grey frames
        ]
        target = tmp_path / "p.pt"
        path = tmp_path / helper_name(target)
        path.write_text(helper_source(target, "x", env.obs_layout.record(), {}, inputs))
        helper = runpy.run_path(str(path))
        assert helper["FRAME_STACK"] == 3
        raw = gym.make("gym_image_envs:ImageDict-v0")
        stack = helper["FrameStack"]()
        obs = stack.reset(raw.reset(seed=0)[0])
        td = env.reset().get("observation")
        for t in range(8):
            xs = helper["inputs"](obs)
            for spec in inputs:
                want = td.get(spec["key"])
                np.testing.assert_array_equal(xs[spec["name"]], want.numpy(), err_msg=f"{t}")
            raw_obs, _, term, trunc, _ = raw.step(0)
            obs = stack.reset(raw.reset()[0]) if term or trunc else stack.step(raw_obs)
            nxt = env.step_action(torch.zeros(1, 1, dtype=torch.int64))
            td = env.autoreset_observation(nxt)
        raw.close()
    finally:
        env.close()


@pytest.mark.parametrize(
    ("change", "words"),
    [
        ({"key": "joint"}, "its actor reads the observation 'joint', which the env of its config"),
        ({"shape": [4]}, "reads the observation 'joints' as {'shape': [4]}; the env of its config"),
    ],
)
def test_an_actor_part_the_env_lacks_is_one_line(runs, tmp_path, monkeypatch, change, words):
    import shutil

    monkeypatch.setenv("RLEXP_ENV_MODULES", "export_envs")
    path = tmp_path / "p.onnx"
    shutil.copy(runs["grouped"] / "p.onnx", path)
    meta = _meta(runs["grouped"] / "p.onnx")
    meta["inputs"][0]["parts"][0].update(change)
    metadata_path(path).write_text(json.dumps(meta))
    rc, _, err = _cli("eval", path)
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert rc == 2 and len(lines) == 1, err
    assert words in lines[0], lines[0]


def test_input_names_are_identifiers_that_never_shadow_the_wrapper_s_own_names():
    """The TorchScript wrapper's argument names come from image keys: anything but a word
    character becomes "_", and a name that would shadow ``self`` / ``torch`` or start with a
    digit gets a prefix; duplicates get a suffix."""
    from types import SimpleNamespace

    from rlexp.deploy.export_actor import input_names

    actor = SimpleNamespace(
        reads_vector=True, image_keys=["torch", "self", "cam.front", "cam_front", "1x", "a);b"]
    )
    assert input_names(actor) == [
        "observation",
        "image_torch",
        "image_self",
        "cam_front",
        "cam_front_",
        "image_1x",
        "a__b",
    ]
