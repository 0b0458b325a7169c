"""The GPU path (#31), marked ``gpu``: deselected by default, run with ``make test-gpu`` (``pytest
-m gpu``) where CUDA exists; skipped without it.

- The batched toy env (``tests/batched_toy.py``) on ``env.device=cuda``, ``trainer.device=auto``:
  auto picks the env's GPU, rollout, GAE and update stay there; checkpoints, Ctrl-C + resume
  (bit-identical: the env's state comes back onto the GPU), ``rlexp eval``, ``rlexp export``
  (the file runs on the CPU and acts as the checkpoint).
- The TorchRL contract on the GPU, and the lean eval loop there against TorchRL's loop.
- ``trainer.device=auto`` keeps a CPU Gymnasium env with a 64x64 MLP on the CPU, and
  ``trainer.device=cuda`` with that env (policy on the GPU, env on the CPU) trains and evaluates.
"""

from __future__ import annotations

import json
import logging

import pytest
import torch
from test_batched_envs import (
    ENV_VARS,
    TORCHRL,
    VECENV,
    _eval_line,
    _export_acts_as_the_policy,
    _interrupt_after_first_checkpoint,
)

from conftest import compose, run_train
from rlexp.checkpoints.files import latest_checkpoint, load_checkpoint

pytestmark = [
    pytest.mark.gpu,
    pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device"),
]
ON_GPU = ["env.device=cuda", "trainer.device=auto"]


def _train_here(args: list[str], run_dir) -> None:
    from rlexp.app import train
    from rlexp.config.validate import to_root_config

    train(to_root_config(compose(args)), run_dir)


def test_vecenv_on_cuda_trains_resumes_exactly_evaluates_and_exports(
    tmp_path, children, monkeypatch, caplog
):
    monkeypatch.setenv("RLEXP_ENV_MODULES", "batched_toy")
    args = [*VECENV, *ON_GPU]
    with caplog.at_level(logging.INFO, logger="rlexp.training.build"):
        _train_here(args, tmp_path / "whole")
    assert "[device] trainer.device=auto -> cuda:0: the env steps on cuda:0" in caplog.text
    broken = tmp_path / "broken"
    _interrupt_after_first_checkpoint(
        children, [*args, f"hydra.run.dir={broken}"], tmp_path, broken
    )
    stopped = load_checkpoint(latest_checkpoint(broken / "checkpoints"))
    assert stopped["config"]["trainer"]["device"] == "cuda:0"  # the device used, recorded
    assert stopped["envs"]["train"]["on_device"], "the env's state was not on the GPU"
    proc = run_train([*args, f"hydra.run.dir={broken}"], cwd=tmp_path, env_extra=ENV_VARS)
    assert "[resume] training envs: restored (the env's get_state)" in proc.stdout + proc.stderr
    a = load_checkpoint(latest_checkpoint(tmp_path / "whole" / "checkpoints"))
    b = load_checkpoint(latest_checkpoint(broken / "checkpoints"))
    assert a["global_step"] == b["global_step"] == 8192
    for key, value in a["policy"].items():
        assert torch.equal(value, b["policy"][key]), f"policy.{key} differs after the resume"
    assert a["windows"]["returns"] == b["windows"]["returns"] and a["last_eval"] == b["last_eval"]
    _export_acts_as_the_policy(broken, [-1.0, -2.0], [1.0, 2.0], eval_tolerance=0.05)


def test_torchrl_env_on_cuda_trains_and_evaluates(tmp_path, monkeypatch):
    monkeypatch.setenv("RLEXP_ENV_MODULES", "batched_toy")
    _train_here([*TORCHRL, *ON_GPU, "trainer.total_frames=1024"], tmp_path / "run")
    status = json.loads((tmp_path / "run" / "status.json").read_text())
    assert status["state"] == "finished" and status["global_step"] == 1024
    _eval_line(tmp_path / "run")


@pytest.mark.parametrize("backend", ["vecenv", "torchrl"])
def test_the_lean_eval_loop_on_the_gpu_equals_torchrl_s(backend):
    """Rewards read back in chunks (no host round trip per step): the same episodes, the same
    numbers as TorchRL's step-by-step loop."""
    from batched_toy import ToyTorchRLEnv, ToyVecEnv

    from rlexp.config.schema import EnvConfig, PolicyConfig
    from rlexp.envs.torchrl_env import TorchRLAdapter
    from rlexp.envs.vecenv import VecEnvAdapter
    from rlexp.policies.actor_critic import policy_for_env
    from rlexp.training.evaluation import run_episodes

    def env_and_policy():
        if backend == "vecenv":
            env = VecEnvAdapter(ToyVecEnv(3, "cuda", seed=2), "toy")
        else:
            env = TorchRLAdapter(ToyTorchRLEnv(3, "cuda", seed=2), "toy")
        torch.manual_seed(0)
        policy = policy_for_env(PolicyConfig(), EnvConfig(normalize_observations=False), env)
        return env, policy.cuda().sampling_policy(deterministic=True)

    results = []
    for lean in (True, False):
        env, policy = env_and_policy()
        env.set_seed(7)
        results.append(run_episodes(env, policy, 7, lean=lean))
    assert results[0] == results[1] and results[0]["eval/episodes"] == 7


def test_auto_keeps_a_cpu_gymnasium_env_with_a_small_mlp_on_the_cpu(tmp_path, caplog):
    tiny = ["env=gym_cartpole", "trainer.total_frames=256", "trainer.frames_per_batch=128",
            "trainer.eval_every=0", "algorithm.num_epochs=1", "trainer.progress=false"]  # fmt: skip
    with caplog.at_level(logging.INFO, logger="rlexp.training.build"):
        _train_here([*tiny, "trainer.device=auto"], tmp_path / "auto")
    assert "[device] trainer.device=auto -> cpu: a CPU env and a small MLP" in caplog.text
    saved = load_checkpoint(latest_checkpoint(tmp_path / "auto" / "checkpoints"))
    assert saved["config"]["trainer"]["device"] == "cpu"
    # policy on the GPU, env on the CPU: one copy each way per step, the update on the GPU
    _train_here([*tiny, "trainer.device=cuda", "trainer.eval_every=128"], tmp_path / "cuda")
    status = json.loads((tmp_path / "cuda" / "status.json").read_text())
    assert status["state"] == "finished" and status["global_step"] == 256
    assert load_checkpoint(latest_checkpoint(tmp_path / "cuda" / "checkpoints"))["last_eval"]
    _eval_line(tmp_path / "cuda")
