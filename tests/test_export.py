"""``rlexp export``: the exported TorchScript / ONNX file, loaded in a process that never imports
rlexp, acts as the checkpoint's deterministic policy (normaliser folded in, actions clipped as the
env clips them) on observations of real rollouts, for PPO's actor-critic on Hopper-v5 and GRPO's
actor-only policy on the native cart_pole; ``rlexp eval`` of an exported file gives the checkpoint's
numbers; ``rlexp eval --video`` writes a decodable mp4; bad input is one line, exit 2."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch

from conftest import REPO, Children
from conftest import rlexp_cli as _cli
from rlexp.checkpoints.files import load_checkpoint, save_checkpoint, step_checkpoints
from rlexp.deploy.policy_eval import evaluate, metadata_path, open_source

#: PPO (actor_critic) on Hopper-v5: two iterations of 256 steps, an eval after each (best.pt).
HOPPER = [
    "env=hopper",
    "env.max_episode_steps=50",
    "env.num_eval_envs=2",
    "trainer.total_frames=512",
    "trainer.frames_per_batch=256",
    "trainer.eval_every=256",
    "trainer.eval_episodes=2",
    "trainer.save_every=256",
    "algorithm.num_epochs=1",
    "trainer.progress=false",
]
#: GRPO (actor_only) on the native cart_pole: one iteration of 8 envs x 32 steps.
CART_POLE = [
    "algorithm=grpo",
    "env=cart_pole",
    "env.num_envs=8",
    "env.num_eval_envs=2",
    "env.max_episode_steps=50",
    "trainer.total_frames=256",
    "trainer.frames_per_batch=256",
    "trainer.eval_every=256",
    "trainer.eval_episodes=2",
    "trainer.save_every=256",
    "algorithm.num_epochs=1",
    "trainer.progress=false",
]
FORMATS = {"torchscript": ".pt", "onnx": ".onnx"}


def _one_line_error(args: tuple, code: int = 2) -> str:
    rc, out, err = _cli(*args)
    lines = err.strip().splitlines()
    assert rc == code and len(lines) == 1 and "Traceback" not in err, (rc, out, err)
    return lines[0]


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, Path]:
    """The two tiny runs, trained side by side (a few seconds each)."""
    root = tmp_path_factory.mktemp("export_runs")
    env = {**os.environ, "PYTHONPATH": str(REPO / "src")}
    with Children() as children:  # both killed (process groups) if one fails or times out
        procs = {
            name: children.popen(
                [
                    sys.executable,
                    str(REPO / "train.py"),
                    *overrides,
                    f"hydra.run.dir={root / name}",
                ],
                cwd=root,
                env=env,
                stdout=subprocess.PIPE,
                stderr=subprocess.STDOUT,
                text=True,
            )
            for name, overrides in (("hopper", HOPPER), ("cart_pole", CART_POLE))
        }
        for name, proc in procs.items():
            out, _ = proc.communicate(timeout=300)
            assert proc.returncode == 0, f"{name}: train.py exited {proc.returncode}\n{out}"
    return {name: root / name for name in procs}


@pytest.fixture(scope="module")
def exported(runs) -> dict[tuple[str, str], Path]:
    """Each run exported in both formats through the command line (run dir: its best.pt)."""
    files = {}
    for task, run_dir in runs.items():
        for fmt, suffix in FORMATS.items():
            rc, out, err = _cli("export", run_dir, "--format", fmt, "--checkpoint", "best")
            assert rc == 0, err
            best = run_dir / "checkpoints" / "best.pt"
            path = run_dir / "exported" / f"best{suffix}"
            assert out.splitlines() == [
                f"exported {best} (step {load_checkpoint(best)['global_step']}; --checkpoint best: "
                f"the best evaluation) as {fmt}: {path}",
                f"metadata: {metadata_path(path)}",
            ], out
            files[task, fmt] = path
    return files


def _rollout_observations(checkpoint: Path, steps: int = 40) -> torch.Tensor:
    """Observations of real episodes of the checkpoint's env (4 copies), acting with its
    deterministic actions plus noise (so the states are varied), and a few far outside the
    training statistics (so the normaliser's clip acts)."""
    from rlexp.config.validate import to_root_config
    from rlexp.deploy.policy_eval import eval_config
    from rlexp.envs.factory import make_env

    source = open_source(checkpoint)
    config = to_root_config(eval_config(source.config))
    env = make_env(config.env, 4, seed=123)
    policy = source.build(config, env)
    sample = policy.sampler()
    gen = torch.Generator().manual_seed(0)
    obs = env.reset().get("observation")
    seen = []
    for _ in range(steps):
        seen.append(obs)
        action = sample(obs)[2]
        nxt = env.step_action(action + 0.3 * torch.randn(action.shape, generator=gen))
        obs = env.autoreset_observation(nxt)
    env.close()
    real = torch.cat(seen)
    return torch.cat([real, real[:4] * 50.0, -real[:4] * 50.0 - 20.0])


def _rlexp_actions(checkpoint: Path, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The checkpoint's deterministic policy (rlexp's sampler, its normaliser) on ``obs``: the
    raw mean action, and the action the env applies (clipped to the action bounds)."""
    from rlexp.config.validate import to_root_config
    from rlexp.deploy.policy_eval import eval_config
    from rlexp.envs.factory import make_env

    source = open_source(checkpoint)
    config = to_root_config(eval_config(source.config))
    env = make_env(config.env, 1, seed=0)
    sample = source.build(config, env).sampler()
    low, high = env.action_spec.space.low[0], env.action_spec.space.high[0]
    env.close()
    with torch.no_grad():
        loc = sample(obs)[2]
    return loc, torch.clamp(loc, low, high)


#: Runs in a fresh interpreter: loads each exported file with torch / onnxruntime only.
_LOADER = textwrap.dedent(
    """
    import json, sys
    import numpy as np
    jobs = json.load(open(sys.argv[1]))
    for job in jobs:
        obs = np.load(job["obs"])
        meta = json.load(open(job["file"] + ".json"))
        if meta["format"] == "torchscript":
            import torch
            module = torch.jit.load(job["file"])
            out = module(torch.from_numpy(obs)).numpy()
            one = module(torch.from_numpy(obs[:1])).numpy()
        else:
            import onnxruntime as ort
            session = ort.InferenceSession(job["file"], providers=["CPUExecutionProvider"])
            [inp], [outp] = session.get_inputs(), session.get_outputs()
            assert (inp.name, outp.name) == (meta["input_name"], meta["output_name"])
            assert inp.shape[1] == meta["observation_dim"] and isinstance(inp.shape[0], str)
            out = session.run([outp.name], {inp.name: obs})[0]
            one = session.run([outp.name], {inp.name: obs[:1]})[0]
        assert one.shape == (1, meta["action_dim"]), one.shape
        np.save(job["out"], out)
    assert "rlexp" not in sys.modules, sorted(m for m in sys.modules if m.startswith("rlexp"))
    print("loaded", len(jobs))
    """
)


def _load_outside_rlexp(jobs: list[dict[str, str]], tmp_path: Path) -> None:
    (tmp_path / "jobs.json").write_text(json.dumps(jobs))
    (tmp_path / "loader.py").write_text(_LOADER)
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    proc = subprocess.run(
        [sys.executable, str(tmp_path / "loader.py"), str(tmp_path / "jobs.json")],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        env=env,
        timeout=120,
    )
    assert proc.returncode == 0 and f"loaded {len(jobs)}" in proc.stdout, proc.stdout + proc.stderr


def _wild_checkpoint(runs, tmp_path: Path) -> Path:
    """Hopper's best.pt with the actor's last layer scaled up: mean actions far outside [-1, 1]."""
    ckpt = load_checkpoint(runs["hopper"] / "checkpoints" / "best.pt")
    layers = [k.split(".")[2] for k in ckpt["policy"] if k.startswith("actor_net.mlp.")]
    last = f"mlp.{max(map(int, layers))}.weight"
    for key in ckpt["policy"]:  # the actor's parameters sit under two names (actor_net, actor)
        if key.startswith("actor") and key.endswith(last):
            ckpt["policy"][key] = ckpt["policy"][key] * 300.0
    ckpt.pop("path")
    return save_checkpoint(tmp_path / "wild.pt", ckpt)


def test_exported_files_act_as_the_checkpoint_outside_rlexp(runs, exported, tmp_path):
    wild = _wild_checkpoint(runs, tmp_path)
    cases = {
        (task, fmt): (runs[task] / "checkpoints" / "best.pt", path)
        for (task, fmt), path in exported.items()
    }
    for fmt in FORMATS:
        rc, _, err = _cli(
            "export", wild, "--format", fmt, "--out", tmp_path / f"wild_policy{FORMATS[fmt]}"
        )
        assert rc == 0, err
        cases["wild", fmt] = (wild, tmp_path / f"wild_policy{FORMATS[fmt]}")
    jobs, expected = [], {}
    for (task, fmt), (ckpt, path) in cases.items():
        obs = _rollout_observations(ckpt)
        loc, applied = _rlexp_actions(ckpt, obs)
        expected[task, fmt] = applied
        if task == "wild":  # the clip matters here: the raw means leave the bounds
            assert (loc.abs() > 1.0).float().mean() > 0.2
        else:
            assert (loc.abs() < 1.0).all()
        name = f"{task}_{fmt}"
        np.save(tmp_path / f"{name}_obs.npy", obs.numpy())
        jobs.append(
            {
                "file": str(path),
                "obs": str(tmp_path / f"{name}_obs.npy"),
                "out": str(tmp_path / f"{name}_act.npy"),
            }
        )
    _load_outside_rlexp(jobs, tmp_path)
    for (task, fmt), job in zip(cases, jobs, strict=True):
        got = torch.from_numpy(np.load(job["out"]))
        torch.testing.assert_close(got, expected[task, fmt], atol=1e-5, rtol=0, msg=f"{task} {fmt}")


def test_metadata_names_the_env_the_source_and_the_tensors(runs, exported):
    from rlexp import __version__

    hopper = json.loads(metadata_path(exported["hopper", "onnx"]).read_text())
    best = runs["hopper"] / "checkpoints" / "best.pt"
    assert {k: hopper[k] for k in ("format", "file", "input_name", "output_name", "env_id")} == {
        "format": "onnx",
        "file": "best.onnx",
        "input_name": "observation",
        "output_name": "action",
        "env_id": "Hopper-v5",
    }
    assert (hopper["observation_dim"], hopper["action_dim"]) == (11, 3)
    assert hopper["action_low"] == [-1.0] * 3 and hopper["action_high"] == [1.0] * 3
    assert hopper["observation_names"] is None and hopper["action_names"] is None
    assert hopper["source_checkpoint"] == str(best.resolve())
    assert hopper["global_step"] == load_checkpoint(best)["global_step"]
    assert hopper["rlexp_version"] == __version__ and hopper["policy"] == "actor_critic"
    assert hopper["observation_normalizer"]["enabled"] and hopper["actions_clamped"]
    cart = json.loads(metadata_path(exported["cart_pole", "torchscript"]).read_text())
    assert (cart["format"], cart["env_id"], cart["native_task"]) == (
        "torchscript",
        "cart_pole",
        "cart_pole",
    )
    assert (cart["algorithm"], cart["policy"]) == ("grpo", "actor_only")
    assert len(cart["observation_names"]) == cart["observation_dim"] == 6
    assert cart["observation_names"][:2] == ["robot/qf[0]", "robot/qf[1]"]
    assert [t["name"] for t in cart["observation_terms"]] == [
        "robot/qf",
        "robot/qpos",
        "robot/qvel",
    ]
    assert cart["action_names"] == ["delta_qpos"] and cart["action_low"] == [-1.0]


def test_eval_of_an_exported_file_equals_eval_of_its_checkpoint(runs, exported):
    for task in runs:
        want = evaluate(str(runs[task] / "checkpoints" / "best.pt"), 4, None)
        for fmt in FORMATS:
            got = evaluate(str(exported[task, fmt]), 4, None)
            assert (got["kind"], got["global_step"]) == (fmt, want["global_step"])
            assert got["mean_return"] == pytest.approx(want["mean_return"], rel=1e-6, abs=1e-6)
            assert got["std_return"] == pytest.approx(want["std_return"], rel=1e-5, abs=1e-5)
    path = exported["cart_pole", "torchscript"]
    rc, out, _ = _cli("eval", path, "--episodes", "4")
    assert out == (
        f"exported policy {path} (torchscript of {runs['cart_pole'] / 'checkpoints' / 'best.pt'}, "
        f"step {want['global_step']}): mean return {want['mean_return']:.3f} +- "
        f"{want['std_return']:.3f} over 4 episodes\n"
    ), out


def test_eval_video_writes_a_decodable_mp4_with_the_same_numbers(exported, tmp_path):
    """An exported Hopper policy (Gymnasium: rendered with render_mode=rgb_array, which rlexp eval
    sets) filmed by the record_video event's recorder; without a path, beside the file."""
    import imageio.v2 as imageio

    path = tmp_path / "policy.pt"
    shutil.copy(exported["hopper", "torchscript"], path)
    shutil.copy(metadata_path(exported["hopper", "torchscript"]), metadata_path(path))
    plain = evaluate(str(path), 1, 1)
    rc, out, err = _cli("eval", path, "--episodes", "1", "--num-envs", "1", "--video")
    assert rc == 0, err
    assert f"mean return {plain['mean_return']:.3f} +- 0.000 over 1 episodes" in out, out
    assert out.splitlines()[-1] == f"video: {tmp_path / 'policy.mp4'}"
    frames = [f for f in imageio.get_reader(tmp_path / "policy.mp4")]  # (list() asks its len: inf)
    assert 1 <= len(frames) <= 50 and frames[0].shape == (480, 480, 3)
    assert np.ptp(np.stack(frames)) > 0  # not a blank picture
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "policy.mp4",
        "policy.pt",
        "policy.pt.json",
    ]


def test_a_run_dir_exports_its_last_checkpoint_and_best_only_when_asked(runs, tmp_path):
    run = shutil.copytree(runs["cart_pole"], tmp_path / "run")
    (run / "checkpoints" / "best.pt").unlink()
    line = _one_line_error(("export", run, "--checkpoint", "best"))
    assert line == (
        f"rlexp export: no best.pt in {str(run)!r} or its checkpoints/ (the run never evaluated): "
        "use --checkpoint last"
    )
    rc, out, err = _cli("export", run, "--out", tmp_path / "out")
    last = step_checkpoints(run / "checkpoints")[-1]
    assert rc == 0 and out.startswith(f"exported {last} (step 256; the last checkpoint)"), err
    assert (tmp_path / "out.pt").is_file() and (tmp_path / "out.pt.json").is_file()


@pytest.mark.parametrize(
    "kind",
    [
        "missing",
        "text file",
        "empty dir",
        "checkpoint flag on a file",
        "onto the checkpoint",
        "wrong suffix",
    ],
)
def test_export_errors_are_one_line_naming_the_path(runs, tmp_path, kind):
    best = runs["hopper"] / "checkpoints" / "best.pt"
    args, wanted = {
        "missing": (("export", tmp_path / "nope"), f"{str(tmp_path / 'nope')!r} does not exist"),
        "text file": (("export", tmp_path / "notes.pt"), f"{str(tmp_path / 'notes.pt')!r}"),
        "empty dir": (
            ("export", tmp_path),
            f"no rlexp checkpoint (*_step_N.pt) in {str(tmp_path)!r}",
        ),
        "checkpoint flag on a file": (
            ("export", best, "--checkpoint", "last"),
            f"{str(best)!r} is a file",
        ),
        "onto the checkpoint": (
            ("export", best, "--out", best),
            f"--out {str(best)!r} exists and is not an rlexp export (no 'best.pt.json' beside it)",
        ),
        "wrong suffix": (
            ("export", best, "--out", tmp_path / "p.onnx"),
            "a torchscript file ends in .pt, not .onnx",
        ),
    }[kind]
    (tmp_path / "notes.pt").write_text("not a checkpoint\n")
    line = _one_line_error(args)
    assert line.startswith("rlexp export: ") and wanted in line, line


def test_export_without_the_onnx_extra_names_it(runs, monkeypatch):
    from rlexp import extras

    real = extras._installed
    monkeypatch.setattr(extras, "_installed", lambda m: False if m == "onnx" else real(m))
    line = _one_line_error(("export", runs["hopper"], "--format", "onnx"))
    assert line == (
        "rlexp export: rlexp export --format onnx needs rlexp's optional 'export' extra (onnx is "
        f"not installed): {extras.install_hint('export')}"
    )
    assert re.search(r"pip install 'onnx[<>=]", line), line


def test_nan_weights_are_not_exported(runs, tmp_path):
    ckpt = load_checkpoint(runs["cart_pole"] / "checkpoints" / "best.pt")
    ckpt["policy"]["actor_net.log_std"] = torch.full_like(
        ckpt["policy"]["actor_net.log_std"], float("nan")
    )
    ckpt.pop("path")
    bad = save_checkpoint(tmp_path / "nan.pt", ckpt)
    line = _one_line_error(("export", bad), code=3)
    assert line.startswith(f"rlexp export: checkpoint {str(bad)!r} holds non-finite policy weights")


def test_eval_of_an_exported_file_without_its_metadata_says_so(exported, tmp_path):
    wanted = {
        "torchscript": "{lone!r} is a TorchScript file without its export metadata 'lone.pt.json'",
        "onnx": "exported policy {lone!r} has no metadata 'lone.onnx.json' beside it",
    }
    for fmt, suffix in FORMATS.items():
        lone = tmp_path / f"lone{suffix}"
        shutil.copy(exported["hopper", fmt], lone)
        line = _one_line_error(("eval", lone))
        assert line.startswith("rlexp eval: " + wanted[fmt].format(lone=str(lone))), line


@pytest.mark.parametrize("normalize", [True, False])
def test_the_folded_normaliser_matches_the_policy_s_own(normalize):
    """Off (env.normalize_observations=false), observations reach the MLP untouched and unclipped,
    as in the policy; on, its statistics and clip act as they do there."""
    from torchrl.data import Bounded

    from conftest import compose
    from rlexp.config.validate import to_root_config
    from rlexp.deploy.export import DeterministicActor
    from rlexp.policies.actor_critic import make_policy

    config = to_root_config(compose(["env=hopper"]))
    spec = Bounded(-1.0, 1.0, (1, 3))
    policy = make_policy(config.policy, 5, 3, spec, normalize, clip_observations=2.0)
    policy.normalizer.update(torch.randn(64, 5) * 4.0 + 1.0)
    obs = torch.randn(32, 5) * 20.0
    want = torch.clamp(policy.sampling_policy(deterministic=True).sample(obs)[2], -1.0, 1.0)
    actor = DeterministicActor(policy, spec.space.low[0], spec.space.high[0], clamp_actions=True)
    scripted = torch.jit.script(actor)
    torch.testing.assert_close(scripted(obs), want, atol=0, rtol=0)
    if not normalize:  # the policy clips nothing either: large inputs reach the MLP as they are
        assert not torch.equal(actor(obs), actor(torch.clamp(obs, -2.0, 2.0)))


def test_eval_video_wants_an_mp4_name(exported, tmp_path):
    line = _one_line_error(
        ("eval", exported["cart_pole", "torchscript"], "--video", tmp_path / "v.gif")
    )
    assert (
        line == f"rlexp eval: --video {str(tmp_path / 'v.gif')!r}: give a file name ending in .mp4"
    )
