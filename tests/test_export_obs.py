"""Exports take the env's own observation (#45 item 4) and act in the env's own action bounds
(item 6): ``rlexp export`` writes a numpy-only observation helper beside the file; docs/export.md's
deployment blocks for a Dict env run verbatim in a process where ``import rlexp`` fails, and every
action they send equals rlexp's own policy's on the same observation. An ``env.rescale_actions``
run's export outputs actions in the env's bounds, says so in its metadata, and ``rlexp eval`` of it
gives the checkpoint's numbers."""

from __future__ import annotations

import json
import os
import pickle
import re
import subprocess
import sys
import textwrap
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import torch
from gymnasium import spaces
from test_docs_envs import _example

from conftest import REPO, train_side_by_side
from conftest import rlexp_cli as _cli
from rlexp.deploy.export_obs import helper_name, helper_source
from rlexp.deploy.policy_eval import evaluate, metadata_path

TESTS = Path(__file__).parent
#: docs/export.md's run dir (the blocks name it; the test trains the corridor run there)
DOC_RUN = "outputs/2026-11-28/10-00-00.412345"
TINY = [
    "env=gym",
    "env.num_eval_envs=2",
    "trainer.total_frames=512",
    "trainer.frames_per_batch=256",
    "trainer.eval_every=256",
    "trainer.eval_episodes=2",
    "trainer.save_every=256",
    "algorithm.num_epochs=1",
    "trainer.progress=false",
]
RUNS = {
    # Dict observation (a Discrete with start=1, a nested Dict), Box actions in [0, 5] x [-3, 1]
    "throttle": ["env.name=toy_envs:Throttle-v0", "env.rescale_actions=true", "seed=3"],
    # docs/envs.md's Corridor: Dict observation with a Discrete goal, Discrete actions
    "corridor": ["env.name=corridor:Corridor-v0", "+env.kwargs.length=10", "seed=1"],
}


def _doc_blocks() -> list[str]:
    text = (REPO / "docs" / "export.md").read_text()
    section = text.split("## Deploying on the env's own observations", 1)[1].split("\n## ", 1)[0]
    return re.findall(r"```python\n(.*?)```", section, re.S)


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> Iterator[dict[str, Path]]:
    """The two tiny runs trained side by side, each exported in both formats (its best.pt)."""
    root = tmp_path_factory.mktemp("export_obs")
    (root / "corridor.py").write_text(_example())
    dirs = {"throttle": root / "throttle", "corridor": root / DOC_RUN}
    extra = {"PYTHONPATH": os.pathsep.join([str(REPO / "src"), str(TESTS), str(root)])}
    train_side_by_side({n: [*TINY, *RUNS[n]] for n in RUNS}, dirs, root, extra)
    sys.path.insert(0, str(root))  # corridor importable here (toy_envs is: tests/)
    try:
        yield _export_all(root, dirs)
    finally:
        sys.path.remove(str(root))


def _export_all(root: Path, dirs: dict[str, Path]) -> dict[str, Path]:
    for run_dir in dirs.values():
        for fmt in ("torchscript", "onnx"):
            rc, out, err = _cli("export", run_dir, "--format", fmt, "--checkpoint", "best")
            assert rc == 0, err
            suffix = {"torchscript": "pt", "onnx": "onnx"}[fmt]
            helper = run_dir / "exported" / f"best_{suffix}_obs.py"
            assert out.splitlines()[-1] == (
                f"observation helper (numpy only; docs/export.md): {helper}"
            ), out
    return {"root": root, **dirs}


#: Runs a docs block in a fresh interpreter (-I: no PYTHONPATH, no cwd, no user site) where rlexp
#: cannot be imported, recording every observation the env gives and every action it is sent.
_HARNESS = textwrap.dedent(
    """
    import pickle, sys
    sys.path = [p for p in sys.path if not p.rstrip("/").endswith("/src")]  # (a checkout's src/)
    class NoRlexp:
        def find_spec(self, name, path=None, target=None):
            if name == "rlexp" or name.startswith("rlexp."):
                raise ModuleNotFoundError(f"No module named {name!r}")
    sys.meta_path.insert(0, NoRlexp())
    try:
        import rlexp  # noqa: F401
        raise SystemExit("rlexp is importable")
    except ModuleNotFoundError:
        pass
    sys.path.insert(0, sys.argv[3])  # where the env module lives (corridor.py, toy_envs.py)
    import gymnasium as gym
    seen = []
    class Record(gym.Wrapper):
        def reset(self, **kw):
            obs, info = self.env.reset(**kw)
            self.obs = obs
            return obs, info
        def step(self, action):
            seen.append((self.obs, action))
            out = self.env.step(action)
            self.obs = out[0]
            return out
    make = gym.make
    gym.make = lambda *a, **kw: Record(make(*a, **kw))
    exec(compile(open(sys.argv[1]).read(), "docs-block", "exec"), {"__name__": "__main__"})
    assert not any(m == "rlexp" or m.startswith("rlexp.") for m in sys.modules)
    pickle.dump(seen, open(sys.argv[2], "wb"))
    print("steps", len(seen))
    """
)


def _run_outside_rlexp(code: str, cwd: Path, module_dir: Path, name: str) -> list:
    (cwd / f"{name}.py").write_text(code)
    (cwd / "harness.py").write_text(_HARNESS)
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    proc = subprocess.run(
        [sys.executable, "-I", "harness.py", f"{name}.py", f"{name}.pkl", str(module_dir)],
        cwd=cwd, env=env, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert proc.returncode == 0 and "steps" in proc.stdout, proc.stdout + proc.stderr
    return pickle.loads((cwd / f"{name}.pkl").read_bytes())


def _rlexp_env_actions(checkpoint: Path, observations: list) -> tuple[np.ndarray, list]:
    """rlexp's own flattening of ``observations`` and the actions its deterministic policy sends
    the env for them (clipped, rescaled, decoded as its env adapter does)."""
    from tensordict import TensorDict

    from rlexp.deploy.policy_eval import open_source, typed_config
    from rlexp.envs.factory import make_env

    source = open_source(checkpoint)
    config = typed_config(source.config, str(checkpoint))
    env = make_env(config.env, 1, seed=0)
    try:
        flat = np.stack([env.obs_layout.flatten(o) for o in observations])
        policy = source.build(config, env)
        with torch.no_grad():
            td = policy(TensorDict({"observation": torch.from_numpy(flat)}, batch_size=[len(flat)]))
        raw = env.clip_array(td["action"].numpy())
        return flat, [env.action_coding.decode(raw[i]) for i in range(len(raw))]
    finally:
        env.close()


def test_the_docs_deployment_blocks_act_as_rlexp_without_rlexp(runs):
    blocks = _doc_blocks()
    assert len(blocks) == 2 and "torch.jit.load" in blocks[0] and "onnxruntime" in blocks[1]
    best = runs["corridor"] / "checkpoints" / "best.pt"
    for i, block in enumerate(blocks):
        seen = _run_outside_rlexp(block, runs["root"], runs["root"], f"block{i}")
        assert len(seen) >= 2
        observations = [obs for obs, _ in seen]
        assert isinstance(observations[0], dict) and set(observations[0]) == {"goal", "position"}
        _, want = _rlexp_env_actions(best, observations)
        assert [a for _, a in seen] == want and all(isinstance(a, int) for a in want)


_THROTTLE_BLOCK = textwrap.dedent(
    """
    import sys
    import gymnasium as gym
    import numpy as np
    import torch
    sys.path.insert(0, "throttle/exported")
    import best_pt_obs, best_onnx_obs
    import onnxruntime as ort
    policy = torch.jit.load("throttle/exported/best.pt")
    session = ort.InferenceSession("throttle/exported/best.onnx", providers=["CPUExecutionProvider"])
    env = gym.vector.SyncVectorEnv([lambda: gym.make("toy_envs:Throttle-v0")] * 3)
    obs, _ = env.reset(seed=5)
    rows = []
    for _ in range(6):
        x = best_pt_obs.flatten(obs, batch=True)
        y = policy(torch.from_numpy(x)).detach().numpy()
        z = session.run(["action"], {"observation": best_onnx_obs.flatten(obs, batch=True)})[0]
        assert np.allclose(y, z, atol=1e-5), (y, z)
        rows.append((obs, best_pt_obs.env_action(y, batch=True)))
        obs, *_ = env.step(best_pt_obs.env_action(y, batch=True))
    import pickle
    pickle.dump(rows, open("throttle_rows.pkl", "wb"))
    """
)


def test_a_dict_env_with_bounds_is_deployed_batched_in_its_bounds(runs):
    """A vector env's batched Dict observations through the helper, both formats; the actions
    are rlexp's (rescaled onto [0, 5] x [-3, 1]) to 1e-5."""
    _run_outside_rlexp(_THROTTLE_BLOCK, runs["root"], TESTS, "throttle")
    rows = pickle.loads((runs["root"] / "throttle_rows.pkl").read_bytes())
    best = runs["throttle"] / "checkpoints" / "best.pt"
    for batched, got in rows:
        observations = [{k: _index(v, i) for k, v in batched.items()} for i in range(3)]
        _, want = _rlexp_env_actions(best, observations)
        np.testing.assert_allclose(got, np.stack(want), atol=1e-5, rtol=0)
        assert (got[:, 0] >= 0).all() and (got[:, 0] <= 5).all()
        assert (got[:, 1] >= -3).all() and (got[:, 1] <= 1).all()


def _index(value, i):
    return {k: _index(v, i) for k, v in value.items()} if isinstance(value, dict) else value[i]


def test_a_rescaled_run_s_export_says_so_and_evaluates_as_its_checkpoint(runs):
    run = runs["throttle"]
    meta = json.loads(metadata_path(run / "exported" / "best.pt").read_text())
    assert meta["actions_rescaled"] is True and meta["actions_clamped"] is True
    assert (meta["action_low"], meta["action_high"]) == ([0.0, -3.0], [5.0, 1.0])
    assert meta["observation_helper"] == "best_pt_obs.py"
    want = evaluate(str(run / "checkpoints" / "best.pt"), 4, None)
    for name in ("best.pt", "best.onnx"):
        got = evaluate(str(run / "exported" / name), 4, None)
        assert got["mean_return"] == pytest.approx(want["mean_return"], rel=1e-5, abs=1e-5)
    # the run's env warned about nothing (rescaled); a plain run of the env would have
    assert "action bounds" not in (runs["root"] / "throttle.log").read_text()


SPACES = {
    "discrete_root": spaces.Discrete(16),
    "discrete_start": spaces.Discrete(4, start=-2),
    "tuple": spaces.Tuple(
        (spaces.MultiDiscrete([3, 2], start=[1, 0]), spaces.MultiBinary(3), spaces.Discrete(2))
    ),
    "nested": spaces.Dict(
        {
            "b": spaces.Box(-1, 1, (2, 2), np.float64),
            "a": spaces.Dict({"z": spaces.Discrete(3, start=5), "y": spaces.Box(0, 9, (1,))}),
        }
    ),
    "box_2d": spaces.Box(-5, 5, (3, 2), np.float32),
}


@pytest.mark.parametrize("kind", sorted(SPACES))
def test_the_helper_flattens_every_space_as_rlexp_does(kind, tmp_path):
    """Without training: the helper's ``flatten`` against rlexp's ``ObsLayout.flatten`` on drawn
    observations, one at a time and batched; Discrete(16) at the root is FrozenLake's one-hot."""
    import runpy

    from rlexp.envs.spaces import action_coding, obs_layout

    space = SPACES[kind]
    layout = obs_layout(space, kind)
    action = action_coding(spaces.MultiBinary((2, 2)), kind).record()
    target = tmp_path / "policy.onnx"
    path = tmp_path / helper_name(target)
    path.write_text(helper_source(target, kind, layout.record(), action))
    helper = runpy.run_path(str(path))
    space.seed(7)
    drawn = [space.sample() for _ in range(5)]
    want = np.stack([layout.flatten(o) for o in drawn])
    got = np.concatenate([helper["flatten"](o) for o in drawn])
    assert got.dtype == np.float32 and np.array_equal(got, want)
    if kind == "discrete_start":  # one-hot by hand: value v at index v - start
        assert np.array_equal(helper["flatten"](-1), [[0.0, 1.0, 0.0, 0.0]])
    # the file's output holds the env's values already: reshaped to the space, its dtype
    one = helper["env_action"](np.array([1, 0, 0, 1]))
    assert one.dtype == np.int8 and one.tolist() == [[1, 0], [0, 1]]
    two = helper["env_action"](np.array([[1, 0, 0, 1], [0, 1, 1, 1]]), batch=True)
    assert two.shape == (2, 2, 2) and two[1].tolist() == [[0, 1], [1, 1]]
