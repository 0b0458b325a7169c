"""``python train.py --config-json FILE ...`` in a subprocess, on tiny budgets: the users' files run
unchanged, overrides apply on top, ``-m`` sweeps from a JSON base, bad files exit 2 with one line."""

from __future__ import annotations

import importlib.util
import json

import pytest
from omegaconf import OmegaConf

from conftest import SHARED, only_run_dir, run_train
from rlexp.config.json_format import load_json_experiment
from rlexp.config.validate import to_dict, to_root_config
from rlexp.launch.json_entry import compose_json_experiment

SEED = SHARED / "seed-configs"


def _native_ready() -> bool:
    try:
        from rlexp.envs.native import make_native_env  # noqa: F401
    except ImportError:
        return False
    return True


pytestmark = [
    pytest.mark.skipif(not SEED.is_dir(), reason=f"{SEED} (the shared seed configs) is not there"),
    pytest.mark.skipif(
        not _native_ready(), reason="rlexp.envs.native.make_native_env is not available yet"
    ),
]

#: A JSON run of a few seconds: one iteration of 2 envs x 16 steps, 10-step episodes.
TINY_JSON = [
    "trainer.iterations=1",
    "env.num_envs=2",
    "trainer.frames_per_batch=32",
    "algorithm.mini_batch_size=16",
    "algorithm.num_epochs=1",
    "env.max_episode_steps=10",
    "trainer.progress=false",
]
#: push_cube evaluates (16 eval envs x 3 episodes in the file): one episode on one env instead.
TINY_EVAL = ["env.num_eval_envs=1", "trainer.eval_episodes=1"]


@pytest.mark.parametrize("task", ["push_cube", "cart_pole"])
def test_shared_file_runs_unchanged_and_round_trips(task, tmp_path):
    extra = TINY_EVAL if task == "push_cube" else []
    proc = run_train(
        ["--config-json", str(SEED / task / "train_config.json"), *TINY_JSON, *extra, "seed=3"],
        cwd=tmp_path,
    )
    run_dir = only_run_dir(tmp_path)
    log = (run_dir / "train.log").read_text()
    assert log.count("with task file") == 1 and "by base name" in log
    assert log.count("accepted but not applicable to the MuJoCo CPU rebuild") == 1
    import torch

    if not torch.cuda.is_available():  # device "cuda:0" in the file: CPU with one warning
        assert log.count("CUDA is not available") == 1
    assert (run_dir / "checkpoints").is_dir()

    config = to_root_config(OmegaConf.to_container(OmegaConf.load(run_dir / "config.yaml")))
    assert config.seed == 3 and config.trainer.iterations == 1  # the overrides won
    assert config.trainer.exp_name == f"{task}_ppo"
    if not torch.cuda.is_available():
        assert config.trainer.device == "cpu"  # the saved config records the device used
    train = json.loads((run_dir / "train_config.json").read_text())
    assert train["trainer"]["device"] == config.trainer.device
    # the run dir's JSON pair loads back to the identical config (from any working dir)
    again = compose_json_experiment(
        load_json_experiment(run_dir / "train_config.json", cwd=tmp_path)
    )
    assert to_dict(again) == to_dict(config)  # (a composed logger node is typed LoggerGroupSchema)
    assert proc.returncode == 0


def test_sweep_from_a_json_base(tmp_path):
    run_train(
        [
            "-m",
            "--config-json",
            str(SEED / "cart_pole" / "train_config.json"),
            "seed=0,1",
            *TINY_JSON,
        ],
        cwd=tmp_path,
    )
    dirs = sorted(p.parent for p in tmp_path.glob("multirun/*/*/*/config.yaml"))
    assert len(dirs) == 2, dirs
    seeds = sorted(
        to_root_config(OmegaConf.to_container(OmegaConf.load(d / "config.yaml"))).seed for d in dirs
    )
    assert seeds == [0, 1]
    assert all((d / "train_config.json").is_file() for d in dirs)


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        (
            '{"trainer": {"gym_config": "gym_config.json",\n  "seed": 1,\n}}',
            "invalid JSON at line 3, column 1",
        ),
        (
            '{"trainer": {"gym_config": "gym_config.json", "iteratons": 3}}',
            "did you mean 'trainer.iterations'?",
        ),
    ],
)
def test_bad_file_on_the_command_line(text, expected, tmp_path):
    (tmp_path / "train_config.json").write_text(text)
    proc = run_train(
        ["--config", "train_config.json", "trainer.iterations=1"],
        cwd=tmp_path,
        check=False,
        timeout=120,
    )
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and expected in lines[0], proc.stderr
    assert not (tmp_path / "outputs").exists() and not (tmp_path / "multirun").exists()


@pytest.mark.skipif(importlib.util.find_spec("torch") is None, reason="torch missing")
def test_strict_device_makes_cuda_on_a_cpu_machine_an_error(tmp_path):
    import torch

    if torch.cuda.is_available():
        pytest.skip("CUDA is available here")
    proc = run_train(
        [
            "--config-json",
            str(SEED / "cart_pole" / "train_config.json"),
            *TINY_JSON,
            "trainer.strict_device=true",
        ],
        cwd=tmp_path,
        check=False,
    )
    assert proc.returncode == 2
    assert "CUDA is not available" in proc.stdout + proc.stderr
