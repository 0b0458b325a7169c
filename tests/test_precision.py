"""``trainer.precision=bf16`` (mixed precision, docs/performance.md "Mixed precision (bf16)"): the
networks' matmuls and convolutions run under ``torch.autocast(bfloat16)`` in the update (PPO's fused
step and TorchRL's ClipPPOLoss, SAC's and TD3's fused and TorchRL steps), in GAE's value pass and in
collection and evaluation; their outputs, the loss maths, the optimiser's state and the weights
stay float32.

The expected values come from plain-torch references that run the same networks' layers under an
explicit ``torch.autocast`` and compute the losses by hand in float32; each check also shows the
bf16 result differs from the float32 one by a small nonzero amount (autocast really acted). Which
dtype each matmul / convolution ran in is read below autograd (``MatmulDtypes``, a dispatch mode)
or by forward hooks on the layers."""

from __future__ import annotations

import copy
import logging
import math

import pytest
import torch
from tensordict import TensorDict
from test_sac import B, _batch, _linears, _nets, _spec
from test_shared_encoder import CLIP_EPS, CLIP_VALUE, CRITIC, ENT, SETTINGS, _minibatch, _policy
from torch.nn import functional as F
from torch.utils._python_dispatch import TorchDispatchMode

from conftest import needs_compiler
from rlexp.algorithms.fused_step import MINIBATCH_KEYS, FusedPPOStep
from rlexp.algorithms.ppo import LOSS_KEYS, make_algorithm
from rlexp.algorithms.sac import SAC
from rlexp.algorithms.td3 import TD3
from rlexp.config.schema_base import MLPConfig
from rlexp.config.schema_offpolicy import SACConfig, SACPolicyConfig, TD3Config, TD3PolicyConfig
from rlexp.policies.offpolicy import SACPolicy, TD3Policy
from rlexp.runtime import precision
from rlexp.runtime.precision import set_precision

pytestmark = pytest.mark.usefixtures("one_torch_thread")

BF16 = torch.bfloat16
_MATMULS = {"addmm", "mm", "bmm", "baddbmm", "convolution", "convolution_backward", "linear"}


class MatmulDtypes(TorchDispatchMode):
    """Within: the dtype of every matmul / convolution torch runs (forward and backward)."""

    def __init__(self) -> None:
        super().__init__()
        self.seen: list[tuple[str, torch.dtype]] = []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        out = func(*args, **(kwargs or {}))
        name = func.overloadpacket.__name__
        if name in _MATMULS:
            first = next(o for o in (out if isinstance(out, tuple) else (out,)) if o is not None)
            self.seen.append((name, first.dtype))
        return out

    def dtypes(self) -> set[torch.dtype]:
        assert self.seen, "no matmul ran: the check would be vacuous"
        return {d for _, d in self.seen}


def _layer_dtypes(module: torch.nn.Module) -> list[torch.dtype]:
    """Forward hooks on every Linear / Conv2d of ``module``: their outputs' dtypes, appended."""
    seen: list[torch.dtype] = []
    for m in module.modules():
        if isinstance(m, (torch.nn.Linear, torch.nn.Conv2d)):
            m.register_forward_hook(lambda _m, _i, out: seen.append(out.dtype))
    return seen


# -- PPO ------------------------------------------------------------------------------------------


def _reference_ppo_loss(pol, mb: TensorDict) -> torch.Tensor:
    """PPO's clipped loss by hand: each network's encoder and MLP under ``torch.autocast``
    (bfloat16), their outputs cast to float32, the loss maths in float32 outside autocast."""
    obs = mb["observation"]
    norm = pol.normalizer(obs["vector"])
    actor_enc = pol.actor_net.inputs.encoders
    critic_enc = pol.critic_net.inputs.encoders
    assert actor_enc["pixels"] is critic_enc["pixels"]  # one shared encoder: one pass
    with torch.autocast("cpu", dtype=BF16):
        pixels = actor_enc["pixels"](obs["pixels"])
        out = pol.actor_net.mlp(torch.cat([norm[:, :4], pixels], -1))
        critic_in = torch.cat([norm, pixels, critic_enc["wrist"](obs["wrist"])], -1)
        value = pol.critic_net.mlp(critic_in)
    assert out.dtype == BF16 and value.dtype == BF16
    out, value = out.float(), value.float()
    action = mb["action"]
    if pol.categorical:
        dists = [torch.distributions.Categorical(logits=b) for b in out.split([3, 2], -1)]
        log_prob = sum(d.log_prob(action[:, i]) for i, d in enumerate(dists))
        entropy = sum(d.entropy() for d in dists)
    else:
        log_std = pol.actor_net.log_std.clamp(pol.actor_net.min_log_std, pol.actor_net.max_log_std)
        normal = torch.distributions.Normal(out, log_std.exp().expand_as(out))
        log_prob, entropy = normal.log_prob(action).sum(-1), normal.entropy().sum(-1)
    adv = mb["advantage"].squeeze(-1)
    adv = (adv - adv.mean()) / adv.std()
    ratio = (log_prob - mb["action_log_prob"]).exp()
    gain = torch.minimum(ratio * adv, ratio.clamp(1 - CLIP_EPS, 1 + CLIP_EPS) * adv)
    target, old = mb["value_target"], mb["state_value"]
    clipped = old + (value - old).clamp(-CLIP_VALUE, CLIP_VALUE)
    loss_value = torch.maximum((target - value) ** 2, (target - clipped) ** 2)
    return -gain.mean() + CRITIC * loss_value.mean() - ENT * entropy.mean()


@pytest.mark.parametrize("categorical", [False, True], ids=["gaussian", "categorical"])
def test_bf16_ppo_loss_and_gradients_equal_an_autocast_reference(categorical):
    """A CNN policy (shared Nature encoder, a critic-only image and group): the fused step's and
    ClipPPOLoss's loss and gradients under bf16 equal the autocast reference; both differ from
    float32 by a small nonzero amount; every matmul and convolution ran in bfloat16."""
    pol = _policy("nature", True, categorical)
    mb = _minibatch(pol)
    params = [p for p in pol.parameters() if p.requires_grad]
    algo = make_algorithm(SETTINGS, pol, total_iterations=1)
    step = FusedPPOStep(algo, compiled=False)
    data = [mb.get(k) for k in MINIBATCH_KEYS]
    hyper = torch.tensor([CLIP_EPS, ENT, CRITIC, 0.37])
    fp32_loss, _ = step.loss(*data, hyper)
    fp32_grads = torch.autograd.grad(fp32_loss, params)

    set_precision(pol, "bf16", "cpu")
    want = _reference_ppo_loss(pol, mb)
    want_grads = torch.autograd.grad(want, params)
    with MatmulDtypes() as seen:
        total, stats = step.loss(*data, hyper)
        got_grads = torch.autograd.grad(total, params)
    assert seen.dtypes() == {BF16}, seen.seen
    assert {"convolution", "convolution_backward", "addmm", "mm"} <= {n for n, _ in seen.seen}
    assert total.dtype == stats.dtype == torch.float32
    torch.testing.assert_close(total, want, rtol=1e-5, atol=1e-6)
    for name, g, w in zip(algo.param_names, got_grads, want_grads, strict=True):
        assert g.dtype == torch.float32, name
        torch.testing.assert_close(g, w, rtol=1e-3, atol=1e-5, msg=f"fused step: {name}")
    # autocast acted: bf16 rounds the networks' outputs (~3 significant digits)
    assert (
        1e-6 < abs(float(total.detach() - fp32_loss.detach())) < 2e-2 * abs(fp32_loss.item()) + 1e-3
    )
    assert max(float((g - w).abs().max()) for g, w in zip(got_grads, fp32_grads, strict=True)) > 0

    # TorchRL's ClipPPOLoss (PPO's path where the fused step does not apply)
    with MatmulDtypes() as seen, pol.encode_once():
        out = algo.loss(mb.clone())
        total = sum(out[k] for k in LOSS_KEYS)
        got_grads = torch.autograd.grad(total, params)
    assert seen.dtypes() == {BF16}, seen.seen
    torch.testing.assert_close(total, want, rtol=1e-5, atol=1e-6)
    for name, g, w in zip(algo.param_names, got_grads, want_grads, strict=True):
        torch.testing.assert_close(g, w, rtol=1e-3, atol=1e-5, msg=f"ClipPPOLoss: {name}")


def test_bf16_update_keeps_gae_log_probs_advantages_adam_and_weights_float32(monkeypatch):
    """A whole PPO.update under bf16: the critic's value pass for GAE and the minibatch steps run
    their layers in bfloat16; the values, advantages, targets, log-probabilities and entropies
    the loss reads, the statistics, Adam's state and the weights are float32."""
    from test_fast_update import SETTINGS as FAST
    from test_fast_update import _policy as vector_policy
    from test_fast_update import _rollout

    from rlexp.config.schema import AlgorithmConfig

    pol = vector_policy(None)
    batch = _rollout(pol)
    set_precision(pol, "bf16", "cpu")
    algo = make_algorithm(AlgorithmConfig(**FAST), pol, total_iterations=10)
    layers = _layer_dtypes(pol)
    seen_gae: list[torch.dtype] = []
    compute = algo.compute_advantages

    def gae(b):
        out = compute(b)
        seen_gae.extend(layers)
        for key in ("state_value", "advantage", "value_target", ("next", "state_value")):
            assert b.get(key).dtype == torch.float32, key
        return out

    monkeypatch.setattr(algo, "compute_advantages", gae)
    loss_dtypes: list[torch.dtype] = []
    log_prob, entropy = FusedPPOStep._log_prob, FusedPPOStep._entropy

    def record(fn):
        def wrapped(self, *args):
            out = fn(self, *args)
            loss_dtypes.append(out.dtype)
            return out

        return wrapped

    monkeypatch.setattr(FusedPPOStep, "_log_prob", record(log_prob))
    monkeypatch.setattr(FusedPPOStep, "_entropy", record(entropy))
    metrics = algo.update(batch.clone())
    assert algo.fused is not None and math.isfinite(metrics["loss/policy"])
    assert seen_gae and set(seen_gae) == {BF16}, "GAE's critic pass did not run in bf16"
    assert len(layers) > len(seen_gae) and set(layers) == {BF16}
    assert loss_dtypes and set(loss_dtypes) == {torch.float32}
    assert all(p.dtype == torch.float32 for p in pol.parameters())
    state = [t for s in algo.optimizer.state.values() for t in s.values()]
    assert state and all(t.dtype == torch.float32 for t in state)


def test_bf16_collection_and_evaluation_forward_run_in_bf16_with_float32_outputs():
    """The collection sampler (values written, the shared encoder once) and the deterministic
    evaluation sampler run their convolutions and layers in bfloat16; everything they return is
    float32 (int64 categorical actions as they are), equal to the float32 sampler's to bf16
    rounding."""
    pol = _policy("nature", True, categorical=False)
    obs = _minibatch(pol)["observation"]
    torch.manual_seed(3)
    fp32 = pol.sampling_policy(values=True).sample(obs)
    set_precision(pol, "bf16", "cpu")
    layers = _layer_dtypes(pol)
    for deterministic in (False, True):
        sampling = pol.sampling_policy(deterministic=deterministic, values=not deterministic)
        torch.manual_seed(3)
        with torch.no_grad():
            out = sampling.sample(obs)
        assert layers and set(layers) == {BF16}, layers
        assert all(t.dtype == torch.float32 for t in out), [t.dtype for t in out]
        layers.clear()
    # (loc, scale, action, log-prob, value): the stochastic call's; bf16 rounding apart
    torch.manual_seed(3)
    with torch.no_grad():
        got = pol.sampling_policy(values=True).sample(obs)
    for g, w in zip(got, fp32, strict=True):
        torch.testing.assert_close(g, w, rtol=0.05, atol=0.05)
    assert any(not torch.equal(g, w) for g, w in zip(got, fp32, strict=True))
    # a categorical head: the logits float32 (masking at float32's minimum), actions int64
    cat = _policy("nature", True, categorical=True)
    set_precision(cat, "bf16", "cpu")
    with torch.no_grad():
        logits, action, log_p = cat.sampling_policy().sample(obs)
    assert logits.dtype == log_p.dtype == torch.float32 and action.dtype == torch.int64


# -- SAC / TD3 ------------------------------------------------------------------------------------


def _mlp(layers, x, act=torch.relu):
    for i, (w, b) in enumerate(layers):
        x = F.linear(x, w, b)
        if i < len(layers) - 1:
            x = act(x)
    return x


def _bf16(fn, *args):
    """``fn(*args)`` under autocast (bfloat16), its output float32: a network in the reference."""
    with torch.autocast("cpu", dtype=BF16):
        out = fn(*args)
    assert out.dtype == BF16
    return out.float()


def _q(nets, obs, act):
    x = torch.cat([obs, act], -1)
    return torch.stack([_bf16(_mlp, layers, x).squeeze(-1) for layers in nets])


LOW, HIGH = torch.tensor([-2.0, -1.0]), torch.tensor([1.0, 3.0])  # test_sac's bounds


def _sac(tmp_path, compile_: str, prec: str) -> SAC:
    """test_sac's SAC (the same seeded networks and settings) at ``prec``."""
    torch.manual_seed(0)
    pcfg = SACPolicyConfig(actor=MLPConfig([5, 4], "relu"), critic=MLPConfig([6], "relu"))
    cfg = SACConfig(gamma=0.9, tau=0.3, alpha_init=0.5, target_entropy=-0.7, lr=1e-3,
                    critic_lr=2e-3, alpha_lr=5e-3, buffer_size=64, batch_size=B,
                    compile=compile_)  # fmt: skip
    policy = SACPolicy(pcfg, 3, 2, _spec())
    set_precision(policy, prec, "cpu")  # as the run's builder: before the learner
    return SAC(cfg, policy, 10, run_dir=tmp_path)


def _td3(tmp_path, compile_: str, prec: str) -> TD3:
    """test_sac's TD3 at ``prec``."""
    torch.manual_seed(0)
    pcfg = TD3PolicyConfig(actor=MLPConfig([5], "relu"), critic=MLPConfig([6], "relu"))
    cfg = TD3Config(gamma=0.8, tau=0.25, lr=1e-3, critic_lr=3e-3, policy_delay=3,
                    target_policy_noise=0.4, target_noise_clip=0.3, buffer_size=64, batch_size=B,
                    compile=compile_)  # fmt: skip
    policy = TD3Policy(pcfg, 3, 2, _spec())
    set_precision(policy, prec, "cpu")
    return TD3(cfg, policy, 10, run_dir=tmp_path)


def _tanh_gaussian(actor, obs, eps):
    loc, log_std = _bf16(_mlp, actor, obs).chunk(2, -1)
    std = log_std.clamp(-20.0, 2.0).exp()
    u = loc + std * eps
    normal = (-0.5 * eps.pow(2) - std.log() - 0.5 * math.log(2 * math.pi)).sum(-1)
    log_prob = (
        normal - torch.log1p(-torch.tanh(u).pow(2)).sum(-1) - torch.log((HIGH - LOW) / 2).sum()
    )
    return LOW + (HIGH - LOW) * (torch.tanh(u) + 1) / 2, log_prob


@pytest.mark.parametrize("compile_", ["false", "auto"])
def test_bf16_sac_step_equals_an_autocast_reference(tmp_path, compile_):
    """SAC's gradient step under bf16 (compile false: TorchRL's SACLoss; auto: the fused step):
    losses and gradients equal a plain-torch SAC whose actor and Q networks run under autocast,
    the targets, log-densities (tanh's log-det) and losses in float32; a small nonzero distance
    from float32's; matmuls in bfloat16, Adam's state and the weights float32."""
    fp32 = _sac(tmp_path / "a", compile_, "fp32")
    torch.manual_seed(123)
    fp32_out = fp32._gradient_step(_batch())

    algo = _sac(tmp_path / "b", compile_, "bf16")  # the same initial networks (seeded)
    batch = _batch()
    actor, q, targets = _nets(algo, 2)
    a_layers = _linears(actor, "")
    q_layers = [_linears(p, "module.mlp.") for p in q]
    t_layers = [_linears(p, "module.mlp.") for p in targets]
    torch.manual_seed(123)
    eps_next, eps_now = torch.randn(B, 2), torch.randn(B, 2)
    obs, act, nxt = batch["observation"], batch["action"], batch["next"]
    with torch.no_grad():
        a_next, logp_next = _tanh_gaussian(a_layers, nxt["observation"], eps_next)
        v_next = _q(t_layers, nxt["observation"], a_next).min(0).values - 0.5 * logp_next
        not_term = (~nxt["terminated"]).float().squeeze(-1)
        y = nxt["reward"].squeeze(-1) + 0.9 * not_term * v_next
    q_loss = (_q(q_layers, obs, act) - y).pow(2).mean(1).sum()
    a_new, logp = _tanh_gaussian(a_layers, obs, eps_now)
    q_frozen = [[(w.detach(), b.detach()) for w, b in layers] for layers in q_layers]
    actor_loss = (0.5 * logp - _q(q_frozen, obs, a_new).min(0).values).mean()
    (q_loss + actor_loss).backward()

    torch.manual_seed(123)
    with MatmulDtypes() as seen:
        out = algo._gradient_step(batch)
    assert seen.dtypes() == {BF16}, seen.seen
    assert {v.dtype for v in out.values()} == {torch.float32}
    # The fused step rounds where the reference does (each layer's output to bfloat16); TorchRL's
    # SACLoss runs the twin Q networks through vmap, whose Linear is a bf16 matmul plus a float32
    # bias (no rounding after the bias): the same maths within bf16 rounding, not closer.
    rel = 1e-4 if compile_ == "auto" else 1e-2
    for key, want in (("loss/qvalue", q_loss), ("loss/actor", actor_loss)):
        assert out[key].item() == pytest.approx(want.item(), rel=rel, abs=1e-5), key
        assert 0 < abs(out[key].item() - fp32_out[key].item()) < 0.05 * abs(want.item()) + 1e-2
    # the actor's gradient (before its Adam step) is what the reference's is
    for name, p in algo.policy.actor_net.mlp.named_parameters():
        assert p.grad.dtype == torch.float32
        torch.testing.assert_close(p.grad, actor[name].grad, rtol=20 * rel, atol=1e-5)
    for opt in (algo.actor_optimizer, algo.q_optimizer, algo.alpha_optimizer):
        state = [t for s in opt.state.values() for t in s.values()]
        assert state and all(t.dtype == torch.float32 for t in state)
    assert all(t.dtype == torch.float32 for t in algo.loss.parameters())


@pytest.mark.parametrize("compile_", ["false", "auto"])
def test_bf16_td3_runs_its_networks_in_bf16_and_its_paths_agree(tmp_path, compile_):
    """TD3 under bf16, TorchRL's TD3Loss and the fused step: matmuls in bfloat16, the losses
    float32, within bf16 rounding of each other and a nonzero distance from float32's."""
    losses = {}
    for name, prec, comp in (("fp32", "fp32", "false"), ("bf16", "bf16", compile_)):
        algo = _td3(tmp_path / name, comp, prec)
        algo.gradient_steps = algo.cfg.policy_delay - 1  # the actor's step too
        torch.manual_seed(7)
        with MatmulDtypes() as seen:
            out = algo._gradient_step(_batch())
        assert seen.dtypes() == ({BF16} if prec == "bf16" else {torch.float32}), seen.seen
        assert set(out) == {"loss/qvalue", "loss/actor"}
        losses[name] = {k: v.item() for k, v in out.items()}
    for key, want in losses["fp32"].items():
        got = losses["bf16"][key]
        assert 0 < abs(got - want) < 0.05 * abs(want) + 1e-2, (key, got, want)


# -- config, support check ------------------------------------------------------------------------


def test_precision_values_and_the_rules_table_agree():
    from rlexp.config.rules import FIELD_RULES, PRECISIONS

    assert PRECISIONS == precision.PRECISIONS
    rule = FIELD_RULES["trainer.precision"]
    assert rule.check("bf16") and rule.check("fp32")
    assert not rule.check("bf16-mixed") and not rule.check("16")
    with pytest.raises(ValueError, match=r"^trainer.precision='fp16' must be one of"):
        precision.check_precision("fp16")


def test_emulated_bf16_warns_once_and_native_bf16_does_not(monkeypatch, caplog):
    monkeypatch.setattr(precision.platform, "machine", lambda: "x86_64")
    monkeypatch.setattr(precision, "_cpu_flags", lambda: {"avx2", "avx512f"})
    with caplog.at_level(logging.WARNING, logger="rlexp.runtime.precision"):
        text = precision.warn_if_slow("bf16", "cpu")
        assert precision.warn_if_slow("fp32", "cpu") is None
    assert text is not None and text.startswith("trainer.precision=bf16 on cpu: ")
    assert "avx512_bf16" in text and "trainer.precision=fp32" in text and "\n" not in text
    assert [r.getMessage() for r in caplog.records] == [text]
    monkeypatch.setattr(precision, "_cpu_flags", lambda: {"avx512f", "avx512_bf16"})
    monkeypatch.setattr(torch.ops.mkldnn, "_is_mkldnn_bf16_supported", lambda: True)
    assert precision.warn_if_slow("bf16", "cpu") is None


def test_float32_policy_is_untouched_by_the_precision_machinery():
    """fp32 (the default): no autocast anywhere, outputs the same tensors bit for bit as a policy
    that never met ``set_precision``."""
    pol = _policy("nature", True, categorical=False)
    obs = _minibatch(pol)["observation"]
    before = pol.actor_net(obs)
    set_precision(pol, "bf16", "cpu")
    set_precision(pol, "fp32", "cpu")
    with MatmulDtypes() as seen:
        after = pol.actor_net(obs)
    assert seen.dtypes() == {torch.float32}
    for b, a in zip(before, after, strict=True):
        assert torch.equal(b, a)
    assert copy.deepcopy(pol).actor_net.autocast_dtype is None


@pytest.mark.slow  # compiling takes ~50 s on the shared 2-core machine
@needs_compiler
def test_bf16_compiled_fused_steps_equal_their_eager_steps(tmp_path):
    """algorithm.compile=true under bf16: PPO's compiled fused step (the autocast inside the
    networks' forward traced by dynamo) and SAC's compiled step give their eager bf16 step's
    losses (to bf16 rounding: inductor fuses the float32 maths around the matmuls)."""
    from test_fast_update import SETTINGS as FAST
    from test_fast_update import _policy as vector_policy
    from test_fast_update import _rollout

    from rlexp.config.schema import AlgorithmConfig

    out = {}
    for choice in ("false", "true"):
        pol = vector_policy(None)
        batch = _rollout(pol)
        set_precision(pol, "bf16", "cpu")
        algo = make_algorithm(AlgorithmConfig(**{**FAST, "compile": choice}), pol, 10)
        torch.manual_seed(5)
        out[choice] = algo.update(batch.clone())
        assert algo.fused is not None and algo.fused.compiled == (choice == "true")
    for key in ("loss/policy", "loss/value", "loss/grad_norm"):
        assert out["true"][key] == pytest.approx(out["false"][key], rel=2e-2, abs=1e-4), key
    sac = {}
    for choice in ("auto", "true"):
        algo = _sac(tmp_path / choice, choice, "bf16")
        torch.manual_seed(123)
        sac[choice] = {k: v.item() for k, v in algo._gradient_step(_batch()).items()}
    for key, want in sac["auto"].items():
        assert sac["true"][key] == pytest.approx(want, rel=1e-3, abs=1e-5), key


def test_bf16_grpo_fused_and_tensordict_paths_run_bf16_and_agree():
    """GRPO (an actor-only policy, a KL penalty to the frozen initial policy): both minibatch paths
    run the actor's and the reference's layers in bfloat16, give float32 statistics within bf16
    rounding of each other and a nonzero distance from float32's; Adam's state float32."""
    from test_fast_update_grpo import SETTINGS as GRPO_SETTINGS
    from test_fast_update_grpo import _policy as actor_only
    from test_fast_update_grpo import _rollout as grpo_rollout

    from rlexp.config.schema import GRPOConfig

    out = {}
    for name, prec, fused in (
        ("fp32", "fp32", True),
        ("fused", "bf16", True),
        ("td", "bf16", False),
    ):
        pol = actor_only(None)
        batch = grpo_rollout(pol)
        set_precision(pol, prec, "cpu")
        algo = make_algorithm(GRPOConfig(**GRPO_SETTINGS), pol, 10)
        algo.use_fused_step = fused
        layers = _layer_dtypes(pol)
        reference = _layer_dtypes(algo.reference)
        torch.manual_seed(2)
        out[name] = algo.update(batch.clone())
        assert (algo.fused is not None) == fused
        want = {BF16} if prec == "bf16" else {torch.float32}
        assert set(layers) == want and set(reference) == want, (name, layers, reference)
        state = [t for s in algo.optimizer.state.values() for t in s.values()]
        assert state and all(t.dtype == torch.float32 for t in state)
    for key, want in out["fused"].items():
        assert out["td"][key] == pytest.approx(want, rel=1e-3, abs=1e-6), key
    assert any(out["fused"][k] != out["fp32"][k] for k in out["fp32"] if k.startswith("loss/"))
