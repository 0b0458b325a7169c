"""Recurrent policies end to end: what refuses them (one line, exit 2, before the run dir) and what
runs them (every rlexp-stepped backend, --distributed)."""

from __future__ import annotations

import os
import re
import subprocess
import sys

import pytest

from conftest import REPO, compose, only_run_dir, run_train
from rlexp.config.validate import ConfigError, to_root_config

GRU = ["policy.memory.type=gru", "policy.memory.hidden_size=16", "algorithm.sequence_length=8"]
TINY_RUN = [
    "trainer.total_frames=512",
    "trainer.frames_per_batch=128",
    "trainer.eval_every=0",
    "trainer.save_every=0",
    "algorithm.num_epochs=1",
    "trainer.progress=false",
]


@pytest.mark.parametrize(
    "overrides,message",
    [
        (
            ["algorithm=grpo", "policy=actor_only", "env.num_envs=4"],
            "policy.memory.type=gru: algorithm=grpo trains feed-forward policies only",
        ),
        (
            ["env.backend=torchrl_gym"],
            "policy.memory.type=gru: env.backend='torchrl_gym' is stepped by TorchRL's generic loop",
        ),
        (["algorithm.overlap=true"], "policy.memory.type=gru: algorithm.overlap=true collects"),
        (["algorithm.compile=true"], "policy.memory.type=gru: algorithm.compile=true, but"),
        (["events=noise"], "policy.memory.type=gru: events.train.observation_noise fires at every step"),
    ],
    ids=["grpo", "torchrl_gym", "overlap", "compile", "step-events"],
)
def test_what_cannot_carry_the_state_is_refused_in_one_line(overrides, message):
    with pytest.raises(ConfigError) as err:
        to_root_config(compose(["env=inverted_pendulum", "policy.memory.type=gru", *overrides]))
    text = str(err.value)
    assert text.startswith(message), text
    assert "\n" not in text


def test_the_memory_settings_are_typed_and_ruled():
    config = to_root_config(compose(["policy.memory.type=lstm"]))
    m = config.policy.memory
    assert (m.type, m.hidden_size, m.num_layers, m.shared) == ("lstm", 256, 1, False)
    assert config.algorithm.sequence_length == 32
    for bad, text in [
        ("policy.memory.type=transformer", "policy.memory.type='transformer' must be one of"),
        ("policy.memory.hidden_size=0", "policy.memory.hidden_size=0 must be in [1, 65536]"),
        ("policy.memory.num_layers=0", "policy.memory.num_layers=0 must be in [1, 16]"),
        ("algorithm.sequence_length=0", "algorithm.sequence_length=0 must be in [1, 65536]"),
    ]:
        with pytest.raises(ConfigError) as err:
            to_root_config(compose([bad]))
        assert str(err.value).startswith(text), str(err.value)


def test_a_refused_run_exits_2_before_its_run_dir(tmp_path):
    proc = run_train(
        ["env=inverted_pendulum", "env.backend=torchrl_gym", *GRU], cwd=tmp_path, check=False
    )
    assert proc.returncode == 2, proc.stderr[-2000:]
    lines = [ln for ln in proc.stderr.splitlines() if "policy.memory.type=gru" in ln]
    assert len(lines) == 1 and "Traceback" not in proc.stderr
    assert not (tmp_path / "outputs").exists()


@pytest.mark.slow
@pytest.mark.parametrize(
    "backend",
    [
        ["env=inverted_pendulum", "env.backend=gymnasium_async", "env.num_envs=2"],
        ["env=inverted_pendulum", "env.backend=envpool", "env.num_envs=2"],
        ["env=cart_pole", "env.num_envs=4"],  # native
        ["env=hopper", "env.backend=vecenv", "env.name=batched_toy:make_vecenv", "env.num_envs=4"],
        ["env=hopper", "env.backend=torchrl", "env.name=batched_toy:make_torchrl_env"],
    ],
    ids=["gymnasium_async", "envpool", "native", "vecenv", "torchrl"],
)
def test_a_recurrent_policy_trains_on_every_rlexp_stepped_backend(tmp_path, backend):
    if "env.backend=envpool" in backend:
        pytest.importorskip("envpool")
    extra = {"PYTHONPATH": f"{REPO / 'src'}{os.pathsep}{REPO / 'tests'}"}
    extra["RLEXP_ENV_MODULES"] = "batched_toy"
    run_train([*backend, *GRU, *TINY_RUN], cwd=tmp_path, env_extra=extra)
    assert list((only_run_dir(tmp_path) / "checkpoints").glob("*_step_000000512.pt"))


@pytest.mark.slow
def test_distributed_ranks_train_a_recurrent_policy_in_step(tmp_path):
    """Two gloo ranks, each on its own envs and carried states; gradients averaged (the ranks end
    with the same parameters)."""
    env = {**os.environ, "PYTHONPATH": str(REPO / "src"), "OMP_NUM_THREADS": "1"}
    args = [
        "env=inverted_pendulum",
        "trainer.frames_per_batch=256",
        "trainer.total_frames=1024",
        "trainer.eval_every=0",
        "trainer.save_every=0",
        "algorithm.num_epochs=2",
        "seed=11",
        "policy.memory.type=lstm",
        "policy.memory.hidden_size=16",
        "algorithm.sequence_length=16",
    ]
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2"]
    proc = subprocess.run(
        [*cmd, str(REPO / "train.py"), "--distributed", *args],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-4000:]
    run_dir = only_run_dir(tmp_path)
    digests = [
        re.search(
            r"parameters identical on all 2 ranks \(sha256 (\w+)\)", (run_dir / n).read_text()
        )
        for n in ("train.log", "train_rank1.log")
    ]
    assert all(digests) and digests[0].group(1) == digests[1].group(1)
