"""The memory work of an image policy's update (issue #47 speed, docs/performance.md "CNN PPO"),
none of which may change a value:

- the rollout's images are made channels-last once per update, so every minibatch reaches the
  encoder already in that layout, and ``encoders.scaled`` casts and divides in one pass: the
  update equals, bit for bit, one that converts every minibatch and casts, then divides (the
  code before), on the fused step, TorchRL's ClipPPOLoss path and GRPO's fused step;
- GAE's next-observation test compares uint8 rows as 8-byte words: the same verdicts as a
  byte-by-byte comparison (numpy), also where the rows are not word-aligned;
- the training process keeps freed memory (glibc's ``mallopt``): a conv net's forward and backward
  stops faulting its pages in again at every step, unless the user set malloc's own options;
- the pre-check builds the policy without its orthogonal init (shapes only: no QR).
"""

from __future__ import annotations

import copy
import os
import subprocess
import sys

import numpy as np
import pytest
import torch
from image_envs import ImageReach
from torch._C._functorch import is_batchedtensor

import rlexp.algorithms.grpo as grpo_module
import rlexp.algorithms.ppo as ppo_module
import rlexp.common.observations as observations
import rlexp.policies.encoders as encoders
from conftest import REPO, compose
from rlexp.algorithms import make_algorithm
from rlexp.common import speedups
from rlexp.common.observations import equal_rows, next_is_following
from rlexp.config.validate import to_root_config
from rlexp.policies.actor_critic import policy_for_env
from rlexp.training.collector import RolloutCollector

pytestmark = pytest.mark.usefixtures("one_torch_thread")

N, T = 3, 16  # envs, steps per env
CL = torch.channels_last
#: a Nature-style CNN of other sizes than the default, on a 5 x 14 x 11 image beside the vector
ENCODER = [
    "policy.encoder.name=nature",
    "policy.encoder.channels=[6,8]",
    "policy.encoder.kernel_sizes=[3,2]",
    "policy.encoder.strides=[2,1]",
    "policy.encoder.features_dim=10",
]
PPO = ["policy=cnn", "policy.critic.hidden_sizes=[12]", "algorithm.clip_value=0.25"]
ALGORITHMS = {  # name -> overrides, and whether the update takes the fused step
    "ppo fused": ([*PPO, "algorithm.max_grad_norm=0.3"], True),
    "ppo clipppoloss": ([*PPO, "algorithm.max_grad_norm=0.3"], False),
    "grpo fused": (["algorithm=grpo", "algorithm.group_size=3", "policy=actor_only"], True),
}


def _setup(name: str, seed: int = 7):
    extra, fused = ALGORITHMS[name]
    config = to_root_config(
        compose(
            [
                "env=hopper",
                "env.backend=torchrl",
                "env.name=image_envs:make_image_env",
                f"env.num_envs={N}",
                *extra,
                *ENCODER,
                f"trainer.frames_per_batch={N * T}",
                "algorithm.mini_batch_size=10",
                "algorithm.num_epochs=3",
                "algorithm.compile=false",
                "algorithm.entropy_coeff=0.02",
                "algorithm.lr=3e-3",
            ]
        )
    )
    torch.manual_seed(seed)
    env = ImageReach(N, seed=seed, channels=5, height=14, width=11, max_len=9)
    policy = policy_for_env(config.policy, config.env, env)
    col = RolloutCollector(
        env, policy.sampling_policy(), frames_per_batch=N * T, total_frames=-1,
        trust_policy=True, auto_register_policy_transforms=False,
    )  # fmt: skip
    try:
        batch = next(iter(col))
    finally:
        col.shutdown()
    algo = make_algorithm(config.algorithm, policy, 4)
    algo.use_fused_step = fused
    return policy, algo, batch


def _reference_scaled(image: torch.Tensor) -> torch.Tensor:
    """``encoders.scaled`` before: every call made the images channels-last, then cast, then
    divided."""
    x = image.reshape(-1, *image.shape[-3:])
    if x.device.type == "cpu" and not is_batchedtensor(x):
        x = x.contiguous(memory_format=CL)
    return x.to(torch.float32) / 255.0


@pytest.fixture
def reference(monkeypatch):
    """The code before: minibatches converted one by one, byte-by-byte comparisons."""

    def use() -> None:
        monkeypatch.setattr(encoders, "scaled", _reference_scaled)
        monkeypatch.setattr(ppo_module, "channels_last_images", lambda data: data)
        monkeypatch.setattr(grpo_module, "channels_last_images", lambda data: data)
        monkeypatch.setattr(observations, "_rows", lambda x, dims: x.flatten(dims))

    return use


def test_scaled_casts_and_divides_every_byte_value_as_before():
    """All 256 values, from an NCHW and a channels-last tensor with two batch dims: the values,
    dtype and layout of the cast followed by the division."""
    values = torch.arange(256, dtype=torch.uint8).reshape(4, 1, 8, 8)
    image = torch.cat([values, values.flip(0)], 1).repeat(3, 1, 1, 1)  # [12, 2, 8, 8]
    for x in (image, image.contiguous(memory_format=CL)):
        got = encoders.scaled(x.reshape(3, 4, 2, 8, 8))
        want = _reference_scaled(x)
        assert got.dtype == torch.float32 and got.shape == (12, 2, 8, 8)
        assert got.is_contiguous(memory_format=CL)
        assert torch.equal(got, want)
    assert encoders.scaled(image)[5, 1, 3, 2] == float(image[5, 1, 3, 2]) / 255.0


@pytest.mark.parametrize("name", list(ALGORITHMS))
def test_every_minibatch_reaches_the_encoder_channels_last(name, monkeypatch):
    """The update's minibatch images are already channels-last when the encoder scales them (the
    rollout's images made so once per update, not every minibatch again)."""
    policy, algo, batch = _setup(name)
    layouts: list[bool] = []
    scaled = encoders.scaled

    def recording(image: torch.Tensor) -> torch.Tensor:
        if torch.is_grad_enabled():  # a loss's forward (GAE's critic pass runs without grad)
            flat = image.reshape(-1, *image.shape[-3:])
            layouts.append(flat.is_contiguous(memory_format=CL) and flat.shape[0] > 1)
        return scaled(image)

    monkeypatch.setattr(encoders, "scaled", recording)
    algo.update(batch)
    assert (algo.fused is not None) == ALGORITHMS[name][1]
    assert len(layouts) >= 3 * (N * T // 10), layouts  # every minibatch of every epoch
    assert all(layouts), f"{layouts.count(False)} of {len(layouts)} minibatches were NCHW"
    assert batch["observation", "pixels"].is_contiguous()  # the caller's rollout is untouched


@pytest.mark.parametrize("name", list(ALGORITHMS))
def test_the_update_equals_the_one_converting_every_minibatch_bit_for_bit(name, reference):
    """Two updates in a row (parameters, Adam's state and the logged statistics): the same bits as
    the code before these changes."""
    policy, algo, batch = _setup(name)
    old_policy = copy.deepcopy(policy)
    old_algo = make_algorithm(algo.cfg, old_policy, 4)
    old_algo.use_fused_step = algo.use_fused_step
    results = []
    for learner in (algo, old_algo):
        if learner is old_algo:
            reference()
        torch.manual_seed(3)
        results.append([learner.update(batch.clone()) for _ in range(2)])
    assert results[0] == results[1]
    moved = 0
    for (key, p), q in zip(policy.named_parameters(), old_policy.parameters(), strict=True):
        assert torch.equal(p, q), key
        moved += "encoders" in key
    assert moved
    for p, q in zip(algo.params, old_algo.params, strict=True):
        for k, v in algo.optimizer.state[p].items():
            assert torch.equal(v, old_algo.optimizer.state[q][k]), k


def _numpy_rows_equal(a: torch.Tensor, b: torch.Tensor, dims: int) -> np.ndarray:
    x, y = a.numpy(), b.numpy()
    rows = x.shape[:dims]
    out = np.empty(rows, dtype=bool)
    for i in np.ndindex(*rows):
        out[i] = np.array_equal(x[i], y[i])
    return out


@pytest.mark.parametrize("shape", [(4, 9, 3, 4, 2), (4, 9, 3, 3, 3), (5, 7, 1, 8)])
def test_rows_compared_as_words_give_the_byte_by_byte_verdicts(shape):
    """Rollouts [envs, T, ...] of uint8 frames whose rows are whole words (24 bytes), are not (27
    bytes: compared byte by byte), and of another rank; next = the following frame except where a
    single byte differs (first, last, inside a word): ``next_is_following`` as numpy compares."""
    g = torch.Generator().manual_seed(5)
    obs = torch.randint(0, 4, shape, dtype=torch.uint8, generator=g)
    nxt = torch.empty_like(obs)
    nxt[:, :-1] = obs[:, 1:]
    nxt[:, -1] = 7
    flat = nxt.view(shape[0], shape[1], -1)
    flat[0, 2, 0] += 1  # the first byte of a row
    flat[1, 4, -1] += 1  # its last byte
    flat[2, 5, flat.shape[-1] // 2 + 1] += 1  # one inside
    flat[3, 0] = flat[3, 0].flip(0) if not torch.equal(flat[3, 0], flat[3, 0].flip(0)) else 9
    got = next_is_following(obs, nxt, 2)
    want = _numpy_rows_equal(nxt[:, :-1], obs[:, 1:], 2)
    assert np.array_equal(got.numpy(), want)
    assert not want[0, 2] and not want[1, 4] and not want[2, 5] and want.sum() > 10
    assert np.array_equal(equal_rows(obs, obs.clone(), 2).numpy(), np.ones(shape[:2], bool))


def test_float_entries_keep_comparing_as_numbers():
    """A float vector is compared by value, as before (-0.0 equals 0.0, NaN equals nothing): only
    uint8 rows are seen as words."""
    a = torch.tensor([[[0.0, 1.5]], [[float("nan"), 2.0]]])  # [2, 1, 2]
    b = torch.tensor([[[-0.0, 1.5]], [[float("nan"), 2.0]]])
    assert equal_rows(a, b, 2).tolist() == [[True], [False]]


FAULTS = """
import resource, sys, torch
from torch import nn
torch.set_num_threads(1)
if sys.argv[1] == "keep":
    from rlexp.common.speedups import keep_freed_memory
    assert keep_freed_memory()
torch.manual_seed(0)
net = nn.Sequential(nn.Conv2d(4, 32, 8, 4), nn.ReLU(), nn.Conv2d(32, 64, 4, 2), nn.ReLU(),
                    nn.Flatten(), nn.Linear(64 * 9 * 9, 64))
x = torch.randint(0, 256, (128, 4, 84, 84), dtype=torch.uint8)
faults = []
for step in range(10):
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    net.zero_grad(set_to_none=True)
    net(x.float() / 255).sum().backward()
    faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
print(sum(faults[4:]))
"""


def _glibc() -> bool:
    try:
        return "glibc" in (os.confstr("CS_GNU_LIBC_VERSION") or "")
    except (ValueError, OSError, AttributeError):
        return False


@pytest.mark.skipif(not _glibc(), reason="glibc's malloc only")
def test_a_training_process_keeps_freed_memory_instead_of_faulting_it_in_again():
    """Steps 5-10 of a conv net's forward and backward (tens of MB freed and allocated again each
    step): page faults by the thousand with glibc's defaults, next to none once kept."""
    env = {**os.environ, "PYTHONPATH": str(REPO / "src")}
    env = {k: v for k, v in env.items() if not k.startswith("MALLOC_") and k != "GLIBC_TUNABLES"}
    counts = {}
    for mode in ("default", "keep"):
        out = subprocess.run(
            [sys.executable, "-c", FAULTS, mode], env=env, capture_output=True, text=True,
            timeout=120, check=True,
        )  # fmt: skip
        counts[mode] = int(out.stdout.split()[-1])
    if counts["default"] < 5000:
        pytest.skip(f"this machine's defaults fault little already ({counts})")
    assert counts["keep"] * 10 < counts["default"], counts


@pytest.mark.parametrize(
    "variable",
    [("MALLOC_TRIM_THRESHOLD_", "1000000"), ("GLIBC_TUNABLES", "glibc.malloc.trim_threshold=9")],
)
def test_a_users_own_malloc_settings_are_left_alone(variable, monkeypatch):
    monkeypatch.setenv(*variable)
    calls = []
    monkeypatch.setattr(speedups.ctypes, "CDLL", lambda *a: calls.append(a))
    assert speedups.keep_freed_memory() is False
    assert not calls


def test_the_precheck_builds_the_policy_without_its_orthogonal_init(monkeypatch):
    """``check_buildable`` needs the policy's shapes, not its weights: no orthogonal init (a QR
    per layer, ~0.1 s for the Nature CNN's Linear) though the config asks for it."""
    from rlexp.launch.checks import check_buildable

    config = to_root_config(compose(["env=hopper", "policy.ortho_init=true"]))

    def refuse(*args, **kwargs):
        raise AssertionError("orthogonal init in the pre-check")

    monkeypatch.setattr(torch.nn.init, "orthogonal_", refuse)
    check_buildable(config)
    assert config.policy.ortho_init  # the run itself still initialises orthogonally
