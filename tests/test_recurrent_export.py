"""Exports of recurrent policies (#48, ``policy.memory.type`` lstm / gru): the file takes the actor's
observation inputs and its state (``actor_h``, ``actor_c`` for an LSTM) and returns the action and
the next state (``actor_h_out``, ``actor_c_out``); the critic's memory is never in it; the metadata's
``memory`` says the state's shape and that it is zeros at an episode's start, and is checked as data.
Outside rlexp (TorchScript and onnxruntime, the numpy helper) whole episodes stepped through the file,
the state carried, act as the policy's ``act`` does step by step; ``rlexp eval`` of the file carries
and resets the state: the run's own eval numbers."""

from __future__ import annotations

import json
import os
import pickle
import re
import shutil
import subprocess
import sys
import textwrap
from collections.abc import Iterator
from pathlib import Path

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
    "trainer.eval_episodes=3",
    "trainer.save_every=128",
    "algorithm.num_epochs=1",
    "algorithm.mini_batch_size=64",
    "algorithm.sequence_length=8",
    "trainer.progress=false",
]
RUNS = {
    # an LSTM of 2 layers x 12 on the actor's selection (joints, phase); the critic, with its own
    # LSTM, also reads the privileged state
    "lstm": [
        "env=gym",
        "env.name=export_envs:Privileged-v0",
        "policy.actor.observations=[joints,phase]",
        "policy.memory.type=lstm",
        "policy.memory.hidden_size=12",
        "policy.memory.num_layers=2",
        "policy.ortho_init=false",  # (torch's default init: actions far from 0, the state matters)
        "seed=3",
    ],
    # a GRU of 8 after the Nature CNN on the HWC camera and the speed vector (categorical actions)
    "gru": [
        "env=gym",
        "env.name=export_envs:Pixels-v0",
        "policy=cnn",
        "policy.actor.observations=[camera,speed]",
        "policy.memory.type=gru",
        "policy.memory.hidden_size=8",
        "policy.ortho_init=false",  # (logits far enough apart for the actions to vary)
        "seed=2",
    ],
    # a GRU with an action mask from info (env=pick_valid): the mask input, then the state
    "masked": [
        "env=pick_valid",
        "policy.memory.type=gru",
        "policy.memory.hidden_size=8",
        "policy.ortho_init=false",
        "seed=1",
    ],
    # docs/export.md's run: an LSTM on Pendulum-v1 (its blocks run verbatim)
    "pendulum": [
        "env=pendulum",
        "policy.memory.type=lstm",
        "policy.memory.hidden_size=12",
        "policy.ortho_init=false",
        "seed=5",
    ],
}
#: docs/export.md's run dir (its blocks name it; the test trains the pendulum run there)
DOC_RUN = "outputs/2026-11-28/11-00-00.123456"
FORMATS = {"torchscript": ".pt", "onnx": ".onnx"}
ENV_VARS = {"RLEXP_ENV_MODULES": "export_envs"}


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> Iterator[dict[str, Path]]:
    """The two tiny recurrent runs, each exported in both formats (its last checkpoint)."""
    root = tmp_path_factory.mktemp("recurrent_export")
    dirs = {name: root / name for name in RUNS}
    dirs["pendulum"] = root / DOC_RUN
    extra = {"PYTHONPATH": os.pathsep.join([str(REPO / "src"), str(TESTS)]), **ENV_VARS}
    train_side_by_side({n: [*TINY, *RUNS[n]] for n in RUNS}, dirs, root, extra)
    old = os.environ.get("RLEXP_ENV_MODULES")
    os.environ["RLEXP_ENV_MODULES"] = "export_envs"
    try:
        for name, run_dir in dirs.items():
            where = ["--checkpoint", "best"] if name == "pendulum" else ["--out", run_dir / "p"]
            for fmt in FORMATS:
                rc, out, err = _cli("export", run_dir, "--format", fmt, *where)
                assert rc == 0, err
                if name == "lstm":  # the last line says what the caller carries
                    assert out.splitlines()[-1] == (
                        "recurrent state (docs/export.md): actor_h, actor_c float32 ['batch', 2, "
                        "12] in, actor_h_out, actor_c_out out; zeros at each episode's start"
                    ), out
        yield {"root": root, **dirs}
    finally:
        if old is None:
            os.environ.pop("RLEXP_ENV_MODULES")
        else:
            os.environ["RLEXP_ENV_MODULES"] = old


def _meta(path: Path) -> dict:
    return json.loads(metadata_path(path).read_text())


def _state(name: str, layers: int, hidden: int) -> dict:
    return {
        "name": name,
        "output": f"{name}_out",
        "dtype": "float32",
        "shape": ["batch", layers, hidden],
    }


def test_the_metadata_says_the_state_and_how_to_reset_it(runs):
    lstm = _meta(runs["lstm"] / "p.pt")
    assert lstm["memory"] == {
        "type": "lstm",
        "num_layers": 2,
        "hidden_size": 12,
        "shared": False,
        "state": [_state("actor_h", 2, 12), _state("actor_c", 2, 12)],
        "reset": "zeros at episode start",
    }
    assert lstm["output_names"] == ["action", "actor_h_out", "actor_c_out"]
    assert [i["name"] for i in lstm["inputs"]] == ["observation"]  # the actor's joints and phase
    gru = _meta(runs["gru"] / "p.onnx")
    assert gru["memory"]["type"] == "gru" and gru["memory"]["state"] == [_state("actor_h", 1, 8)]
    assert gru["output_names"] == ["action", "actor_h_out"]
    assert [i["name"] for i in gru["inputs"]] == ["observation", "camera"]
    for meta in (lstm, gru):  # the critic's memory is not the file's
        assert "critic_" not in json.dumps({k: meta[k] for k in ("memory", "inputs")})


#: Runs in a fresh interpreter where ``import rlexp`` fails: whole episodes of the env stepped
#: through each file with the numpy helper, the state carried from output to input.
_OUTSIDE = textwrap.dedent(
    """
    import pickle, runpy, sys
    sys.path = [p for p in sys.path if not p.rstrip("/").endswith("/src")]
    class NoRlexp:
        def find_spec(self, name, path=None, target=None):
            if name == "rlexp" or name.startswith("rlexp."):
                raise ModuleNotFoundError(f"No module named {name!r}")
    sys.meta_path.insert(0, NoRlexp())
    import gymnasium as gym, numpy as np, torch
    job = pickle.load(open(sys.argv[1], "rb"))
    sys.path.insert(0, job["tests"])
    import export_envs  # registers the ids
    if job["env_file"]:  # an env shipped inside rlexp (pick_valid): its file alone, by path
        import importlib.util
        spec = importlib.util.spec_from_file_location("env_outside", job["env_file"])
        spec.loader.exec_module(importlib.util.module_from_spec(spec))
    try:
        import onnxruntime as ort
    except ImportError:
        ort = None
    out = {}
    for fmt, (file, helper) in job["files"].items():
        if fmt == "onnx" and ort is None:
            continue
        h = runpy.run_path(helper)
        names = [s["name"] for s in h["MEMORY"]["state"]]
        if fmt == "torchscript":
            module = torch.jit.load(file)
            run = lambda feed: [y.numpy() for y in module(*[torch.from_numpy(v) for v in feed.values()])]
        else:
            session = ort.InferenceSession(file, providers=["CPUExecutionProvider"])
            signature = [(i.name, i.shape) for i in session.get_inputs()]
            outputs = [o.name for o in session.get_outputs()]
            run = lambda feed: session.run(outputs, feed)
        env = gym.make(job["env_id"])
        obs, info = env.reset(seed=job["seed"])
        state = h["initial_state"]()
        steps = []
        for episode in range(job["episodes"]):
            done, start = False, True
            while not done:
                y, *new = run({**h["inputs"](obs, info=info), **state})
                steps.append((obs, start, y, new, info))
                state, start = dict(zip(names, new)), False
                obs, _, terminated, truncated, info = env.step(h["env_action"](y[0]))
                done = terminated or truncated
            obs, info = env.reset()
            state = h["reset_state"](state, [True])  # the next episode starts from zeros
        out[fmt] = {"steps": steps, "signature": signature if fmt == "onnx" else None,
                    "outputs": outputs if fmt == "onnx" else None}
    assert not any(m == "rlexp" or m.startswith("rlexp.") for m in sys.modules)
    pickle.dump(out, open(sys.argv[2], "wb"))
    """
)


def _outside_rlexp(run_dir: Path, tmp_path: Path, episodes: int = 2) -> dict:
    files = {}
    for fmt, suffix in FORMATS.items():
        path = run_dir / f"p{suffix}"
        files[fmt] = (str(path), str(path.parent / _meta(path)["observation_helper"]))
    module, env_id = _meta(run_dir / "p.pt")["env_id"].split(":")
    env_file = None  # an env module inside rlexp (env=pick_valid) is loaded by its file's path
    if module.startswith("rlexp."):
        env_file = str(REPO / "src" / (module.replace(".", "/") + ".py"))
    job, result = tmp_path / "job.pkl", tmp_path / "result.pkl"
    job.write_bytes(pickle.dumps({"files": files, "env_id": env_id, "seed": 17, "episodes": episodes,
                                  "tests": str(TESTS), "env_file": env_file}))  # fmt: skip
    (tmp_path / "outside.py").write_text(_OUTSIDE)
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    proc = subprocess.run(
        [sys.executable, "-I", "outside.py", str(job), str(result)],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return pickle.loads(result.read_bytes())


def _policy_actions(run_dir: Path, steps: list, carry: bool = True) -> np.ndarray:
    """The checkpoint's policy, in process, on the observations the file saw: ``policy.act`` with
    the state carried and set to ``initial_state`` at each episode's start (``carry=False``: at
    every step, a policy without memory), as the env's values (Box clipped, categorical + start).
    A step's ``info`` mask (an env with ``info["action_mask"]``) joins the observation as rlexp's
    env puts it there."""
    from tensordict import TensorDict

    from rlexp.deploy.policy_eval import open_source, typed_config
    from rlexp.envs.factory import make_env

    source = open_source(run_dir)
    config = typed_config(source.config, str(run_dir))
    env = make_env(config.env, 1, seed=0)
    try:
        policy = source.build(config, env).policy  # (rlexp eval's RecurrentActor holds it)
        coding = env.action_coding
        out, state = [], None
        for obs, start, *_, info in steps:
            encoded = env.obs_layout.encode(obs, info)  # (an info mask: in the TensorDict)
            if isinstance(encoded, dict):
                x = TensorDict({k: torch.from_numpy(np.asarray(v))[None] for k, v in
                                encoded.items()}, batch_size=[1])  # fmt: skip
            else:
                x = torch.from_numpy(np.asarray(encoded))[None]
            if start or not carry:
                state = policy.initial_state(1)
            action, state = policy.act(x, state, deterministic=True)
            if coding.categorical:
                out.append((action + torch.tensor(coding.start)).numpy()[0])
            else:
                low, high = env.action_spec.space.low[0], env.action_spec.space.high[0]
                out.append(torch.clamp(action, low, high).numpy()[0])
        return np.stack(out)
    finally:
        env.close()


#: Each run's memory (num_layers, hidden_size, state inputs) and its episodes' length.
SHAPES = {
    "lstm": (2, 12, ["actor_h", "actor_c"], 12),
    "gru": (1, 8, ["actor_h"], 8),
    "masked": (1, 8, ["actor_h"], 20),
}


@pytest.mark.parametrize("name", ["lstm", "gru", "masked"])
def test_episodes_stepped_through_the_file_outside_rlexp_act_as_the_policy(runs, tmp_path, name):
    """Two whole episodes per file (one env, the state carried from output to input, zeros after
    the reset): each action equals ``policy.act``'s with its own carried state; the masked file's
    never an invalid one."""
    pytest.importorskip("onnxruntime", reason="the ONNX half needs onnxruntime (extra 'export')")
    got = _outside_rlexp(runs[name], tmp_path)
    assert set(got) == set(FORMATS)
    layers, hidden, states, length = SHAPES[name]
    onnx = got["onnx"]
    inputs = [i["name"] for i in _meta(runs[name] / "p.onnx")["inputs"]]
    assert [n for n, _ in onnx["signature"]] == [*inputs, *states]  # the state last
    assert [s for n, s in onnx["signature"] if n in states] == [["batch", layers, hidden]] * len(
        states
    )
    assert onnx["outputs"] == ["action", *(f"{s}_out" for s in states)]
    for fmt, result in got.items():
        steps = result["steps"]
        assert len(steps) == 2 * length
        assert [i for i, step in enumerate(steps) if step[1]] == [0, length]  # episode starts
        file_actions = np.concatenate([step[2] for step in steps])
        assert not np.allclose(file_actions, file_actions[:1]), "one action throughout: vacuous"
        want = _policy_actions(runs[name], steps)
        if name == "lstm":
            np.testing.assert_allclose(file_actions, want, atol=1e-5, rtol=0, err_msg=fmt)
        else:
            np.testing.assert_array_equal(file_actions, want, err_msg=fmt)
        for step in steps:  # the state out has the metadata's shape
            assert [s.shape for s in step[3]] == [(1, layers, hidden)] * len(states), fmt
        if name == "masked":  # never an invalid action
            assert all(step[4]["action_mask"][int(step[2][0, 0])] for step in steps), fmt
    # the memory matters: without the carried state the policy acts otherwise
    steps = got["torchscript"]["steps"]
    memoryless = _policy_actions(runs[name], steps, carry=False)
    assert not np.allclose(memoryless, np.concatenate([step[2] for step in steps]))


def test_rlexp_eval_of_the_files_carries_and_resets_the_state_as_the_run_did(runs, monkeypatch):
    """The run's last eval round (in training), ``rlexp eval`` of its checkpoint and of its
    TorchScript file: the same numbers, exactly (ONNX: within onnxruntime's rounding); a file
    whose state is never reset at an episode's end gives others."""
    from rlexp.checkpoints.files import latest_checkpoint, load_checkpoint
    from rlexp.deploy.export_feed import ExportedPolicy

    monkeypatch.setenv("RLEXP_ENV_MODULES", "export_envs")
    run_dir = runs["lstm"]
    logged = load_checkpoint(latest_checkpoint(run_dir / "checkpoints"))["last_eval"]
    want = (logged["eval/episode_return"], logged["eval/episode_return_std"])
    checkpoint = evaluate(str(run_dir), None, None)
    script = evaluate(str(run_dir / "p.pt"), None, None)
    assert checkpoint["episodes"] == script["episodes"] == 3
    assert (checkpoint["mean_return"], checkpoint["std_return"]) == want
    assert (script["mean_return"], script["std_return"]) == want
    onnx = evaluate(str(run_dir / "p.onnx"), None, None)
    assert onnx["mean_return"] == pytest.approx(want[0], rel=1e-5)
    monkeypatch.setattr(ExportedPolicy, "episodes_ended", lambda self, done: None)
    kept = evaluate(str(run_dir / "p.pt"), None, None)
    assert abs(kept["mean_return"] - want[0]) > 1e-3, kept  # (float rounding is far below)


@pytest.mark.parametrize(
    ("change", "words"),
    [
        ({"type": "rnn"}, "memory.type='rnn' is not one of ['lstm', 'gru']"),
        ({"hidden_size": 13}, "memory.state="),
        ({"reset": "never"}, "memory.reset='never' is not 'zeros at episode start'"),
        ({"num_layers": 0}, "memory.num_layers=0 is not a whole number >= 1"),
        ({"shared": "yes"}, "memory.shared='yes' is not true or false"),
    ],
)
def test_a_tampered_memory_field_is_one_line(runs, tmp_path, change, words):
    path = tmp_path / "p.pt"
    shutil.copy(runs["lstm"] / "p.pt", path)
    meta = _meta(runs["lstm"] / "p.pt")
    meta["memory"].update(change)
    metadata_path(path).write_text(json.dumps(meta))
    rc, _, err = _cli("eval", path)
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert rc == 2 and len(lines) == 1, err
    assert words in lines[0] and "export metadata is data" in lines[0], lines[0]


def test_an_image_key_named_like_a_state_input_is_renamed():
    """The state inputs keep their fixed names (actor_h, actor_c): an image keyed ``actor_h``
    becomes ``actor_h_``."""
    from types import SimpleNamespace

    from torch import nn

    from rlexp.deploy.export_actor import LstmStep, input_names, state_names

    core = LstmStep(nn.LSTM(3, 4, batch_first=True))
    actor = SimpleNamespace(reads_vector=True, image_keys=["actor_h", "actor_c"], core=core)
    assert state_names(actor) == ["actor_h", "actor_c"]
    assert input_names(actor) == ["observation", "actor_h_", "actor_c_"]


@pytest.mark.parametrize("suffix", list(FORMATS.values()))
def test_metadata_without_the_memory_of_a_recurrent_file_is_one_line(runs, tmp_path, suffix):
    """A recurrent file whose metadata lost its ``memory`` would be called without its state."""
    pytest.importorskip("onnxruntime")
    path = tmp_path / f"p{suffix}"
    shutil.copy(runs["lstm"] / f"p{suffix}", path)
    meta = _meta(runs["lstm"] / f"p{suffix}")
    del meta["memory"], meta["output_names"]
    metadata_path(path).write_text(json.dumps(meta))
    rc, _, err = _cli("eval", path)
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert rc == 2 and len(lines) == 1, err
    assert "takes the inputs ['observation', 'actor_h', 'actor_c']; its metadata names " \
        "['observation']" in lines[0], lines[0]  # fmt: skip


#: Runs a docs block in a fresh interpreter where ``import rlexp`` fails, recording each step the
#: block's env takes: (observation, whether an episode starts with it, action).
_HARNESS = textwrap.dedent(
    """
    import pickle, runpy, sys
    sys.path = [p for p in sys.path if not p.rstrip("/").endswith("/src")]
    class NoRlexp:
        def find_spec(self, name, path=None, target=None):
            if name == "rlexp" or name.startswith("rlexp."):
                raise ModuleNotFoundError(f"No module named {name!r}")
    sys.meta_path.insert(0, NoRlexp())
    import gymnasium as gym
    real_make, seen = gym.make, []
    def make(*args, **kwargs):
        env = real_make(*args, **kwargs)
        reset, step, last = env.reset, env.step, {}
        def on_reset(*a, **k):
            obs, info = reset(*a, **k)
            last.update(obs=obs, start=True)
            return obs, info
        def on_step(action):
            seen.append((last["obs"], last["start"], action))
            out = step(action)
            last.update(obs=out[0], start=False)
            return out
        env.reset, env.step = on_reset, on_step
        return env
    gym.make = make
    runpy.run_path(sys.argv[1], run_name="__main__")
    assert not any(m == "rlexp" or m.startswith("rlexp.") for m in sys.modules)
    pickle.dump(seen, open(sys.argv[2], "wb"))
    """
)


def _doc_blocks() -> list[str]:
    text = (REPO / "docs" / "export.md").read_text()
    section = text.split("## Recurrent policies", 1)[1].split("\n## ", 1)[0]
    return re.findall(r"```python\n(.*?)```", section, re.S)


def test_the_docs_recurrent_blocks_run_verbatim_and_act_as_the_policy(runs):
    """docs/export.md's two blocks (TorchScript: two episodes; ONNX: one), outside rlexp in the
    run's folder: every action the env got is the policy's, the state carried and reset."""
    pytest.importorskip("onnxruntime")
    blocks = _doc_blocks()
    assert len(blocks) == 2 and "torch.jit.load" in blocks[0] and "onnxruntime" in blocks[1]
    root = runs["root"]
    (root / "harness.py").write_text(_HARNESS)
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    for i, (block, episodes) in enumerate(zip(blocks, (2, 1), strict=True)):
        (root / f"block{i}.py").write_text(block)
        proc = subprocess.run(
            [sys.executable, "-I", "harness.py", f"block{i}.py", f"block{i}.pkl"],
            cwd=root, env=env, capture_output=True, text=True, timeout=120,
        )  # fmt: skip
        assert proc.returncode == 0, proc.stdout + proc.stderr
        seen = pickle.loads((root / f"block{i}.pkl").read_bytes())
        assert len(seen) == 200 * episodes and sum(start for _, start, _ in seen) == episodes
        got = np.stack([np.asarray(a, dtype=np.float32) for _, _, a in seen])
        best = runs["pendulum"] / "checkpoints" / "best.pt"  # what the blocks' files hold
        want = _policy_actions(best, [(o, start, None, None, None) for o, start, _ in seen])
        np.testing.assert_allclose(got, want, atol=1e-5, rtol=0, err_msg=f"block {i}")
        assert not np.allclose(got, got[:1])
