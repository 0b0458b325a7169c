"""SAC and TD3 gradient steps against plain-torch references (non-default gamma, tau, alpha and its
target, policy delay, smoothing noise and clip, asymmetric action bounds), with a batch that holds
a terminated and a truncated transition: the targets bootstrap through the truncation only."""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Bounded

from rlexp.algorithms.sac import SAC
from rlexp.algorithms.td3 import TD3
from rlexp.config.schema_base import MLPConfig
from rlexp.config.schema_offpolicy import SACConfig, SACPolicyConfig, TD3Config, TD3PolicyConfig
from rlexp.policies.offpolicy import SACPolicy, TD3Policy

LOW = torch.tensor([-2.0, -1.0])
HIGH = torch.tensor([1.0, 3.0])
B = 8


def _spec() -> Bounded:
    return Bounded(LOW.clone(), HIGH.clone(), shape=(2,))


def _batch(seed: int = 5) -> TensorDict:
    g = torch.Generator().manual_seed(seed)
    terminated = torch.zeros(B, 1, dtype=torch.bool)
    truncated = torch.zeros(B, 1, dtype=torch.bool)
    terminated[1] = True  # no bootstrap
    truncated[2] = True  # bootstraps from its next observation
    action = LOW + (HIGH - LOW) * torch.rand(B, 2, generator=g)
    return TensorDict(
        {
            "observation": torch.randn(B, 3, generator=g),
            "action": action,
            "next": {
                "observation": torch.randn(B, 3, generator=g),
                "reward": torch.randn(B, 1, generator=g),
                "terminated": terminated,
                "truncated": truncated,
                "done": terminated | truncated,
            },
        },
        [B],
    )


def _linears(
    params: dict[str, torch.Tensor], prefix: str
) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """The (weight, bias) pairs of an MLP's Linear layers, in order, from flat parameter names."""
    idx = sorted({int(k[len(prefix) :].split(".")[0]) for k in params if k.startswith(prefix)})
    return [(params[f"{prefix}{i}.weight"], params[f"{prefix}{i}.bias"]) for i in idx]


def _mlp(layers, x: torch.Tensor) -> torch.Tensor:
    for i, (w, b) in enumerate(layers):
        x = x @ w.T + b
        if i < len(layers) - 1:
            x = torch.relu(x)
    return x


def _q(layers_per_net, obs, act) -> torch.Tensor:
    """[n_nets, B] Q values."""
    x = torch.cat([obs, act], -1)
    return torch.stack([_mlp(layers, x).squeeze(-1) for layers in layers_per_net])


def _squash(u):
    return LOW + (HIGH - LOW) * (torch.tanh(u) + 1) / 2


def _tanh_gaussian(actor, obs, eps):
    """Action and log-density of the tanh-squashed Gaussian (change of variables by hand)."""
    loc, log_std = _mlp(actor, obs).chunk(2, -1)
    std = log_std.clamp(-20.0, 2.0).exp()
    u = loc + std * eps
    normal = (-0.5 * eps.pow(2) - std.log() - 0.5 * math.log(2 * math.pi)).sum(-1)
    log_prob = (
        normal - torch.log1p(-torch.tanh(u).pow(2)).sum(-1) - torch.log((HIGH - LOW) / 2).sum()
    )
    return _squash(u), log_prob


def _nets(algo, n_q: int):
    """Plain copies of the actor, Q and target Q layers (leaf tensors with grad)."""
    actor = {
        k: v.detach().clone().requires_grad_()
        for k, v in algo.policy.actor_net.mlp.state_dict().items()
    }
    qp = algo.loss.qvalue_network_params.flatten_keys(".")
    tq = algo.loss.target_qvalue_network_params.flatten_keys(".")
    q = [{k: qp[k][i].detach().clone().requires_grad_() for k in qp.keys()} for i in range(n_q)]
    t = [{k: tq[k][i].detach().clone() for k in tq.keys()} for i in range(n_q)]
    return actor, q, t


def _sac(tmp_path, **kw) -> SAC:
    torch.manual_seed(0)
    pcfg = SACPolicyConfig(actor=MLPConfig([5, 4], "relu"), critic=MLPConfig([6], "relu"))
    cfg = SACConfig(gamma=0.9, tau=0.3, alpha_init=0.5, target_entropy=-0.7, lr=1e-3,
                    critic_lr=2e-3, alpha_lr=5e-3, buffer_size=64, batch_size=B, **kw)  # fmt: skip
    return SAC(cfg, SACPolicy(pcfg, 3, 2, _spec()), 10, run_dir=tmp_path)


@pytest.mark.parametrize("compile_", ["false", "auto", "true"])
def test_sac_gradient_step_matches_a_plain_torch_sac(tmp_path, compile_):
    """compile false: TorchRL's SACLoss; auto: the fused step (fused_sac.py); true: it compiled."""
    algo = _sac(tmp_path, compile=compile_)
    assert (algo.fused is None) == (compile_ == "false")
    batch = _batch()
    actor, q, targets = _nets(algo, 2)
    log_alpha = torch.tensor(math.log(0.5), requires_grad=True)
    a_layers = _linears(actor, "")
    q_layers = [_linears(p, "module.mlp.") for p in q]
    t_layers = [_linears(p, "module.mlp.") for p in targets]

    torch.manual_seed(123)
    eps_next, eps_now = torch.randn(B, 2), torch.randn(B, 2)  # the loss draws in this order
    obs, act, nxt = batch["observation"], batch["action"], batch["next"]
    with torch.no_grad():
        a_next, logp_next = _tanh_gaussian(a_layers, nxt["observation"], eps_next)
        v_next = _q(t_layers, nxt["observation"], a_next).min(0).values - 0.5 * logp_next
        not_term = (~nxt["terminated"]).float().squeeze(-1)
        y = nxt["reward"].squeeze(-1) + 0.9 * not_term * v_next
    # the truncated row bootstraps, the terminated one does not (a check of the reference itself)
    assert y[1] == nxt["reward"][1, 0] and y[2] != nxt["reward"][2, 0]
    q_loss = (_q(q_layers, obs, act) - y).pow(2).mean(1).sum()
    a_new, logp = _tanh_gaussian(a_layers, obs, eps_now)
    q_frozen = [[(w.detach(), b.detach()) for w, b in layers] for layers in q_layers]
    actor_loss = (0.5 * logp - _q(q_frozen, obs, a_new).min(0).values).mean()
    alpha_loss = (-log_alpha * (logp.detach() - 0.7)).mean()
    (q_loss + actor_loss + alpha_loss).backward()

    torch.manual_seed(123)
    out = algo._gradient_step(batch)
    assert out["loss/qvalue"].item() == pytest.approx(q_loss.item(), rel=1e-5)
    assert out["loss/actor"].item() == pytest.approx(actor_loss.item(), rel=1e-5)
    assert out["loss/alpha"].item() == pytest.approx(alpha_loss.item(), rel=1e-5)
    # gradients, then one Adam step per network with its own learning rate, then the targets
    for name, p in algo.policy.actor_net.mlp.named_parameters():
        torch.testing.assert_close(p.grad, actor[name].grad, rtol=1e-4, atol=1e-6)
    torch.testing.assert_close(algo.loss.log_alpha.grad, log_alpha.grad, rtol=1e-4, atol=1e-7)
    opt = torch.optim.Adam([*actor.values()], lr=1e-3, eps=1e-8)
    qopt = torch.optim.Adam([v for p in q for v in p.values()], lr=2e-3, eps=1e-8)
    aopt = torch.optim.Adam([log_alpha], lr=5e-3, eps=1e-8)
    for o in (opt, qopt, aopt):
        o.step()
    for name, p in algo.policy.actor_net.mlp.named_parameters():
        torch.testing.assert_close(p.detach(), actor[name].detach(), rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(algo.loss.log_alpha.detach(), log_alpha.detach())
    qp = algo.loss.qvalue_network_params.flatten_keys(".")
    tq = algo.loss.target_qvalue_network_params.flatten_keys(".")
    for i in range(2):
        for k in q[i]:
            torch.testing.assert_close(qp[k][i].detach(), q[i][k].detach(), rtol=1e-5, atol=1e-6)
            soft = 0.3 * q[i][k].detach() + 0.7 * targets[i][k]  # tau = 0.3
            torch.testing.assert_close(tq[k][i].detach(), soft, rtol=1e-5, atol=1e-6)


def test_sac_auto_target_entropy_is_minus_act_dim_and_hooks_change_it(tmp_path):
    torch.manual_seed(0)
    pcfg = SACPolicyConfig(actor=MLPConfig([4], "relu"), critic=MLPConfig([4], "relu"))
    algo = SAC(
        SACConfig(buffer_size=16, batch_size=4), SACPolicy(pcfg, 3, 2, _spec()), 1, run_dir=tmp_path
    )
    assert algo.hyperparameters()["target_entropy"] == -2.0
    assert algo.loss.target_entropy.item() == -2.0
    algo.set_hyperparameter("target_entropy", -0.25)
    algo.set_hyperparameter("tau", 0.125)
    assert algo.loss.target_entropy.item() == -0.25
    assert algo.target_update.eps == pytest.approx(0.875)


def _td3(tmp_path, compile_: str = "auto") -> TD3:
    torch.manual_seed(0)
    pcfg = TD3PolicyConfig(actor=MLPConfig([5], "relu"), critic=MLPConfig([6], "relu"))
    cfg = TD3Config(gamma=0.8, tau=0.25, lr=1e-3, critic_lr=3e-3, policy_delay=3,
                    target_policy_noise=0.4, target_noise_clip=0.3, buffer_size=64, batch_size=B,
                    compile=compile_)  # fmt: skip
    return TD3(cfg, TD3Policy(pcfg, 3, 2, _spec()), 10, run_dir=tmp_path)


@pytest.mark.parametrize("compile_", ["false", "auto"])
def test_td3_gradient_steps_match_a_plain_torch_td3(tmp_path, compile_):
    """Three critic steps, the actor and the targets on the third (policy_delay=3); smoothing noise
    0.4 and clip 0.3 in half-ranges of the asymmetric bounds (half-ranges 1.5 and 2)."""
    algo = _td3(tmp_path, compile_)
    assert (algo.fused is None) == (compile_ == "false")
    batch = _batch(7)
    actor, q, targets = _nets(algo, 2)
    tactor = {k: v.detach().clone() for k, v in actor.items()}
    a_layers, ta_layers = _linears(actor, ""), _linears(tactor, "")
    q_layers = [_linears(p, "module.mlp.") for p in q]
    t_layers = [_linears(p, "module.mlp.") for p in targets]
    opt = torch.optim.Adam([*actor.values()], lr=1e-3, eps=1e-8)
    qopt = torch.optim.Adam([v for p in q for v in p.values()], lr=3e-3, eps=1e-8)
    obs, act, nxt = batch["observation"], batch["action"], batch["next"]
    half = (HIGH - LOW) / 2

    def mu(layers, x):
        return _squash(_mlp(layers, x))

    for step in range(3):
        torch.manual_seed(50 + step)
        noise = torch.maximum(
            torch.minimum(torch.randn(B, 2) * 0.4 * half, 0.3 * half), -0.3 * half
        )
        with torch.no_grad():
            a_next = torch.maximum(
                torch.minimum(mu(ta_layers, nxt["observation"]) + noise, HIGH), LOW
            )
            not_term = (~nxt["terminated"]).float().squeeze(-1)
            y = (
                nxt["reward"].squeeze(-1)
                + 0.8 * not_term * _q(t_layers, nxt["observation"], a_next).min(0).values
            )
        qopt.zero_grad()
        q_loss = (_q(q_layers, obs, act) - y).pow(2).mean(1).sum()
        q_loss.backward()
        qopt.step()
        torch.manual_seed(50 + step)
        out = algo._gradient_step(batch)
        algo.gradient_steps += 1
        assert out["loss/qvalue"].item() == pytest.approx(q_loss.item(), rel=1e-5)
        assert ("loss/actor" in out) == (step == 2)
        if step == 2:
            opt.zero_grad()
            q1 = [[(w.detach(), b.detach()) for w, b in q_layers[0]]]
            actor_loss = -_q(q1, obs, mu(a_layers, obs))[0].mean()
            actor_loss.backward()
            opt.step()
            assert out["loss/actor"].item() == pytest.approx(actor_loss.item(), rel=1e-5)
            with torch.no_grad():
                for k in tactor:
                    tactor[k].lerp_(actor[k], 0.25)
                for i in range(2):
                    for k in targets[i]:
                        targets[i][k].lerp_(q[i][k], 0.25)
    for name, p in algo.policy.actor_net.mlp.named_parameters():
        torch.testing.assert_close(p.detach(), actor[name].detach(), rtol=1e-5, atol=1e-6)
    qp = algo.loss.qvalue_network_params.flatten_keys(".")
    tq = algo.loss.target_qvalue_network_params.flatten_keys(".")
    ta = algo.loss.target_actor_network_params.flatten_keys(".")
    for i in range(2):
        for k in q[i]:
            torch.testing.assert_close(qp[k][i].detach(), q[i][k].detach(), rtol=1e-5, atol=1e-6)
            torch.testing.assert_close(tq[k][i].detach(), targets[i][k], rtol=1e-5, atol=1e-6)
    for k in tactor:
        key = next(t for t in ta.keys() if t.endswith("mlp." + k))
        torch.testing.assert_close(ta[key].detach(), tactor[k], rtol=1e-5, atol=1e-6)


def test_update_waits_for_learning_starts_then_keeps_the_update_to_data_ratio(tmp_path):
    """learning_starts=12 env steps with uniform actions first; updates_per_step=0.75 on rollouts
    of 8 transitions: 6 gradient steps each once learning has started."""
    algo = _sac(tmp_path, learning_starts=12, updates_per_step=0.75, compile="false")
    roll = _batch().reshape(2, 4)
    assert bool(algo.policy.uniform_actions)
    m = algo.update(roll)
    assert "loss/qvalue" not in m and bool(algo.policy.uniform_actions)
    m = algo.update(roll)  # 16 >= 12
    assert m["loss/gradient_steps"] == 6 and not bool(algo.policy.uniform_actions)
    m = algo.update(roll)
    assert m["loss/gradient_steps"] == 12


def test_the_fused_step_follows_the_torchrl_step_over_many_updates(tmp_path):
    """20 gradient steps from the same start and draws: the same parameters (to float rounding)."""
    runs = []
    for compile_ in ("false", "auto"):
        algo = _sac(tmp_path / compile_, compile=compile_)
        torch.manual_seed(77)
        for _ in range(20):
            algo._gradient_step(_batch())
        runs.append(algo.loss.state_dict())
    for key, value in runs[0].items():
        torch.testing.assert_close(runs[1][key], value, rtol=1e-4, atol=1e-5, msg=key)


def test_pbt_exploit_takes_networks_and_optimisers_but_not_the_buffer(tmp_path):
    """load_training_state (PBT's exploit): the other member's actor, Q networks, targets, alpha
    and optimisers; this member's replay buffer and counters stay."""
    a, b = _sac(tmp_path / "a"), _sac(tmp_path / "b")
    a.update(_batch(1).reshape(2, 4))
    a.update(_batch(2).reshape(2, 4))
    b.update(_batch(3).reshape(2, 4))
    theirs, rows = a.state_dict(), b.replay.sample(4)
    b.policy.load_state_dict(a.policy.state_dict())
    b.load_training_state(theirs)
    for key, value in theirs["loss"].items():
        assert torch.equal(b.loss.state_dict()[key], value), key
    assert (b.frames, len(b.replay), len(a.replay)) == (8, 8, 16)
    mine = _batch(3)["observation"]
    for row in b.replay.sample(16)["observation"]:  # every row is still one of b's own
        assert (mine == row).all(-1).any()
    assert rows["observation"].shape == (4, 3)


def test_n_step_targets_discount_by_gamma_to_the_steps_taken(tmp_path):
    """n_step=3: the buffer's n-step rewards and ``steps_to_next_obs`` (fewer steps at an episode's
    end); TorchRL's path and the fused one both discount the bootstrap by gamma ** steps."""
    g = torch.Generator().manual_seed(3)
    n, t = 2, 10
    done = torch.zeros(n, t, 1, dtype=torch.bool)
    done[0, 4] = True  # env 0's episode terminates at step 4
    roll = TensorDict(
        {
            "observation": torch.randn(n, t, 3, generator=g),
            "action": LOW + (HIGH - LOW) * torch.rand(n, t, 2, generator=g),
            "next": {
                "observation": torch.randn(n, t, 3, generator=g),
                "reward": torch.randn(n, t, 1, generator=g),
                "terminated": done.clone(),
                "truncated": torch.zeros(n, t, 1, dtype=torch.bool),
                "done": done.clone(),
            },
        },
        [n, t],
    )
    states = []
    for compile_ in ("false", "auto"):
        algo = _sac(tmp_path / compile_, n_step=3, compile=compile_)
        algo.replay.extend(roll)
        sample = algo.replay.sample(B)
        steps = sample["steps_to_next_obs"]
        assert steps.min() >= 1 and steps.max() == 3 and (steps < 3).any()  # both kinds drawn
        torch.manual_seed(4)
        out = algo._gradient_step(sample)
        states.append((out, algo.loss.state_dict()))
    (a, sa), (b, sb) = states
    assert a["loss/qvalue"].item() == pytest.approx(b["loss/qvalue"].item(), rel=1e-5)
    for key, value in sa.items():
        torch.testing.assert_close(sb[key], value, rtol=1e-5, atol=1e-6, msg=key)
