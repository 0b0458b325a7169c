"""Action masking (issue #48): the masked distribution against hand-computed numbers, no invalid
action ever sampled or chosen, the update's log-probabilities the collection's, KL over valid
actions only, every backend's masks alike, one-line refusals, and a task that learns with masks
and fails without."""

from __future__ import annotations

import json
import math
import os
import pickle
import subprocess
import sys
import textwrap
from pathlib import Path

import mask_envs  # noqa: F401  (registers the MaskedMulti / MaskedBits / MaskedBox envs)
import numpy as np
import pytest
import torch
from tensordict import TensorDict

from conftest import only_run_dir, run_train
from rlexp.config.schema import AlgorithmConfig, EnvConfig, PolicyConfig
from rlexp.envs.factory import make_env
from rlexp.policies.actor_critic import policy_for_env

NVEC = (3, 4)


def _env(name: str = "mask_envs:MaskedMulti-v0", n: int = 2, **cfg):
    return make_env(EnvConfig(name=name, **cfg), n, seed=3)


def _policy_with_logits(logits: list[float]):
    """A policy for MaskedMulti-v0 whose actor gives ``logits`` whatever it observes."""
    env = _env()
    pol = policy_for_env(PolicyConfig(), EnvConfig(), env)
    env.close()
    last = pol.actor_net.mlp[-1]
    with torch.no_grad():
        last.weight.zero_()
        last.bias.copy_(torch.tensor(logits))
    return pol


def _obs(mask: torch.Tensor) -> TensorDict:
    rows = mask.shape[0]
    return TensorDict(
        {"vector": torch.randn(rows, 2), "action_mask": mask.bool()}, batch_size=[rows]
    )


def test_the_env_gives_the_mask_as_the_observations_bool_entry_not_in_the_vector():
    env = _env(n=3)
    assert env.obs_layout.mask.source == "observation"
    assert [p.key for p in env.obs_layout.parts] == ["pos"]  # the mask key is not a policy input
    obs = env.reset()["observation"]
    assert obs.get("vector").shape == (3, 2)
    assert obs.get("action_mask").dtype == torch.bool and obs.get("action_mask").shape == (3, 7)
    env.close()


def test_masked_distribution_equals_hand_computed_probabilities_entropy_and_log_prob():
    """MultiDiscrete([3, 4]): component 0 with values {0, 2} valid, component 1 with only value 2
    valid; its highest logits on invalid values."""
    logits = [0.5, 2.0, -1.0, 3.0, 0.2, -0.7, 1.5]
    pol = _policy_with_logits(logits)
    mask = torch.tensor([[1, 0, 1, 0, 0, 1, 0]])
    dist = pol.actor.get_dist(TensorDict({"observation": _obs(mask)}, batch_size=[1]))
    p0 = math.exp(0.5) / (math.exp(0.5) + math.exp(-1.0))  # 0.8175744761936437
    p2 = 1.0 - p0
    entropy = -(p0 * math.log(p0) + p2 * math.log(p2))  # component 1 is certain: 0
    actions = torch.tensor([[0, 2], [2, 2], [1, 2], [0, 0], [2, 3]])
    log_prob = dist.log_prob(actions)
    torch.testing.assert_close(log_prob[0], torch.tensor(math.log(p0)))
    torch.testing.assert_close(log_prob[1], torch.tensor(math.log(p2)))
    assert torch.all(log_prob[2:].exp() == 0)  # an invalid value in either component
    torch.testing.assert_close(dist.entropy(), torch.tensor([entropy]))
    assert torch.isfinite(dist.entropy()).all()
    probs = [p.probs[0] for p in dist._parts]
    torch.testing.assert_close(probs[0], torch.tensor([p0, 0.0, p2]))
    assert torch.equal(probs[1], torch.tensor([0.0, 0.0, 1.0, 0.0]))
    assert dist.mode.tolist() == [[0, 2]]
    # TorchRL's MaskedCategorical (the reference the issue names) agrees per component
    from torchrl.modules import MaskedCategorical

    blocks = torch.tensor([logits, logits]).split(NVEC, -1)
    masks = mask.bool().expand(2, 7).split(NVEC, -1)
    ref = [MaskedCategorical(logits=b, mask=m) for b, m in zip(blocks, masks, strict=True)]
    torch.testing.assert_close(dist.entropy(), sum(r.entropy() for r in ref)[:1])
    torch.testing.assert_close(
        log_prob[:2], sum(r.log_prob(actions[:2, i]) for i, r in enumerate(ref))
    )
    # the collection sampler scores its draws as the loss's distribution does
    torch.manual_seed(0)
    obs = _obs(mask.expand(4000, 7))
    _, action, lp = pol.sampling_policy().sample(obs)
    full = pol.actor.get_dist(TensorDict({"observation": obs}, batch_size=[4000]))
    torch.testing.assert_close(lp, full.log_prob(action))
    assert set(action[:, 1].tolist()) == {2}
    freq = (action[:, 0] == 0).double().mean().item()
    assert abs(freq - p0) < 0.03 and not (action[:, 0] == 1).any()


def test_entropy_and_gradients_stay_finite_with_a_single_valid_action_everywhere():
    pol = _policy_with_logits([1.0, -2.0, 0.3, 4.0, -1.0, 2.0, 0.0])
    mask = torch.tensor([[0, 1, 0, 0, 0, 0, 1]])
    dist = pol.actor.get_dist(TensorDict({"observation": _obs(mask)}, batch_size=[1]))
    loss = dist.entropy().sum() + dist.log_prob(torch.tensor([[1, 3]])).sum()
    loss.backward()
    assert dist.entropy().item() == 0.0
    assert all(torch.isfinite(p.grad).all() for p in pol.parameters() if p.grad is not None)


def test_no_invalid_action_is_ever_sampled_or_chosen_by_argmax():
    """Random masks (a single valid value often), logits favouring invalid values by far."""
    torch.manual_seed(1)
    pol = _policy_with_logits([9.0, 8.0, 7.0, 9.0, 8.0, 7.0, 6.0])
    rows = 20000
    mask = torch.rand(rows, 7) < 0.4
    mask[torch.arange(rows), torch.randint(0, 3, (rows,))] = True
    mask[torch.arange(rows), 3 + torch.randint(0, 4, (rows,))] = True
    mask[: rows // 2, 0] = False  # the best logit of component 0 never valid in half the rows
    mask[: rows // 2, 1:3] = torch.tensor([False, True])
    obs = _obs(mask)

    def valid(action: torch.Tensor) -> bool:
        return bool(
            mask[torch.arange(rows), action[:, 0]].all()
            and mask[torch.arange(rows), 3 + action[:, 1]].all()
        )

    with torch.no_grad():
        for deterministic in (False, True):
            action = pol.sampling_policy(deterministic).sample(obs)[1]
            assert valid(action), f"deterministic={deterministic}"
        dist = pol.actor.get_dist(TensorDict({"observation": obs}, batch_size=[rows]))
        assert valid(dist.sample()) and valid(dist.mode)


def test_kl_sums_over_valid_actions_only():
    """KL(behaviour || current) of two masked policies: invalid logits differ wildly and do not
    count; hand-computed over the valid values."""
    old_logits = [0.0, 50.0, 1.0, -30.0, 0.5, 0.0, 20.0]
    new_logits = [1.0, -40.0, 0.0, 10.0, 0.0, 1.5, -20.0]
    mask = torch.tensor([[1, 0, 1, 0, 1, 1, 0]])
    old = _policy_with_logits(old_logits)
    new = _policy_with_logits(new_logits)
    obs = _obs(mask)
    behaviour = {"logits": old.actor_net(obs).detach()}
    kl = new.actor_net.kl(behaviour, obs)

    def softmax(xs):
        z = sum(math.exp(x) for x in xs)
        return [math.exp(x) / z for x in xs]

    want = 0.0
    for o, n in (((0.0, 1.0), (1.0, 0.0)), ((0.5, 0.0), (0.0, 1.5))):
        p, q = softmax(o), softmax(n)
        want += sum(pi * math.log(pi / qi) for pi, qi in zip(p, q, strict=True))
    torch.testing.assert_close(kl, torch.tensor(want))


@pytest.mark.parametrize("fused", [True, False])
def test_collection_log_probs_are_the_updates_and_no_invalid_action_reaches_the_env(fused):
    """A masked rollout of the lean collector (mask from info): each stored action valid under its
    stored mask, its log-probability the loss distribution's on the stored observation; the PPO
    update (fused step or TorchRL's ClipPPOLoss) on it finite."""
    from rlexp.algorithms.ppo import make_algorithm
    from rlexp.training.collector import RolloutCollector

    torch.manual_seed(0)
    env = _env(n=4, kwargs={"mask_in": "info"})
    assert env.obs_layout.mask.source == "info"
    pol = policy_for_env(PolicyConfig(), EnvConfig(), env)
    col = RolloutCollector(env, pol.sampling_policy(), frames_per_batch=4 * 64, total_frames=-1,
                           trust_policy=True, track_traj_ids=False)  # fmt: skip
    batch = next(iter(col))
    mask = batch["observation", "action_mask"]
    assert mask.dtype == torch.bool and mask.shape == (4, 64, 7)
    a = batch["action"]
    assert torch.gather(mask[..., :3], -1, a[..., :1]).all()
    assert torch.gather(mask[..., 3:], -1, a[..., 1:]).all()
    assert sum(e.unwrapped.invalid for e in env._envs) == 0
    with torch.no_grad():
        dist = pol.actor.get_dist(batch.select("observation"))
    torch.testing.assert_close(dist.log_prob(a), batch["action_log_prob"])
    cfg = AlgorithmConfig(num_epochs=2, mini_batch_size=64, entropy_coeff=0.03, lr=3e-3)
    algo = make_algorithm(cfg, pol, total_iterations=10)
    algo.use_fused_step = fused
    stats = algo.update(batch)
    assert (algo.fused is not None) == fused
    assert all(math.isfinite(v) for v in stats.values()), stats
    col.shutdown()
    # GRPO (actor only, a KL term to the reference policy: over valid values only) likewise
    from rlexp.algorithms import make_algorithm as make_any
    from rlexp.config.schema import ActorOnlyConfig, GRPOConfig

    actor_only = policy_for_env(ActorOnlyConfig(), EnvConfig(), env)
    actor_only.actor_net.load_state_dict(pol.actor_net.state_dict())
    grpo = make_any(
        GRPOConfig(num_epochs=2, mini_batch_size=64, kl_coeff=0.1, group_size=2, lr=3e-3),
        actor_only,
        total_iterations=10,
    )
    grpo.use_fused_step = fused
    stats = grpo.update(batch.exclude("state_value", "advantage", "value_target"))
    assert (grpo.fused is not None) == fused
    assert all(math.isfinite(v) for v in stats.values()), stats


def test_multibinary_mask_from_info_in_process_and_in_async_workers_alike():
    """MultiBinary(3): the mask's pairs; the async workers give what the in-process env gives."""
    from rlexp.policies.actor_critic import policy_for_env as build

    envs = [_env("mask_envs:MaskedBits-v0", 2, backend=b) for b in ("gymnasium", "gymnasium_async")]
    try:
        pol = build(PolicyConfig(), EnvConfig(), envs[0])
        assert pol.nvec == (2, 2, 2)
        obs = [e.reset()["observation"] for e in envs]
        sample = pol.sampling_policy(deterministic=True).sampler()
        for _ in range(12):
            assert torch.equal(obs[0].get("action_mask"), obs[1].get("action_mask"))
            assert (obs[0].get("action_mask").reshape(2, 3, 2).sum(-1) >= 1).all()
            action = sample(obs[0])[-2]
            outs = [e.step_tensors(action) for e in envs]
            assert not outs[0]["terminated"].any()  # never an invalid bit
            obs = [e.autoreset_observation(o) for e, o in zip(envs, outs, strict=True)]
    finally:
        for e in envs:
            e.close()


@pytest.mark.parametrize(
    ("cfg", "message"),
    [
        (
            {"name": "mask_envs:MaskedBox-v0", "action_mask": "info"},
            "env.action_mask=info masks categorical actions; the action space is a Box",
        ),
        (
            {"kwargs": {"width": 6}},
            "the action mask (observation key 'action_mask') has 6 entries; expected "
            "sum(nvec)=7 (nvec=[3, 4]",
        ),
        (
            {"kwargs": {"mask_in": "info", "width": 9}, "action_mask": "info"},
            "the action mask (info['action_mask']) has 9 entries; expected sum(nvec)=7",
        ),
        (
            {"kwargs": {"mask_in": "info"}, "action_mask": "info", "action_mask_key": "valid"},
            "env.action_mask=info reads info['valid']; the env's reset gives info keys "
            "['action_mask']",
        ),
        (
            {"action_mask": "observation", "action_mask_key": "valid"},
            "env.action_mask=observation reads the Dict observation key "
            "env.action_mask_key='valid'; the observation space has keys ['action_mask', 'pos']",
        ),
    ],
)
def test_masks_that_cannot_apply_are_refused_in_one_line(cfg, message):
    with pytest.raises(ValueError) as info:
        make_env(EnvConfig(**{"name": "mask_envs:MaskedMulti-v0", **cfg}), 1, seed=0)
    assert message in str(info.value) and "\n" not in str(info.value)


def test_a_component_with_no_valid_action_is_refused_and_auto_masks_nothing_on_a_box():
    from rlexp.envs.masks import MaskSpec, mask_encoder

    encode = mask_encoder(MaskSpec("info", "action_mask", NVEC), "env.name='x'")
    assert encode(np.array([0, 1, 0, 1, 0, 0, 0])).tolist() == [0, 1, 0, 1, 0, 0, 0]
    with pytest.raises(ValueError, match="allows no action of a component"):
        encode(np.array([1, 1, 1, 0, 0, 0, 0]))
    env = _env("mask_envs:MaskedBox-v0", 1)  # auto: a Box action space has no mask
    assert env.obs_layout.mask is None and not env.obs_layout.structured
    env.close()
    off = _env(n=1, action_mask="off")  # off: the key is an ordinary part of the observation
    assert off.obs_layout.mask is None and off.obs_dim == 2 + 7
    off.close()


def test_a_backend_without_masks_is_refused_before_the_run_dir(tmp_path):
    proc = run_train(
        ["env=pick_valid", "env.backend=envpool", "env.action_mask=info", "trainer=smoke"],
        cwd=tmp_path,
        check=False,
        timeout=120,
    )
    assert proc.returncode == 2
    lines = [x for x in proc.stderr.splitlines() if "env.action_mask=info" in x]
    assert lines and "does not read action masks" in lines[0]
    assert not list(tmp_path.rglob("metrics.jsonl"))


def _final_eval(tmp_path, extra: list[str], frames: int) -> float:
    tmp_path.mkdir()
    run_train(
        ["env=pick_valid", "trainer=smoke", f"trainer.total_frames={frames}",
         "trainer.eval_episodes=10", "trainer.progress=false", "seed=1", *extra],
        cwd=tmp_path,
        timeout=300,
    )  # fmt: skip
    rows = [
        json.loads(x) for x in (only_run_dir(tmp_path) / "metrics.jsonl").read_text().splitlines()
    ]
    return [r["eval/episode_return"] for r in rows if "eval/episode_return" in r][-1]


@pytest.mark.parametrize(
    ("frames", "eval_async", "masked_at_least", "unmasked_at_most"),
    [
        (8192, "true", 15.0, 2.0),  # seconds; the masked run evaluates in the eval worker
        pytest.param(49152, "false", 19.0, 2.0, marks=pytest.mark.slow),
    ],
)
def test_pick_valid_learns_with_masking_and_fails_without(
    tmp_path, frames, eval_async, masked_at_least, unmasked_at_most
):
    """PickValid-v0 (20 steps, best valid action +1, invalid -1 and the end): a random masked
    policy earns ~12, the best 20; unmasked episodes end at the first invalid action. The eval's
    argmax is over valid actions (in the eval worker, or in process)."""
    masked = _final_eval(tmp_path / "masked", [f"trainer.eval_async={eval_async}"], frames)
    unmasked = _final_eval(tmp_path / "off", ["env.action_mask=off"], frames)
    assert masked >= masked_at_least, (masked, unmasked)
    assert unmasked <= unmasked_at_most, (masked, unmasked)


_DEPLOY = textwrap.dedent(
    """
    import pickle, sys
    sys.path = [p for p in sys.path if not p.rstrip("/").endswith("/src")]  # (a checkout's src/)
    class NoRlexp:
        def find_spec(self, name, path=None, target=None):
            if name == "rlexp" or name.startswith("rlexp."):
                raise ModuleNotFoundError(f"No module named {name!r}")
    sys.meta_path.insert(0, NoRlexp())
    sys.path.insert(0, sys.argv[1])  # tests/: mask_envs
    sys.path.insert(0, "run/exported")
    import gymnasium as gym
    import mask_envs
    import numpy as np
    import torch
    import best_pt_obs
    policy = torch.jit.load("run/exported/best.pt")
    try:
        import onnxruntime as ort
        import best_onnx_obs
        session = ort.InferenceSession("run/exported/best.onnx", providers=["CPUExecutionProvider"])
    except ImportError:
        session = None
    env = gym.make("mask_envs:MaskedMulti-v0", mask_in=sys.argv[2])
    rows = []
    for seed in range(3):
        obs, info = env.reset(seed=seed)
        done = False
        while not done:
            xs = best_pt_obs.inputs(obs, info=info)
            y = policy(*[torch.from_numpy(x) for x in xs.values()]).numpy()
            if session is not None:
                z = session.run(["action"], best_onnx_obs.inputs(obs, info=info))[0]
                assert np.array_equal(y, z), (y, z)
            mask = xs["action_mask"]
            rows.append((xs, best_pt_obs.env_action(y[0])))
            obs, r, term, trunc, info = env.step(best_pt_obs.env_action(y[0]))
            done = term or trunc
    assert not any(m == "rlexp" or m.startswith("rlexp.") for m in sys.modules)
    pickle.dump((rows, env.unwrapped.invalid), open("rows.pkl", "wb"))
    """
)


@pytest.mark.parametrize("mask_in", ["observation", "info"])
def test_the_export_takes_the_mask_and_acts_as_the_policy_without_rlexp(tmp_path, mask_in):
    """A masked MultiDiscrete policy exported (TorchScript and ONNX): the file's action_mask input
    in the metadata; episodes stepped through the file and its helper without rlexp take the
    policy's own argmax over valid values, never an invalid one."""
    from conftest import rlexp_cli
    from rlexp.deploy.policy_eval import open_source, typed_config

    tests = Path(__file__).parent
    run = tmp_path / "run"
    run_train(
        ["env=gym", "env.name=mask_envs:MaskedMulti-v0", f"+env.kwargs.mask_in={mask_in}",
         "trainer=smoke", "trainer.total_frames=512", "trainer.frames_per_batch=256",
         "trainer.eval_every=256", "trainer.save_every=256", "trainer.eval_episodes=2",
         "trainer.progress=false", f"hydra.run.dir={run}"],
        cwd=tmp_path,
        env_extra={"PYTHONPATH": os.pathsep.join([str(tests.parent / "src"), str(tests)])},
    )  # fmt: skip
    for fmt in ("torchscript", "onnx"):
        rc, _, err = rlexp_cli("export", run, "--format", fmt, "--checkpoint", "best")
        assert rc == 0, err
    meta = json.loads((run / "exported" / "best.pt.json").read_text())
    assert meta["inputs"][-1] == {
        "name": "action_mask", "kind": "action_mask", "key": "action_mask", "dtype": "bool",
        "shape": ["batch", 7], "source": mask_in, "mask_key": "action_mask", "nvec": [3, 4],
    }  # fmt: skip
    (tmp_path / "deploy.py").write_text(_DEPLOY)
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    proc = subprocess.run(
        [sys.executable, "-I", "deploy.py", str(tests), mask_in],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stdout + proc.stderr
    rows, invalid = pickle.loads((tmp_path / "rows.pkl").read_bytes())
    assert invalid == 0 and len(rows) >= 3
    best = run / "checkpoints" / "best.pt"
    source = open_source(best)
    config = typed_config(source.config, str(best))
    built = make_env(config.env, 1, seed=0)
    try:
        policy = source.build(config, built)
        obs = TensorDict(
            {
                "vector": torch.from_numpy(np.concatenate([x["observation"] for x, _ in rows])),
                "action_mask": torch.from_numpy(
                    np.concatenate([x["action_mask"] for x, _ in rows])
                ),
            },
            batch_size=[len(rows)],
        )
        with torch.no_grad():
            want = policy(TensorDict({"observation": obs}, batch_size=[len(rows)]))["action"]
    finally:
        built.close()
    got = np.stack([np.asarray(a).reshape(-1) for _, a in rows])
    assert np.array_equal(got, want.numpy())


def test_a_mask_with_no_valid_value_mid_run_fails_the_run_in_one_line(tmp_path):
    tests = Path(__file__).parent
    proc = run_train(
        ["env=gym", "env.name=mask_envs:MaskedMulti-v0", "+env.kwargs.empty_after=40",
         "trainer=smoke", "trainer.total_frames=512", "trainer.frames_per_batch=256",
         "env.num_eval_envs=0", "trainer.progress=false", f"hydra.run.dir={tmp_path / 'run'}"],
        cwd=tmp_path,
        check=False,
        env_extra={"PYTHONPATH": os.pathsep.join([str(tests.parent / "src"), str(tests)])},
    )  # fmt: skip
    assert proc.returncode == 1, proc.stderr
    line = "the action mask (observation key 'action_mask') allows no action of a component"
    assert [x for x in (proc.stdout + proc.stderr).splitlines() if line in x]
    status = json.loads((tmp_path / "run" / "status.json").read_text())
    assert status["state"] == "failed"


def test_a_vecenv_mask_from_its_extras_is_used_in_collection_and_refused_when_wrong(monkeypatch):
    """env.backend=vecenv: extras["action_mask"] of get_observations() and step(); the lean
    collector's rollout never sends an invalid action; the wrong width is one line."""
    from rlexp.training.collector import RolloutCollector

    monkeypatch.setenv("RLEXP_ENV_MODULES", "mask_envs")
    torch.manual_seed(0)
    cfg = EnvConfig(name="mask_envs:make_masked_vecenv", backend="vecenv", num_envs=4)
    env = make_env(cfg, 4, seed=0)
    assert env.obs_layout.mask.source == "info" and env.obs_layout.mask.width == 7
    pol = policy_for_env(PolicyConfig(), cfg, env)
    col = RolloutCollector(env, pol.sampling_policy(), frames_per_batch=4 * 40, total_frames=-1,
                           trust_policy=True, track_traj_ids=False)  # fmt: skip
    batch = next(iter(col))
    assert batch["next", "done"].any()
    assert batch["observation", "action_mask"].dtype == torch.bool
    assert env.raw.invalid == 0
    with torch.no_grad():
        dist = pol.actor.get_dist(batch.select("observation"))
    torch.testing.assert_close(dist.log_prob(batch["action"]), batch["action_log_prob"])
    col.shutdown()
    off = make_env(EnvConfig(**{**cfg.__dict__, "action_mask": "off"}), 4, seed=0)
    assert off.obs_layout.mask is None
    with pytest.raises(ValueError) as info:
        make_env(EnvConfig(**{**cfg.__dict__, "kwargs": {"width": 6}}), 4, seed=0)
    assert "extras['action_mask'] is [4, 6]; the action mask is [num_envs=4, sum(nvec)=7]" in str(
        info.value
    )
