"""The PPO loss of a CNN policy whose actor and critic share the image encoder (issue #47 speed,
``policy.share_encoder``): the encoder runs once per minibatch and feeds both heads (SB3's and
CleanRL's shared-features network), in the fused step and in TorchRL's ClipPPOLoss path; the loss
and every parameter's gradient equal a plain-torch reference that runs the encoder once for the
actor and again for the critic (autograd sums the two uses' gradients either way).

Non-default settings: Nature and IMPALA encoders of other sizes, shared and separate encoders, a
grouped observation (a vector with a critic-only group, an image both read and a critic-only
image), hidden layers, value clipping, a Gaussian and a categorical head."""

from __future__ import annotations

import copy
import dataclasses
import math

import pytest
import torch
from tensordict import TensorDict
from torch.nn import functional as F
from torchrl.data import Bounded
from torchrl.data import MultiCategorical as MultiCategoricalSpec

from conftest import PLAIN_PPO, needs_compiler
from rlexp.algorithms.fused_step import MINIBATCH_KEYS, FusedPPOStep
from rlexp.algorithms.ppo import LOSS_KEYS, make_algorithm
from rlexp.config.schema import (
    AlgorithmConfig,
    EncoderConfig,
    GRPOConfig,
    MLPConfig,
    PolicyConfig,
)
from rlexp.envs.spaces import ObsLayout, ObsPart
from rlexp.policies.actor_critic import make_policy

pytestmark = pytest.mark.usefixtures("one_torch_thread")

#: vector [0:4] group policy, [4:6] group critic; "pixels" (both read it), "wrist" (critic only)
LAYOUT = ObsLayout(
    "Dict",
    (
        ObsPart("", "image", (3, 26, 22), -1, 0, image_key="pixels", source_layout="hwc"),
        ObsPart("proprio", "box", (4,), 0, 4),
        ObsPart("priv", "box", (2,), 4, 2, group="critic"),
        ObsPart("wrist", "image", (1, 20, 18), -1, 0, group="critic", image_key="wrist"),
    ),
    6,
)
ENCODERS = {
    "nature": EncoderConfig(
        name="nature", channels=[5, 7], kernel_sizes=[4, 3], strides=[2, 2], features_dim=9
    ),
    "impala": EncoderConfig(name="impala", channels=[4, 6], num_res_blocks=1, features_dim=11),
}
CLIP_EPS, ENT, CRITIC, CLIP_VALUE = 0.13, 0.02, 0.7, 0.2
SETTINGS = AlgorithmConfig(
    clip_epsilon=CLIP_EPS,
    entropy_coeff=ENT,
    critic_coeff=CRITIC,
    clip_value=CLIP_VALUE,
    loss_critic_type="l2",
    max_grad_norm=0.37,
    mini_batch_size=12,
    compile="false",
    **PLAIN_PPO,
)
N = 12


def _policy(encoder: str, share: bool, categorical: bool):
    torch.manual_seed(4)
    cfg = PolicyConfig(
        actor=MLPConfig(hidden_sizes=[10]),
        critic=MLPConfig(hidden_sizes=[8, 5]),
        encoder=ENCODERS[encoder],
        share_encoder=share,
        init_log_std=-0.3,
    )
    if categorical:
        spec = MultiCategoricalSpec(nvec=[3, 2], shape=(2,), dtype=torch.int64)
        pol = make_policy(cfg, 6, 2, spec, nvec=(3, 2), layout=LAYOUT)
    else:
        pol = make_policy(cfg, 6, 2, Bounded(-1.0, 1.0, shape=(2,)), layout=LAYOUT)
    g = torch.Generator().manual_seed(8)
    pol.normalizer.update(torch.randn(50, 6, generator=g) * 3 + 1)  # a non-trivial normaliser
    return pol


def _minibatch(pol) -> TensorDict:
    g = torch.Generator().manual_seed(5)
    obs = TensorDict(
        {
            "vector": torch.randn(N, 6, generator=g),
            "pixels": torch.randint(0, 256, (N, 3, 26, 22), dtype=torch.uint8, generator=g),
            "wrist": torch.randint(0, 256, (N, 1, 20, 18), dtype=torch.uint8, generator=g),
        },
        batch_size=[N],
    )
    with torch.no_grad():
        sampled = pol.sampling_policy().sample(obs)
    return TensorDict(
        {
            "observation": obs,
            "action": sampled[-2],
            "action_log_prob": sampled[-1] + 0.4 * torch.randn(N, generator=g),
            "advantage": torch.randn(N, 1, generator=g),
            "value_target": torch.randn(N, 1, generator=g),
            "state_value": torch.randn(N, 1, generator=g) * 0.3,
        },
        batch_size=[N],
    )


def _reference_loss(pol, mb: TensorDict) -> torch.Tensor:
    """PPO's clipped loss by hand, each network running its own encoder pass on the images."""
    obs = mb["observation"]
    norm = pol.normalizer(obs["vector"])
    actor_enc = pol.actor_net.inputs.encoders
    critic_enc = pol.critic_net.inputs.encoders
    actor_in = torch.cat([norm[:, :4], actor_enc["pixels"](obs["pixels"])], -1)
    critic_in = torch.cat(  # the encoder again, shared or not
        [norm, critic_enc["pixels"](obs["pixels"]), critic_enc["wrist"](obs["wrist"])], -1
    )
    out = pol.actor_net.mlp(actor_in)
    action = mb["action"]
    if pol.categorical:
        blocks = out.split([3, 2], -1)
        dists = [torch.distributions.Categorical(logits=b) for b in blocks]
        log_prob = sum(d.log_prob(action[:, i]) for i, d in enumerate(dists))
        entropy = sum(d.entropy() for d in dists)
    else:
        log_std = pol.actor_net.log_std.clamp(pol.actor_net.min_log_std, pol.actor_net.max_log_std)
        scale = log_std.exp().expand_as(out)
        log_prob = (
            -((action - out) ** 2) / (2 * scale**2) - scale.log() - math.log(math.sqrt(2 * math.pi))
        ).sum(-1)
        entropy = (0.5 + 0.5 * math.log(2 * math.pi) + scale.log()).sum(-1)
    adv = mb["advantage"].squeeze(-1)
    adv = (adv - adv.mean()) / adv.std()
    ratio = (log_prob - mb["action_log_prob"]).exp()
    gain = torch.minimum(ratio * adv, ratio.clamp(1 - CLIP_EPS, 1 + CLIP_EPS) * adv)
    value = pol.critic_net.mlp(critic_in)
    target, old = mb["value_target"], mb["state_value"]
    clipped = old + (value - old).clamp(-CLIP_VALUE, CLIP_VALUE)
    loss_value = torch.maximum(F.mse_loss(target, value, reduction="none"), (target - clipped) ** 2)
    return -gain.mean() + CRITIC * loss_value.mean() - ENT * entropy.mean()


def _count_encoder_calls(pol) -> dict[str, int]:
    """Per encoder module (actor's / critic's, by key), its forward calls from now on."""
    calls: dict[str, int] = {}
    modules = {}
    for net in ("actor", "critic"):
        for key, enc in getattr(pol, f"{net}_net").inputs.encoders.items():
            modules.setdefault(id(enc), (enc, []))[1].append(f"{net}.{key}")
    for enc, names in modules.values():
        name = "+".join(names)
        calls[name] = 0

        def hook(*_, name=name):
            calls[name] += 1

        enc.register_forward_hook(hook)
    return calls


@pytest.mark.parametrize("categorical", [False, True], ids=["gaussian", "categorical"])
@pytest.mark.parametrize("share", [True, False], ids=["shared", "separate"])
@pytest.mark.parametrize("encoder", list(ENCODERS))
def test_the_shared_encoder_runs_once_per_minibatch_with_the_two_pass_loss_and_gradients(
    encoder, share, categorical
):
    pol = _policy(encoder, share, categorical)
    assert (
        pol.actor_net.inputs.encoders["pixels"] is pol.critic_net.inputs.encoders["pixels"]
    ) == share
    mb = _minibatch(pol)
    params = [p for p in pol.parameters() if p.requires_grad]
    want = _reference_loss(pol, mb)
    want_grads = torch.autograd.grad(want, params)
    assert any(g.abs().sum() > 0 for g in want_grads[:4]), "no gradient reached the encoder"
    calls = _count_encoder_calls(pol)
    # each image tensor is encoded once per encoder module: the shared one for both heads
    once = {name: 1 for name in calls}
    if share:
        assert set(calls) == {"actor.pixels+critic.pixels", "critic.wrist"}
    else:
        assert set(calls) == {"actor.pixels", "critic.pixels", "critic.wrist"}

    algo = make_algorithm(SETTINGS, pol, total_iterations=1)
    step = FusedPPOStep(algo, compiled=False)
    data = [mb.get(k) for k in MINIBATCH_KEYS]
    hyper = torch.tensor([CLIP_EPS, ENT, CRITIC, 0.37])
    total, _ = step.loss(*data, hyper)
    assert calls == once, f"fused step: encoder forward calls {calls}"
    got_grads = torch.autograd.grad(total, params)
    torch.testing.assert_close(total, want, rtol=1e-5, atol=1e-6)
    for name, g, w in zip(algo.param_names, got_grads, want_grads, strict=True):
        torch.testing.assert_close(g, w, rtol=1e-4, atol=1e-6, msg=f"fused step: {name}")

    # TorchRL's ClipPPOLoss (the path PPO takes where the fused step does not apply)
    calls.update(dict.fromkeys(calls, 0))
    with pol.encode_once():
        out = algo.loss(mb.clone())
    assert calls == once, f"ClipPPOLoss: encoder forward calls {calls}"
    total = sum(out[k] for k in LOSS_KEYS)
    torch.testing.assert_close(total, want, rtol=1e-5, atol=1e-6)
    for name, g, w in zip(
        algo.param_names, torch.autograd.grad(total, params), want_grads, strict=True
    ):
        torch.testing.assert_close(g, w, rtol=1e-4, atol=1e-6, msg=f"ClipPPOLoss: {name}")
    # outside a loss call the networks run their encoders as before
    calls.update(dict.fromkeys(calls, 0))
    pol.actor_net(mb["observation"]), pol.critic_net(mb["observation"])
    assert calls[next(n for n in calls if "actor.pixels" in n)] == (2 if share else 1)


def test_the_update_s_minibatch_loop_encodes_each_minibatch_once(monkeypatch):
    """PPO.update through both minibatch paths: one pass of the shared encoder per minibatch."""
    for fused in (True, False):
        pol = _policy("nature", True, False)
        mb = _minibatch(pol)
        algo = make_algorithm(
            dataclasses.replace(SETTINGS, num_epochs=2, mini_batch_size=4), pol, 1
        )
        algo.use_fused_step = fused
        calls = _count_encoder_calls(pol)
        monkeypatch.setattr(algo, "compute_advantages", lambda batch: batch)
        algo.update(mb.clone())
        assert (algo.fused is not None) == fused
        assert calls["actor.pixels+critic.pixels"] == 2 * (N // 4), (fused, calls)


def _image_env_policy(share: bool = True):
    """tests/image_envs.py's ImageReach (vector [4] + uint8 pixels 3x12x10) and a CNN policy."""
    from image_envs import ImageReach

    env = ImageReach(3, seed=5)
    torch.manual_seed(6)
    cfg = PolicyConfig(
        critic=MLPConfig(hidden_sizes=[7]),
        encoder=ENCODERS["nature"],
        share_encoder=share,
    )
    pol = make_policy(cfg, 4, 2, env.action_spec[0], layout=env.obs_layout)
    pol.normalizer.update(torch.randn(40, 4) * 2 + 0.5)
    return env, pol


def _collect(env, sampling, steps: int = 16):
    from rlexp.training.collector import RolloutCollector

    col = RolloutCollector(
        env, sampling, frames_per_batch=3 * steps, total_frames=-1, trust_policy=True,
        auto_register_policy_transforms=False,
    )  # fmt: skip
    try:
        return next(iter(col))
    finally:
        col.shutdown()


@pytest.mark.parametrize("loop", ["lean", "torchrl"])
def test_collection_values_give_gae_the_advantages_of_its_own_critic_pass(loop):
    """An image policy sharing its encoder writes V(s_t) while collecting (the actor's features,
    the critic's head); GAE then evaluates only the bootstrap observations (episode ends, the last
    step), and its values, advantages and targets equal those of its own pass over the rollout."""
    from torchrl.envs import Compose, TransformedEnv

    env, pol = _image_env_policy()
    if loop == "torchrl":
        env = TransformedEnv(env, Compose())
    sampling = pol.sampling_policy(values=True)
    assert sampling.out_keys[-1] == "state_value"
    batch = _collect(env, sampling)
    assert batch["next", "done"].any(), "episodes must end inside the rollout"
    cfg = AlgorithmConfig(gamma=0.93, lmbda=0.7, mini_batch_size=10)
    algo = make_algorithm(cfg, pol, 1)
    rows = []
    enc = pol.critic_net.inputs.encoders["pixels"]
    enc.register_forward_hook(
        lambda m, args, out: rows.append(args[0].reshape(-1, 3, 12, 10).shape[0])
    )
    mine = algo.compute_advantages(batch.clone())
    bootstrap = int(batch["next", "done"][:, :-1].sum()) + 3  # finished episodes, last steps
    assert sum(rows) <= bootstrap < 3 * 16, rows  # never the whole rollout again
    rows.clear()
    theirs = algo.compute_advantages(batch.clone().exclude("state_value"))
    assert sum(rows) >= 3 * 16
    for key in ("state_value", ("next", "state_value"), "advantage", "value_target"):
        torch.testing.assert_close(mine[key], theirs[key], rtol=1e-5, atol=1e-6, msg=str(key))


def test_the_training_collector_writes_values_only_where_gae_may_take_them():
    """PPO without overlap: values in the rollout; overlap (collection during the update, one
    update behind), GRPO, separate encoders, evaluation, a vector-only policy: none."""
    from rlexp.training.loop import collection_policy

    env, pol = _image_env_policy()
    ppo = make_algorithm(SETTINGS, pol, 1)
    assert "state_value" in collection_policy(pol, ppo, overlap=False).out_keys
    assert "state_value" not in collection_policy(pol, ppo, overlap=True).out_keys
    grpo = make_algorithm(GRPOConfig(), pol, 1)
    assert "state_value" not in collection_policy(pol, grpo, overlap=False).out_keys
    assert "state_value" not in pol.sampling_policy(deterministic=True).out_keys
    _, separate = _image_env_policy(share=False)
    assert not separate.values_in_collection
    assert "state_value" not in separate.sampling_policy(values=True).out_keys
    flat = make_policy(PolicyConfig(), 5, 2, Bounded(-1.0, 1.0, shape=(2,)))
    assert "state_value" not in flat.sampling_policy(values=True).out_keys


@needs_compiler
@pytest.mark.slow  # compiles a CNN's loss (about a minute here)
def test_a_compiled_clipppoloss_update_of_a_cnn_policy_equals_the_eager_one():
    """The compiled ClipPPOLoss path (the fused step off): its first call runs the loss twice on
    one minibatch (compiling, then for real), and no call reuses another call's features."""
    pol = _policy("nature", True, False)
    ref = copy.deepcopy(pol)
    batch = torch.cat([_minibatch(pol)] * 2)
    cfg = dataclasses.replace(SETTINGS, num_epochs=2, mini_batch_size=6)
    compiled = make_algorithm(dataclasses.replace(cfg, compile="true"), pol, 5)
    eager = make_algorithm(cfg, ref, 5)
    for algo in (compiled, eager):
        algo.use_fused_step = False
        algo.compute_advantages = lambda b: b
    for seed in (0, 1):
        torch.manual_seed(seed)
        compiled.update(batch.clone())
        torch.manual_seed(seed)
        eager.update(batch.clone())
    assert compiled.compiled and compiled.fused is None and eager.fused is None
    for (name, p), q in zip(pol.named_parameters(), ref.parameters(), strict=True):
        torch.testing.assert_close(p, q, rtol=1e-4, atol=1e-5, msg=name)
