"""Your own environment (#28), end to end through ``train.py``: a non-MuJoCo Box env checkpoints and
resumes, discrete actions train (PPO and GRPO), a Dict-observation / MultiDiscrete env named by
``module:EnvId`` resumes exactly through its ``get_state`` / ``set_state``, unsupported spaces and
MuJoCo-only events are one line before anything is written, and an exported discrete policy acts as
the checkpoint's in a process without rlexp."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from test_resume import _kill_after_checkpoint

from conftest import REPO, run_train
from rlexp.checkpoints.files import latest_checkpoint, load_checkpoint

TESTS = Path(__file__).resolve().parent
#: toy_envs.py importable in the training process (``env.name=toy_envs:<Id>``)
PYPATH = {"PYTHONPATH": f"{REPO / 'src'}{os.pathsep}{TESTS}"}

SMALL = [
    "trainer.frames_per_batch=256",
    "trainer.eval_every=256",
    "trainer.eval_episodes=2",
    "trainer.save_every=256",
    "algorithm.num_epochs=2",
    "trainer.progress=false",
]


def _train(
    tmp_path: Path, run: str, args: list[str], **kw
) -> tuple[Path, subprocess.CompletedProcess]:
    run_dir = tmp_path / run
    proc = run_train(
        [*SMALL, f"hydra.run.dir={run_dir}", *args], cwd=tmp_path, env_extra=PYPATH, **kw
    )
    return run_dir, proc


def _metrics(run_dir: Path) -> list[dict]:
    return [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]


def test_pendulum_checkpoints_and_resumes_with_new_episodes(tmp_path):
    """The run that lost everything at its first checkpoint (a non-MuJoCo env has no MuJoCo state)."""
    args = ["env=hopper", "env.name=Pendulum-v1", "seed=7", "trainer.total_frames=512"]
    run_dir, _ = _train(tmp_path, "pend", args)
    status = json.loads((run_dir / "status.json").read_text())
    assert status["state"] == "finished" and status["global_step"] == 512
    ckpt = load_checkpoint(latest_checkpoint(run_dir / "checkpoints"))
    assert ckpt["envs"]["train"]["kind"] == "restart"
    assert ckpt["observation_layout"]["dim"] == 3
    _, proc = _train(tmp_path, "pend", [*args[:3], "trainer.total_frames=1024"])
    status = json.loads((run_dir / "status.json").read_text())
    assert status["state"] == "finished" and status["global_step"] == 1024
    # new episodes seeded (seed + 1,000,003 x env steps taken) mod 2**31: 7 + 1000003 * 512
    assert status["env_resume"].startswith("restarted (new episodes seeded 512001543:")
    assert "[resume] training envs: restarted" in proc.stdout + proc.stderr


@pytest.mark.parametrize("algorithm", ["ppo", "grpo"])
def test_cartpole_trains_and_evaluates_with_a_categorical_policy(tmp_path, algorithm):
    extra = (
        ["algorithm=grpo", "algorithm.group_size=2", "env.num_envs=4"]
        if algorithm == "grpo"
        else []
    )
    run_dir, _ = _train(
        tmp_path,
        algorithm,
        [
            "env=hopper",
            "env.name=CartPole-v1",
            "trainer.total_frames=1024",
            "seed=3",
            "algorithm.entropy_coeff=0.01",
            *extra,
        ],
    )
    rows = _metrics(run_dir)
    train = [r for r in rows if "loss/policy" in r]
    assert len(train) == 4 and all("loss/log_std" not in r for r in train)
    # the entropy H of a 2-way categorical is in (0, log 2]; the loss term is -0.01 H
    assert all(0.0 < r["loss/entropy"] <= 0.69315 + 1e-6 for r in train)
    assert all(r["loss/entropy_term"] == pytest.approx(-0.01 * r["loss/entropy"]) for r in train)
    evals = [r for r in rows if "eval/episode_return" in r]
    assert evals and all(1.0 <= r["eval/episode_return"] <= 500.0 for r in evals)
    out = subprocess.run(
        [sys.executable, "-m", "rlexp", "eval", str(run_dir), "--episodes", "3"],
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, **PYPATH},
    )
    assert out.returncode == 0, out.stderr
    assert "mean return" in out.stdout


def test_dict_observation_env_by_module_syntax_resumes_exactly_through_get_state(tmp_path):
    """toy_envs:DictGoal-v0: Dict observations (nested, a Discrete part), MultiDiscrete actions, an
    RNG drawn every step, 30-step episodes that straddle the checkpoints; killed after its first
    checkpoint and resumed, it ends bit-identical to the run that was never interrupted."""
    args = [
        "env=hopper",
        "env.name=toy_envs:DictGoal-v0",
        "env.num_envs=2",
        "trainer.total_frames=1024",
        "trainer.save_every=512",
        "trainer.eval_every=512",
        "seed=11",
    ]
    whole, _ = _train(tmp_path, "whole", args)
    broken = tmp_path / "broken"
    cmd = [*SMALL, f"hydra.run.dir={broken}", *args]
    _kill_after_checkpoint(cmd, tmp_path, broken / "checkpoints", 512, PYPATH)
    _, proc = _train(tmp_path, "broken", args)
    assert "[resume] training envs: restored (the env's get_state)" in proc.stdout + proc.stderr
    status = json.loads((broken / "status.json").read_text())
    assert status["env_resume"] == "restored (the env's get_state)"
    a = load_checkpoint(latest_checkpoint(whole / "checkpoints"))
    b = load_checkpoint(latest_checkpoint(broken / "checkpoints"))
    assert a["global_step"] == b["global_step"] == 1024
    assert a["observation_layout"]["parts"][0]["key"] == "phase"  # sorted: phase, pos, target/xy
    assert [p["key"] for p in a["observation_layout"]["parts"]] == ["phase", "pos", "target/xy"]
    assert a["envs"]["train"]["kind"] == "state"
    for key, value in a["policy"].items():
        assert torch.equal(value, b["policy"][key]), f"policy.{key} differs after resume"
    assert a["windows"]["returns"] == b["windows"]["returns"] and a["windows"]["returns"]
    assert a["last_eval"] == b["last_eval"] and a["last_eval"]


def test_an_unsupported_space_is_one_line_and_exit_2_before_the_run_dir(tmp_path):
    name = "toy_envs:ImageObs-v0"
    run_dir, proc = _train(tmp_path, "r", ["env=hopper", f"env.name={name}"], check=False)
    assert proc.returncode == 2, proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "is an image" in lines[0] and name in lines[0], proc.stderr
    assert "Traceback" not in proc.stderr and not run_dir.exists()


@pytest.mark.parametrize(
    ("name", "words"),
    [
        ("toy_envs:TextObs-v0", "observation space is Text"),
        ("toy_envs:TupleAction-v0", "action space is Tuple"),
        ("no_such_module:Env-v0", "module 'no_such_module' could not be imported"),
        ("toy_envs:Missing-v0", "was imported but did not register it"),
        ("toy_envs:BadState-v0", "get_state()['sim'] is a object; a checkpoint holds only plain"),
    ],
)
def test_what_cannot_run_is_one_line_at_the_config_check(name, words):
    """The check ``train.py`` runs before the run dir exists (the subprocess test above shows the
    exit code and the missing run dir for one of them)."""
    from conftest import compose
    from rlexp.config.validate import ConfigError, to_root_config
    from rlexp.launch.checks import check_buildable

    config = to_root_config(compose(["env=hopper", f"env.name={name}"]))
    with pytest.raises(ConfigError) as err:
        check_buildable(config)
    msg = str(err.value)
    assert "\n" not in msg and words in msg and name in msg


@pytest.mark.parametrize(
    ("events", "words"),
    [
        ("noise", "action_noise adds Gaussian noise to continuous (Box) actions"),
        ("domain_randomization", "env.name='CartPole-v1' has no MuJoCo model"),
    ],
)
def test_events_that_need_box_actions_or_mujoco_are_refused_at_config_check(
    tmp_path, events, words
):
    run_dir, proc = _train(
        tmp_path, "r", ["env=hopper", "env.name=CartPole-v1", f"events={events}"], check=False
    )
    assert proc.returncode == 2 and words in proc.stderr, proc.stderr
    assert not run_dir.exists()


def test_observation_noise_and_rollout_recording_work_on_a_discrete_env(tmp_path):
    import numpy as np

    base = ["env=hopper", "env.name=toy_envs:NoStateWalk-v0", "trainer.total_frames=512"]
    run_dir, _ = _train(tmp_path, "rec", [*base, "events=record_rollouts"])
    data = np.load(sorted((run_dir / "rollouts").glob("*.npz"))[0])
    # the policy's indices 0..2 (the env got them as -1..1: Discrete(3, start=-1) asserts it)
    assert data["action"].dtype == np.int64 and set(np.unique(data["action"])) <= {0, 1, 2}
    assert data["observation"].shape == (1, 256, 1) and len(np.unique(data["action"])) > 1
    noise = [
        "events=noise",
        "~events.train.action_noise",
        "events.train.observation_noise.params.std=0.5",
    ]
    run_dir, _ = _train(tmp_path, "noise", [*base, *noise])
    assert json.loads((run_dir / "status.json").read_text())["state"] == "finished"


EXPORT_PARITY = r"""
import json, sys
import numpy as np, torch
assert "rlexp" not in sys.modules
path, probe = sys.argv[1], np.load(sys.argv[2])
meta = json.load(open(path + ".json"))
net = torch.jit.load(path)
out = net(torch.from_numpy(probe)).numpy()
import onnxruntime as ort
onnx = ort.InferenceSession(sys.argv[3], providers=["CPUExecutionProvider"])
out2 = onnx.run(None, {"observation": probe})[0]
assert "rlexp" not in sys.modules
print(json.dumps({"torchscript": out.tolist(), "onnx": out2.tolist(),
                  "dtype": str(out.dtype), "space": meta["action_space"],
                  "layout": [p["key"] for p in meta["observation_layout"]["parts"]]}))
"""


def test_exported_discrete_policy_acts_as_the_checkpoint_without_rlexp(tmp_path):
    import numpy as np

    run_dir, _ = _train(
        tmp_path,
        "r",
        ["env=hopper", "env.name=toy_envs:DictGoal-v0", "trainer.total_frames=512", "seed=4"],
    )
    for fmt in ("torchscript", "onnx"):
        out = subprocess.run(
            [
                sys.executable,
                "-m",
                "rlexp",
                "export",
                str(run_dir),
                "--checkpoint",
                "best",
                "--format",
                fmt,
            ],  # fmt: skip
            capture_output=True,
            text=True,
            timeout=300,
            env={**os.environ, **PYPATH},
        )
        assert out.returncode == 0, out.stderr
    ckpt = load_checkpoint(run_dir / "checkpoints" / "best.pt")
    from torchrl.data import MultiCategorical

    from rlexp.config.schema import PolicyConfig
    from rlexp.policies.actor_critic import make_policy

    spec = MultiCategorical(nvec=[3, 3], shape=(2,))
    policy = make_policy(PolicyConfig(), 7, 2, spec, nvec=(3, 3))  # one-hot phase (3), pos, goal
    policy.load_state_dict(ckpt["policy"])
    gen = torch.Generator().manual_seed(0)
    probe = (torch.rand(64, 7, generator=gen) * 4).numpy().astype(np.float32)
    np.save(tmp_path / "probe.npy", probe)
    with torch.no_grad():
        want = policy.sampling_policy(deterministic=True).sample(torch.from_numpy(probe))[1]
    proc = subprocess.run(
        [
            sys.executable,
            "-c",
            EXPORT_PARITY,
            str(run_dir / "exported" / "best.pt"),
            str(tmp_path / "probe.npy"),
            str(run_dir / "exported" / "best.onnx"),
        ],
        capture_output=True,
        text=True,
        timeout=300,
        env={k: v for k, v in os.environ.items() if k != "PYTHONPATH"},
    )
    assert proc.returncode == 0, proc.stderr
    got = json.loads(proc.stdout)
    assert got["dtype"] == "int64" and got["layout"] == ["phase", "pos", "target/xy"]
    assert got["space"]["kind"] == "multi_discrete" and got["space"]["start"] == [0, 0]
    assert torch.equal(torch.tensor(got["torchscript"]), want)  # the env's values (start 0)
    assert torch.equal(torch.tensor(got["onnx"]), want)
    assert len(set(map(tuple, got["torchscript"]))) > 1, "a constant policy: vacuous comparison"


def test_rlexp_eval_of_an_exported_discrete_policy_with_start_equals_its_checkpoint(tmp_path):
    """Discrete(3, start=-1): the file outputs the env's values (-1..1), rlexp eval maps them back;
    the same episodes, the same mean return as the checkpoint's own policy."""
    run_dir, _ = _train(
        tmp_path,
        "r",
        ["env=hopper", "env.name=toy_envs:NoStateWalk-v0", "trainer.total_frames=512"],
    )

    def rlexp(*args: str, trust: bool = False) -> str:
        # an exported file's metadata imports a module:EnvId module only once the user allows it
        # (docs/envs.md, "Security: what a name may import")
        allow = {"RLEXP_ENV_MODULES": "toy_envs"} if trust else {}
        out = subprocess.run(
            [sys.executable, "-m", "rlexp", *args],
            capture_output=True,
            text=True,
            timeout=300,
            env={**os.environ, **PYPATH, **allow},
        )
        assert out.returncode == 0, out.stderr
        return out.stdout

    rlexp("export", str(run_dir), "--checkpoint", "best", "--format", "torchscript")
    meta = json.loads((run_dir / "exported" / "best.pt.json").read_text())
    assert meta["action_space"]["start"] == [-1] and meta["action_dtype"] == "int64"
    ret = re.compile(r"mean return (-?[\d.]+) \+- ([\d.]+) over 4 episodes")
    from_ckpt = ret.search(
        rlexp("eval", str(run_dir / "checkpoints" / "best.pt"), "--episodes", "4")
    )
    exported = str(run_dir / "exported" / "best.pt")
    from_file = ret.search(rlexp("eval", exported, "--episodes", "4", trust=True))
    assert from_ckpt and from_file and from_ckpt.groups() == from_file.groups()
