"""The training loop with image observations (issue #47, DESIGN47 §3): the observation is a
TensorDict of a float32 ``vector`` and uint8 ``pixels`` (tests/image_envs.py), the policy a CNN.

Rollouts keep the images uint8 and nothing makes a float copy of a rollout's images (a dispatch
mode records every float tensor torch creates); GAE's V(s') reuse against TorchRL's GAE with the
critic as its value network; the fused minibatch step against TorchRL's ClipPPOLoss; evaluation's
lean loop against TorchRL's; the events that touch observations; overlap's forked collection and a
checkpoint's pending rollout; and a SIGKILLed image run resumed bit for bit (best.pt included).
"""

from __future__ import annotations

import copy
import os
import signal
from pathlib import Path

import numpy as np
import pytest
import torch
from image_envs import ImageReach
from tensordict import TensorDict
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_flatten
from torchrl.envs import Compose, TransformedEnv

from conftest import REPO, compose, run_train
from rlexp.algorithms import make_algorithm
from rlexp.algorithms.ppo import make_gae
from rlexp.checkpoints.fields import FieldError, check_state
from rlexp.checkpoints.files import latest_checkpoint, load_checkpoint, save_checkpoint
from rlexp.common.observations import from_plain, to_plain
from rlexp.config.schema import AlgorithmConfig
from rlexp.config.validate import to_root_config
from rlexp.events.builtin import observation_noise, record_rollouts
from rlexp.events.manager import EventContext
from rlexp.policies.actor_critic import policy_for_env
from rlexp.training import overlap
from rlexp.training.collector import RolloutCollector, supports_fast_rollout
from rlexp.training.evaluation import run_episodes

TESTS = Path(__file__).resolve().parent
#: image_envs.py importable and allowed in the training process
ENV_VARS = {"PYTHONPATH": f"{REPO / 'src'}{os.pathsep}{TESTS}", "RLEXP_ENV_MODULES": "image_envs"}
#: a small Nature-style CNN (two convs) on the 3 x 12 x 10 image, beside the 4-value vector
POLICY = [
    "policy=cnn",
    "policy.encoder.channels=[6,8]",
    "policy.encoder.kernel_sizes=[3,3]",
    "policy.encoder.strides=[2,1]",
    "policy.encoder.features_dim=12",
    "policy.critic.hidden_sizes=[16]",
]
N, T, MB = 3, 16, 8  # envs, steps per env, minibatch rows
IMAGE = 3 * 12 * 10


def _config(*extra: str):
    return to_root_config(
        compose(
            [
                "env=hopper",
                "env.backend=torchrl",
                "env.name=image_envs:make_image_env",
                f"env.num_envs={N}",
                *POLICY,
                f"trainer.frames_per_batch={N * T}",
                f"algorithm.mini_batch_size={MB}",
                "algorithm.num_epochs=2",
                "algorithm.compile=false",
                "algorithm.entropy_coeff=0.01",
                *([] if "algorithm=grpo" in extra else ["algorithm.clip_value=0.3"]),
                *extra,
            ]
        )
    )


def _setup(seed: int = 3, *extra: str):
    config = _config(*extra)
    torch.manual_seed(seed)
    env = ImageReach(N, seed=seed)
    policy = policy_for_env(config.policy, config.env, env)
    return config, env, policy


def _rollout(env, policy, steps: int = T):
    col = RolloutCollector(
        env, policy.sampling_policy(), frames_per_batch=N * steps, total_frames=-1,
        trust_policy=True, auto_register_policy_transforms=False,
    )  # fmt: skip
    try:
        return next(iter(col)), col
    finally:
        col.shutdown()


class FloatTensors(TorchDispatchMode):
    """Records the largest floating-point tensor any torch operation returns while active."""

    def __init__(self) -> None:
        super().__init__()
        self.largest, self.op = 0, ""

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        out = func(*args, **(kwargs or {}))
        for t in tree_flatten(out)[0]:
            if isinstance(t, torch.Tensor) and t.is_floating_point() and t.numel() > self.largest:
                self.largest, self.op = t.numel(), str(func)
        return out


@pytest.mark.parametrize("loop", ["lean", "torchrl"])
def test_a_rollout_and_its_update_keep_images_uint8_and_never_make_a_float_copy(loop):
    """The rollout holds the images as uint8 (observation and next observation), and neither the
    collection, GAE nor the PPO update (both minibatch paths) nor the normaliser's update creates
    a float tensor as large as the rollout's images: the /255 happens per minibatch."""
    config, env, policy = _setup(4)
    if (
        loop == "torchrl"
    ):  # TorchRL's Collector (the fallback: any transform turns the lean loop off)
        env = TransformedEnv(env, Compose())
    assert supports_fast_rollout(env, policy.sampling_policy()) == (loop == "lean")
    algo = make_algorithm(config.algorithm, policy, 4)
    fused = copy.deepcopy(policy)
    fused_algo = make_algorithm(config.algorithm, fused, 4)
    algo.use_fused_step = False  # the TorchRL ClipPPOLoss path; fused_algo takes the fused step
    with FloatTensors() as seen:
        batch, _ = _rollout(env, policy)
        algo.update(batch.clone())
        fused_algo.update(batch.clone())
        policy.normalizer.update(batch["observation", "vector"])
    assert algo.fused is None and fused_algo.fused is not None
    for key in (("observation", "pixels"), ("next", "observation", "pixels")):
        assert batch[key].dtype == torch.uint8 and batch[key].shape == (N, T, 3, 12, 10), key
    assert batch["observation", "vector"].dtype == torch.float32
    rollout_images = N * T * IMAGE
    assert seen.largest <= MB * IMAGE < rollout_images, (
        f"{seen.op} made a float tensor of {seen.largest} values (a minibatch's images are "
        f"{MB * IMAGE}, the rollout's {rollout_images})"
    )


def test_gae_reuses_next_values_only_where_every_entry_of_the_observation_follows():
    """compute_advantages (V(s') taken from V(s_t+1) where the next observation is the following
    one) equals TorchRL's GAE evaluating V(s') itself with the critic; a next observation that
    differs from the following one in a single pixel (vector equal) is evaluated on its own."""
    config, env, policy = _setup(5)
    batch, _ = _rollout(env, policy)
    assert batch["next", "done"].any(), "episodes must end inside the rollout"
    policy.normalizer.update(batch["observation", "vector"])  # a non-trivial critic input
    # One pixel of one next observation changed (no reset there): not the following observation.
    t = int((~batch["next", "done"][1, :-1, 0]).nonzero()[2])
    batch["next", "observation", "pixels"][1, t, 2, 5, 7] += 99
    cfg = AlgorithmConfig(gamma=0.9, lmbda=0.8, mini_batch_size=5)
    mine = make_algorithm(cfg, policy, 1).compute_advantages(batch.clone())
    theirs = make_gae(cfg, policy.critic)(batch.clone())
    got, want = mine["next", "state_value"], theirs["next", "state_value"]
    assert got[1, t] != mine["state_value"][1, t + 1], "the changed pixel was not noticed"
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(mine["advantage"], theirs["advantage"], rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(mine["value_target"], theirs["value_target"], rtol=1e-5, atol=1e-5)


def test_the_fused_step_updates_a_cnn_policy_as_torchrl_clip_ppo_loss_does():
    """One PPO update (2 epochs of 6 minibatches, entropy, value clipping) through the fused step
    and through TorchRL's ClipPPOLoss: the same parameters, encoder included."""
    config, env, policy = _setup(6)
    batch, _ = _rollout(env, policy)
    other = copy.deepcopy(policy)
    a, b = make_algorithm(config.algorithm, policy, 4), make_algorithm(config.algorithm, other, 4)
    b.use_fused_step = False
    torch.manual_seed(11)
    out_a = a.update(batch.clone())
    torch.manual_seed(11)
    out_b = b.update(batch.clone())
    assert a.fused is not None and b.fused is None
    moved = 0
    for (name, p), q in zip(policy.named_parameters(), other.parameters(), strict=True):
        torch.testing.assert_close(p, q, rtol=1e-4, atol=1e-5, msg=name)
        moved += "encoders" in name
    assert moved, "no encoder parameter was compared"
    for key in ("loss/policy", "loss/value", "loss/entropy"):
        assert out_a[key] == pytest.approx(out_b[key], rel=1e-4, abs=1e-6), key


def test_evaluation_lean_loop_equals_torchrl_loop_with_images():
    """Deterministic episodes of a CNN policy: rlexp's lean loop and TorchRL's loop agree."""
    _, env, policy = _setup(7)
    results = []
    for lean in (True, False):
        env.set_seed(21)
        results.append(run_episodes(env, policy.sampling_policy(deterministic=True), 7, lean=lean))
    assert results[0] == results[1]
    assert results[0]["eval/episodes"] == 7


def test_observation_noise_touches_the_vector_only_and_record_rollouts_writes_uint8_images(
    tmp_path,
):
    pixels = torch.randint(0, 255, (2, 3, 4, 5), dtype=torch.uint8)
    vector = torch.tensor([[0.5, -1.0], [2.0, 3.0]])
    td = TensorDict(
        {"observation": TensorDict({"vector": vector, "pixels": pixels}, [2])}, batch_size=[2]
    )
    ctx = EventContext(tensordict=td, phase="observation", rng=np.random.default_rng(9))
    observation_noise(ctx, std=0.3, clip=0.4)
    want = vector + np.clip(np.random.default_rng(9).normal(0.0, 0.3, (2, 2)), -0.4, 0.4)
    torch.testing.assert_close(td["observation", "vector"], want.float())
    assert torch.equal(td["observation", "pixels"], pixels)

    _, env, policy = _setup(8)
    batch, _ = _rollout(env, policy, steps=4)
    ctx = EventContext(batch=batch, run_dir=tmp_path, global_step=12, event="record_rollouts")
    record_rollouts(ctx)
    data = np.load(tmp_path / "rollouts" / "step_000000012.npz")
    for name, key in (
        ("observation", "observation"),
        ("next_observation", ("next", "observation")),
    ):
        assert data[f"{name}.pixels"].dtype == np.uint8
        assert np.array_equal(data[f"{name}.pixels"], batch[key]["pixels"].numpy())
        assert np.array_equal(data[f"{name}.vector"], batch[key]["vector"].numpy())


def test_overlap_collects_images_in_the_child_and_a_checkpoint_holds_the_pending_rollout(tmp_path):
    """algorithm.overlap's forked collector hands image rollouts back uint8; the checkpoint's
    pending rollout and next observation (a dict of the vector and the image) load back as saved."""
    config, env, policy = _setup(9)
    sections = {"policy": policy.state_dict(),
                "algorithm": make_algorithm(config.algorithm, policy, 1).state_dict()}  # fmt: skip
    base = RolloutCollector(
        env, policy.sampling_policy(), frames_per_batch=N * 4, total_frames=-1,
        trust_policy=True, auto_register_policy_transforms=False,
    )  # fmt: skip
    col = overlap.OverlapCollector(base, policy, timeout_s=60)
    try:
        first = next(iter(col))
        col.start()
        pending = overlap.pending_rollout(col, None)
        obs = col.next_observation()
    finally:
        col.shutdown()
    assert first["observation", "pixels"].dtype == torch.uint8
    assert isinstance(obs, TensorDict) and obs["pixels"].dtype == torch.uint8
    state = {**sections, "pending_rollout": pending, "pending_observation": to_plain(obs)}
    path = save_checkpoint(tmp_path / "c.pt", state)
    loaded = torch.load(path, weights_only=True)  # plain tensors: the safe loader reads them
    check_state(loaded, 0, resume=False)
    back = overlap.unpack(loaded["pending_rollout"])
    assert back["next", "observation", "pixels"].dtype == torch.uint8
    assert (back == overlap.unpack(pending)).all()
    again = from_plain(loaded["pending_observation"])
    assert again.batch_size == (N,) and (again == obs).all()
    bad = {"vector": obs["vector"], "pixels": obs["pixels"].float()}
    with pytest.raises(FieldError, match="pending_observation\\['pixels'\\]"):
        check_state({**sections, "pending_observation": bad}, 0, resume=False)


def _train(args, cwd, **kw):
    return run_train(args, cwd=cwd, timeout=300, env_extra=ENV_VARS, **kw)


@pytest.mark.parametrize(
    "extra",
    [
        pytest.param([], id="lean-loop"),
        pytest.param(["events=noise", "~events.train.action_noise"], id="observation-noise"),
    ],
)
def test_sigkill_and_resume_of_an_image_run_is_bit_identical(tmp_path, extra):
    """train -> SIGKILL after the checkpoint at step 96 -> resume: the same parameters, optimiser
    state, windows, eval and best.pt as the uninterrupted run (the env's image noise generator,
    the uint8 next observation and, with observation noise, the event's RNG carried over)."""
    from test_resume import _kill_after_checkpoint, _same

    base = [
        "env=hopper", "env.backend=torchrl", "env.name=image_envs:make_image_env",
        "env.num_envs=3", "env.num_eval_envs=2", *POLICY, "trainer.total_frames=192",
        "trainer.frames_per_batch=48", "trainer.save_every=96", "trainer.eval_every=96",
        "trainer.eval_episodes=3", "algorithm.num_epochs=2", "algorithm.mini_batch_size=16",
        "algorithm.compile=false", "algorithm.entropy_coeff=0.01", "logger=none",
        "trainer.progress=false", "seed=13", *extra,
    ]  # fmt: skip
    whole, broken = tmp_path / "whole", tmp_path / "broken"
    _train([*base, f"hydra.run.dir={whole}"], tmp_path)
    _kill_after_checkpoint(
        [*base, f"hydra.run.dir={broken}"], tmp_path, broken / "checkpoints", 96,
        env_extra=ENV_VARS, sig=signal.SIGKILL,
    )  # fmt: skip
    proc = _train([*base, f"hydra.run.dir={broken}"], tmp_path)
    assert "[resume] continuing from" in proc.stdout + proc.stderr
    a = load_checkpoint(latest_checkpoint(whole / "checkpoints"))
    b = load_checkpoint(latest_checkpoint(broken / "checkpoints"))
    assert a["global_step"] == b["global_step"] == 192
    assert isinstance(a["pending_observation"], dict)
    assert a["pending_observation"]["pixels"].dtype == torch.uint8
    assert any("encoders" in k for k in a["policy"])
    for key, value in a["policy"].items():
        assert torch.equal(value, b["policy"][key]), f"policy.{key} differs after resume"
    assert _same(a["algorithm"], b["algorithm"]), "optimiser state differs after resume"
    assert _same(a["pending_observation"], b["pending_observation"])
    assert a["windows"]["returns"] == b["windows"]["returns"]
    assert a["last_eval"] and a["last_eval"] == b["last_eval"]
    assert _same(a["events"], b["events"])
    best_a, best_b = (load_checkpoint(d / "checkpoints" / "best.pt") for d in (whole, broken))
    assert best_a["global_step"] == best_b["global_step"]
    for key, value in best_a["policy"].items():
        assert torch.equal(value, best_b["policy"][key]), f"best.pt policy.{key} differs"


def test_the_eval_worker_evaluates_image_snapshots_as_the_training_process_does(tmp_path):
    """trainer.eval_async=true: the worker builds its own image env, receives each snapshot through
    its pipe and reports the same rounds as in-process evaluation (every logged eval, best.pt)."""
    import json

    base = [
        "env=hopper", "env.backend=torchrl", "env.name=image_envs:make_image_env",
        "env.num_envs=3", "env.num_eval_envs=2", *POLICY, "trainer.total_frames=144",
        "trainer.frames_per_batch=48", "trainer.save_every=0", "trainer.eval_every=48",
        "trainer.eval_episodes=3", "algorithm.num_epochs=2", "algorithm.mini_batch_size=16",
        "algorithm.compile=false", "logger=none", "logger.jsonl=true", "trainer.progress=false",
        "seed=17",
    ]  # fmt: skip
    evals = {}
    for mode in ("true", "false"):
        run = tmp_path / mode
        proc = _train([*base, f"trainer.eval_async={mode}", f"hydra.run.dir={run}"], tmp_path)
        assert ("eval worker started" in proc.stdout + proc.stderr) == (mode == "true")
        rows = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
        evals[mode] = [
            (r["step"], r["eval/episode_return"]) for r in rows if "eval/episode_return" in r
        ]
    assert [s for s, _ in evals["false"]] == [48, 96, 144]
    assert evals["true"] == evals["false"]


def test_the_nan_guard_checks_the_vector_of_an_image_rollout():
    """A NaN in a next observation's vector is named; uint8 images pass (always finite)."""
    from rlexp.algorithms.base import NonFiniteError
    from rlexp.runtime.distributed import DistInfo
    from rlexp.training.loop import check_rollout_finite

    _, env, policy = _setup(10)
    batch, _ = _rollout(env, policy, steps=3)
    check_rollout_finite(batch, DistInfo(), torch.device("cpu"), 9)
    batch["next", "observation", "vector"][2, 1, 3] = float("nan")
    with pytest.raises(NonFiniteError, match="next/observation from the env at step 9"):
        check_rollout_finite(batch, DistInfo(), torch.device("cpu"), 9)


def test_grpo_updates_a_cnn_policy_that_has_a_critic():
    """GRPO reads the actor only; with policy=cnn's critic beside it (no gradient there) the update
    takes the TensorDict path and leaves the critic as it was (the fused step would fail on the
    missing gradients)."""
    config, env, policy = _setup(11, "algorithm=grpo", "algorithm.group_size=3")
    batch, _ = _rollout(env, policy)
    critic_mlp = copy.deepcopy(policy.critic_net.mlp.state_dict())
    actor_before = copy.deepcopy(policy.actor_net.mlp.state_dict())
    algo = make_algorithm(config.algorithm, policy, 4)
    algo.update(batch)
    assert algo.fused is None
    for k, v in policy.critic_net.mlp.state_dict().items():
        assert torch.equal(v, critic_mlp[k]), k
    assert any(
        not torch.equal(v, actor_before[k]) for k, v in policy.actor_net.mlp.state_dict().items()
    )
