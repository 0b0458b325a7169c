"""Shared test fixtures: Hydra composition of the real conf/, and the repository's paths."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("WANDB_MODE", "offline")

REPO = Path(__file__).resolve().parents[1]
CONF_DIR = REPO / "conf"
SHARED = REPO.parent / "shared"
sys.path.insert(0, str(REPO / "src"))


def compose(overrides: list[str] | None = None):
    """Compose conf/config.yaml with ``overrides`` exactly as ``python train.py`` would."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from rlexp.config.schema import register_configs

    register_configs()
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return hydra_compose(config_name="config", overrides=list(overrides or []))


def run_train(
    args: list[str],
    cwd: Path,
    timeout: float = 300,
    check: bool = True,
    env_extra: dict[str, str | None] | None = None,
    **kw,
) -> subprocess.CompletedProcess:
    """``python train.py ARGS`` in a subprocess, in ``cwd`` (``env_extra``: None removes a variable)."""
    env = {**os.environ, "PYTHONPATH": str(REPO / "src")}
    for key, value in (env_extra or {}).items():
        if value is None:
            env.pop(key, None)
        else:
            env[key] = value
    proc = subprocess.run(
        [sys.executable, str(REPO / "train.py"), *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=timeout,
        env=env,
        **kw,
    )
    if check and proc.returncode != 0:
        raise AssertionError(
            f"train.py {args} exited {proc.returncode}\nSTDOUT:\n{proc.stdout}\nSTDERR:\n{proc.stderr}"
        )
    return proc


def only_run_dir(root: Path) -> Path:
    """The single run dir Hydra created under ``root/outputs``."""
    dirs = [p.parent for p in root.glob("outputs/*/*/config.yaml")]
    assert len(dirs) == 1, f"expected one run dir under {root}/outputs, found {dirs}"
    return dirs[0]


#: Overrides that make a full training run take a few seconds.
TINY = [
    "env=inverted_pendulum",
    "trainer.total_frames=512",
    "trainer.frames_per_batch=256",
    "trainer.eval_every=256",
    "trainer.eval_episodes=2",
    "trainer.save_every=256",
    "algorithm.num_epochs=2",
]


#: A sweep job: TINY with one PPO epoch, 512 env steps in about a second.
SWEEP_TINY = [
    "env=inverted_pendulum",
    "trainer.total_frames=512",
    "trainer.frames_per_batch=256",
    "algorithm.num_epochs=1",
    "trainer.eval_every=256",
    "trainer.eval_episodes=2",
    "trainer.save_every=256",
]


#: Two iterations, a checkpoint after each, no evaluation: for tests about what a run dir holds.
SHORT = [
    "env=inverted_pendulum",
    "trainer.total_frames=512",
    "trainer.frames_per_batch=256",
    "trainer.save_every=256",
    "trainer.eval_every=0",
    "algorithm.num_epochs=1",
]


@pytest.fixture
def tiny_overrides() -> list[str]:
    return list(TINY)


def _compile_problem() -> str | None:
    import torch

    from rlexp.algorithms.ppo import compile_unavailable

    return compile_unavailable(torch.device("cpu"))


#: For tests that really run torch.compile: inductor needs a C++ compiler for CPU code.
needs_compiler = pytest.mark.skipif(
    _compile_problem() is not None, reason=f"torch.compile cannot run here: {_compile_problem()}"
)


#: PPO without the MuJoCo references' extras that rlexp turns on by default (reward scaling and
#: clipping, LR annealing): the plain update the hand-written references in the tests implement.
PLAIN_PPO = {"anneal_lr": False, "normalize_rewards": False, "clip_rewards": None}


def clipped_adam_step(params, grads, m, v, step: int, cfg, betas=(0.9, 0.999)) -> None:
    """A hand-written reference optimiser step: clip the gradients to ``cfg.max_grad_norm`` as
    ``clip_grad_norm_`` does, then Adam (bias-corrected, ``cfg.lr``, ``cfg.adam_eps``) in place;
    ``m`` / ``v``: the moment tensors, ``step``: 1 for the first step."""
    import torch

    beta1, beta2 = betas
    norm = torch.sqrt(sum(g.pow(2).sum() for g in grads))
    coef = min(1.0, cfg.max_grad_norm / (float(norm) + 1e-6))
    with torch.no_grad():
        for p, g, mi, vi in zip(params, grads, m, v, strict=True):
            g = g * coef
            mi.mul_(beta1).add_((1 - beta1) * g)
            vi.mul_(beta2).add_((1 - beta2) * g * g)
            m_hat = mi / (1 - beta1**step)
            v_hat = vi / (1 - beta2**step)
            p.sub_(cfg.lr * m_hat / (v_hat.sqrt() + cfg.adam_eps))
