"""``python train.py --config-json FILE ...`` in a subprocess, on tiny budgets: the users' files run
unchanged, overrides apply on top, ``-m`` sweeps from a JSON base, bad files exit 2 with one line."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from conftest import REPO, SHARED, only_run_dir, run_train
from rlexp.config.json_format import load_json_experiment
from rlexp.config.validate import to_dict, to_root_config
from rlexp.launch.json_entry import compose_json_experiment

SEED = SHARED / "seed-configs"
EXAMPLES = REPO / "examples" / "json"


def seed_file(task: str) -> Path:
    """The users' real train file: the tests that run it unchanged fail, not skip, without it."""
    path = SEED / task / "train_config.json"
    if not path.is_file():
        pytest.fail(
            f"{path} is missing: these tests run our users' real experiment files; put the shared "
            "seed configs at ../shared/seed-configs"
        )
    return path


def example_copy(folder: Path, task: str = "cart_pole", **trainer) -> Path:
    """The ``task`` example pair copied into ``folder`` with ``trainer`` keys changed."""
    folder.mkdir(parents=True, exist_ok=True)
    train = json.loads((EXAMPLES / task / "train_config.json").read_text())
    train["trainer"].update(trainer)
    shutil.copy(EXAMPLES / task / "gym_config.json", folder / "gym_config.json")
    (folder / "train_config.json").write_text(json.dumps(train, indent=2))
    return folder / "train_config.json"


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
    run_train(["--config-json", str(seed_file(task)), *TINY_JSON, *extra, "seed=3"], cwd=tmp_path)
    run_dir = only_run_dir(tmp_path)
    log = (run_dir / "train.log").read_text()
    assert log.count("with task file") == 1 and "by base name" in log
    assert log.count("accepted but not applicable to the MuJoCo CPU rebuild") == 1
    if not torch.cuda.is_available():  # device "cuda:0" in the file: CPU with one warning
        assert log.count("CUDA is not available") == 1
    # one iteration of 2 envs x 16 steps: the checkpoint saved on exit is at step 32
    ckpts = sorted(p.name for p in (run_dir / "checkpoints").glob(f"{task}_ppo_step_*.pt"))
    assert ckpts == [f"{task}_ppo_step_000000032.pt"], ckpts
    ckpt = torch.load(run_dir / "checkpoints" / ckpts[0], map_location="cpu", weights_only=False)
    assert ckpt["global_step"] == 32
    assert ckpt["config"]["env"]["native"]["task"] == task and ckpt["config"]["seed"] == 3
    steps = [json.loads(line)["step"] for line in (run_dir / "metrics.jsonl").open()]
    assert steps and max(steps) == 32

    config = to_root_config(OmegaConf.to_container(OmegaConf.load(run_dir / "config.yaml")))
    assert config.seed == 3 and config.trainer.iterations == 1  # the overrides won
    assert (config.env.num_envs, config.trainer.frames_per_batch) == (2, 32)
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


def test_sweep_from_a_json_base(tmp_path):
    run_train(
        [
            "-m",
            "--config-json",
            str(EXAMPLES / "cart_pole" / "train_config.json"),
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


def test_strict_device_makes_cuda_on_a_cpu_machine_an_error(tmp_path):
    if torch.cuda.is_available():
        pytest.skip("CUDA is available here")
    proc = run_train(
        [
            "--config-json",
            str(example_copy(tmp_path / "files", device="cuda:0")),
            *TINY_JSON,
            "trainer.strict_device=true",
        ],
        cwd=tmp_path,
        check=False,
    )
    assert proc.returncode == 2
    assert "CUDA is not available" in proc.stdout + proc.stderr


@pytest.mark.parametrize("logger", [None, "logger=none"])
def test_use_wandb_and_logger_none_on_the_command_line(logger, tmp_path):
    """use_wandb: true in the file runs W&B (offline here); logger=none on the command line wins."""
    path = example_copy(tmp_path / "files", use_wandb=True, enable_eval=False)
    run_train(
        ["--config-json", str(path), *TINY_JSON, *([logger] if logger else [])],
        cwd=tmp_path / "files",
    )
    run_dir = only_run_dir(tmp_path / "files")
    config = to_root_config(OmegaConf.to_container(OmegaConf.load(run_dir / "config.yaml")))
    wandb_on = logger is None
    assert config.logger.wandb.enabled is wandb_on
    assert config.logger.tensorboard.enabled is wandb_on  # logger=none: no TensorBoard either
    assert (run_dir / "wandb").is_dir() is wandb_on
    assert (run_dir / "wandb_run_id.txt").is_file() is wandb_on
    assert (run_dir / "tensorboard").is_dir() is wandb_on
    written = json.loads((run_dir / "train_config.json").read_text())
    assert written["trainer"]["use_wandb"] is wandb_on


def test_a_path_in_the_file_is_taken_literally(tmp_path):
    """An eval-video save_path of "${oc.env:VAR}/videos" is a folder of that name under the working
    dir, not the folder the variable names: nothing is written outside."""
    outside = tmp_path / "outside"
    path = example_copy(tmp_path / "files")
    train = json.loads(path.read_text())
    params = train["trainer"]["events"]["eval"]["record_camera"]["params"]
    params["save_path"] = "${oc.env:RLEXP_TEST_OUT}/videos"
    path.write_text(json.dumps(train))
    work = tmp_path / "work"
    work.mkdir()
    run_train(
        ["--config-json", str(path), *TINY_JSON, *TINY_EVAL, "env.max_episode_steps=5"],
        cwd=work,
        env_extra={"RLEXP_TEST_OUT": str(outside)},
    )
    assert not outside.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["files", "work"]
    videos = list(work.rglob("*.mp4"))  # under the working dir or the run dir: both inside
    assert len(videos) == 1, videos
    assert videos[0].parent.parts[-2:] == ("${oc.env:RLEXP_TEST_OUT}", "videos")
    run_dir = only_run_dir(work)
    written = json.loads((run_dir / "train_config.json").read_text())
    video = written["trainer"]["events"]["eval"]["record_camera"]["params"]
    assert video["save_path"] == "${oc.env:RLEXP_TEST_OUT}/videos"
    assert str(outside) not in (run_dir / "train_config.json").read_text()
