"""``algorithm.compile``: when auto compiles, what true does without a compiler, bad values."""

from __future__ import annotations

import logging

import pytest
import torch
from torchrl.data import Bounded

from conftest import run_train
from rlexp.algorithms import ppo
from rlexp.algorithms.ppo import make_algorithm
from rlexp.config.schema import AlgorithmConfig, PolicyConfig
from rlexp.config.validate import ConfigError
from rlexp.policies.actor_critic import make_policy


def _algo(compile_choice: str, iterations: int, **kw):
    pol = make_policy(PolicyConfig(), 5, 2, Bounded(-1.0, 1.0, shape=(2,)))
    return make_algorithm(AlgorithmConfig(compile=compile_choice, **kw), pol, iterations)


def test_auto_compiles_long_runs_only(caplog):
    # Standard setting: 2048 frames per iteration, 10 epochs x 32 minibatches of 64.
    with caplog.at_level(logging.INFO, logger="rlexp.algorithms.ppo"):
        short = _algo("auto", iterations=50)  # ~100k env steps: ~18 s saved, not worth a compile
        short._decide_compile(updates=50 * 320, mb=64)
        assert not short.compiled and short._loss_fn is short.loss
        assert "eager loss" in caplog.text
        long = _algo("auto", iterations=489)  # 1M env steps: ~176 s saved
        long._decide_compile(updates=489 * 320, mb=64)
        assert long.compiled
    # Batched (minibatch 8192, 80 updates per iteration): the per-sample saving counts.
    batched = _algo("auto", iterations=92)  # the users' 6M-step PushCube run
    batched._decide_compile(updates=92 * 80, mb=8192)
    assert batched.compiled
    never = _algo("false", iterations=10_000)
    never._decide_compile(updates=10_000 * 320, mb=64)
    assert not never.compiled


def test_compile_true_without_a_compiler_fails_at_build_time_naming_the_key(monkeypatch):
    monkeypatch.setattr(ppo.shutil, "which", lambda name: None)
    with pytest.raises(ConfigError, match=r"algorithm\.compile=true.*C\+\+ compiler"):
        _algo("true", iterations=1)


def test_auto_without_a_compiler_warns_and_stays_eager(monkeypatch, caplog):
    monkeypatch.setattr(ppo.shutil, "which", lambda name: None)
    algo = _algo("auto", iterations=10_000)
    with caplog.at_level(logging.WARNING, logger="rlexp.algorithms.ppo"):
        algo._decide_compile(updates=10_000 * 320, mb=64)
    assert not algo.compiled and "no C++ compiler" in caplog.text


@pytest.mark.parametrize(
    ("value", "expected"),
    [
        ("True", "true"),
        ("FALSE", "false"),
        ("auto", "auto"),
        (" Auto ", "auto"),
        (True, "true"),
        (False, "false"),
    ],
)
def test_compile_accepts_booleans_and_words(value, expected):
    assert ppo.parse_compile(value) == expected


def test_a_bad_compile_value_is_a_config_error_on_the_command_line(tmp_path, tiny_overrides):
    proc = run_train([*tiny_overrides, "algorithm.compile=maybe"], cwd=tmp_path, check=False)
    assert proc.returncode == 2
    assert "algorithm.compile='maybe'" in proc.stdout + proc.stderr
    assert not list(tmp_path.rglob("checkpoints"))


def _minibatch(n: int = 16):
    from tensordict import TensorDict

    return TensorDict(
        {
            "observation": torch.randn(n, 5),
            "action": torch.rand(n, 2) * 2 - 1,
            "action_log_prob": torch.randn(n),
            "advantage": torch.randn(n, 1),
            "value_target": torch.randn(n, 1),
        },
        batch_size=[n],
    )


def _broken_compile(module, **kwargs):
    def call(*args, **kw):
        torch.rand(3)  # a backend that drew random numbers before it failed
        raise RuntimeError("inductor exploded")

    return call


def test_auto_falls_back_to_eager_when_compiling_fails(monkeypatch, caplog):
    monkeypatch.setattr(ppo.torch, "compile", _broken_compile)
    algo = _algo("auto", iterations=10_000)
    algo._decide_compile(updates=10_000 * 320, mb=64)
    mb = _minibatch()
    torch.manual_seed(3)
    with caplog.at_level(logging.WARNING, logger="rlexp.algorithms.ppo"):
        out = algo._loss_fn(mb)
    after = torch.rand(1)
    torch.manual_seed(3)
    assert torch.equal(after, torch.rand(1)), "the failed compile's random draws were not undone"
    assert "torch.compile failed" in caplog.text and "inductor exploded" in caplog.text
    assert not algo.compiled and algo._loss_fn is algo.loss
    torch.testing.assert_close(out["loss_objective"], algo.loss(mb)["loss_objective"])


def test_compile_true_does_not_hide_a_failing_compile(monkeypatch):
    monkeypatch.setattr(ppo.torch, "compile", _broken_compile)
    algo = _algo("true", iterations=1)
    algo._decide_compile(updates=1, mb=64)
    with pytest.raises(RuntimeError, match="inductor exploded"):
        algo._loss_fn(_minibatch())
