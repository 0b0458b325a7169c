"""What each network reads (policy.actor.observations / policy.critic.observations, issue #47): the
selection by key, key prefix and group, the defaults (actor: group "policy"; critic: every group),
the critic-only perturbation test, images beside vectors with shared and separate encoders, the
one-line refusals, state_dict round trips, and the layout comparison of old checkpoints."""

from __future__ import annotations

import copy
import dataclasses
import os

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Bounded, MultiCategorical

from conftest import PLAIN_PPO, REPO, compose, run_train
from fused_parity import assert_same, update_both
from rlexp.algorithms.ppo import make_algorithm
from rlexp.checkpoint import latest_checkpoint, load_checkpoint
from rlexp.config.schema import (
    ActorOnlyConfig,
    AlgorithmConfig,
    EncoderConfig,
    MLPConfig,
    PolicyConfig,
)
from rlexp.config.validate import ConfigError, to_root_config
from rlexp.envs.layout_check import check_layout
from rlexp.envs.spaces import ObsLayout, ObsPart
from rlexp.policies.actor_critic import make_policy
from rlexp.policies.inputs import layout_of
from rlexp.policies.numpy_sampler import numpy_sampler

TESTS = REPO / "tests"

#: joint/pos [0:3], joint/vel [3:5], cmd [5:6] (group policy); priv/cube_vel [6:9],
#: priv/goal_offset [9:11] (group critic): push_cube's privileged critic, in small.
GROUPED = ObsLayout(
    "Dict",
    (
        ObsPart("cmd", "box", (1,), 0, 1),
        ObsPart("joint/pos", "box", (3,), 1, 3),
        ObsPart("joint/vel", "box", (2,), 4, 2),
        ObsPart("priv/cube_vel", "box", (3,), 6, 3, group="critic"),
        ObsPart("priv/goal_offset", "box", (2,), 9, 2, group="critic"),
    ),
    11,
)
ACTOR_COLUMNS = [0, 1, 2, 3, 4, 5]
CRITIC_ONLY = [6, 7, 8, 9, 10]
ACT = 2


def _spec():
    return Bounded(-1.0, 1.0, shape=(ACT,))


def _policy(cfg=None, layout=GROUPED, seed=0, nvec=None):
    torch.manual_seed(seed)
    cfg = cfg or PolicyConfig(init_log_std=-0.4)
    spec = MultiCategorical(nvec=list(nvec)) if nvec else _spec()
    pol = make_policy(cfg, layout.dim, len(nvec) if nvec else ACT, spec, nvec=nvec, layout=layout)
    # a normaliser with statistics of its own per dimension (not the identity)
    pol.normalizer.update(torch.randn(256, layout.dim) * torch.linspace(0.5, 3.0, layout.dim) + 2)
    return pol


def _obs(n=5, dim=11, seed=1):
    return torch.randn(n, dim, generator=torch.Generator().manual_seed(seed)) * 2


def _keys(parts):
    return [p["key"] for p in parts]


def test_defaults_the_actor_reads_group_policy_the_critic_every_group():
    pol = _policy()
    assert _keys(pol.actor_input_parts) == ["cmd", "joint/pos", "joint/vel"]
    assert _keys(pol.critic_input_parts) == [p.key for p in GROUPED.parts]
    assert (
        pol.critic_input_parts[3]["group"] == "critic" and "group" not in pol.actor_input_parts[0]
    )
    assert pol.actor_net.mlp[0].in_features == 6 and pol.critic_net.mlp[0].in_features == 11
    assert not pol.obs_structured
    # the actor's input is the normalised observation's columns of group policy
    x = _obs()
    want = pol.actor_net.mlp(pol.normalizer(x)[:, ACTOR_COLUMNS])
    torch.testing.assert_close(pol.actor_net(x)[0], want, rtol=0, atol=0)


@pytest.mark.parametrize("nvec", [None, (3, 4)])
def test_perturbing_only_the_critics_observations_leaves_the_actor_bit_identical(nvec):
    """Issue #47: the critic-only parts changed (by a lot), the actor's distribution parameters,
    its deterministic and sampled actions and their log-probabilities are bit-identical, the
    critic's value is not."""
    pol = _policy(nvec=nvec)
    x = _obs()
    y = x.clone()
    y[:, CRITIC_ONLY] += torch.linspace(-5.0, 7.0, len(CRITIC_ONLY))
    a, b = pol.actor_net(x), pol.actor_net(y)
    pairs = zip(a, b, strict=True) if isinstance(a, tuple) else [(a, b)]
    assert all(torch.equal(u, v) for u, v in pairs)
    for deterministic in (True, False):
        torch.manual_seed(7)
        out_x = pol.sampling_policy(deterministic).sample(x)
        torch.manual_seed(7)
        out_y = pol.sampling_policy(deterministic).sample(y)
        assert all(torch.equal(u, v) for u, v in zip(out_x, out_y, strict=True))
    # the TorchRL modules the loss uses
    td_x = TensorDict({"observation": x}, batch_size=[5])
    td_y = TensorDict({"observation": y}, batch_size=[5])
    keys = pol.actor_net.dist_keys
    ax, ay = pol.actor.get_dist_params(td_x.clone()), pol.actor.get_dist_params(td_y.clone())
    assert all(torch.equal(ax[k], ay[k]) for k in keys)
    vx, vy = pol.critic(td_x.clone())["state_value"], pol.critic(td_y.clone())["state_value"]
    assert (vx - vy).abs().min() > 0  # every row's value moved
    # and perturbing what the actor reads does move it
    z = x.clone()
    z[:, 2] += 3.0
    first = pol.actor_net(z)
    first = first[0] if isinstance(first, tuple) else first
    assert not torch.equal(first, a[0] if isinstance(a, tuple) else a)


def test_the_numpy_sampler_reads_the_actors_columns():
    pol = _policy()
    x = _obs(n=3)
    sampler = pol.sampling_policy().sampler()
    assert hasattr(sampler, "arrays")  # the numpy form applies to a gathered flat input
    torch.manual_seed(2)
    loc, _, action, logp = sampler(x)
    torch.manual_seed(2)
    loc_t, _, action_t, logp_t = pol.actor_net.sampler(False, list(pol.actor_net.mlp))(x)
    torch.testing.assert_close(loc, loc_t)
    torch.testing.assert_close(action, action_t)
    torch.testing.assert_close(logp, logp_t)
    y = x.clone()
    y[:, CRITIC_ONLY] = 100.0
    torch.manual_seed(2)
    assert torch.equal(sampler(y)[0], loc)


@pytest.mark.parametrize(
    ("names", "keys"),
    [
        (["joint/vel", "cmd"], ["cmd", "joint/vel"]),  # keys, in layout order
        (["joint"], ["joint/pos", "joint/vel"]),  # a prefix at a "/" boundary
        (["critic"], ["priv/cube_vel", "priv/goal_offset"]),  # a group
        (["priv/goal_offset", "policy"], ["cmd", "joint/pos", "joint/vel", "priv/goal_offset"]),
    ],
)
def test_selection_by_key_prefix_and_group(names, keys):
    cfg = PolicyConfig(
        actor=MLPConfig(hidden_sizes=[8], observations=names),
        critic=MLPConfig(hidden_sizes=[8], observations=names),
    )
    pol = _policy(cfg)
    assert _keys(pol.actor_input_parts) == keys == _keys(pol.critic_input_parts)
    columns = [
        i for p in GROUPED.parts if p.key in keys for i in range(p.offset, p.offset + p.size)
    ]
    x = _obs()
    want = pol.critic_net.mlp(pol.normalizer(x)[:, columns])
    torch.testing.assert_close(pol.critic_net(x), want, rtol=0, atol=0)


def test_grpos_actor_only_reads_the_actors_selection():
    cfg = ActorOnlyConfig(actor=MLPConfig(observations=["priv/cube_vel", "cmd"]))
    pol = _policy(cfg)
    assert pol.critic_net is None and pol.critic_input_parts == []
    assert _keys(pol.actor_input_parts) == ["cmd", "priv/cube_vel"]
    assert pol.actor_net.mlp[0].in_features == 4


@pytest.mark.parametrize(
    ("names", "words"),
    [
        (["joint/pos", "jiont"], "'jiont' names no observation of this env"),
        (["join"], "'join' names no observation"),  # a prefix only at a "/" boundary
        (["privv"], "did you mean 'priv'?"),
        ([], "policy.actor.observations=[] selects no observation"),
    ],
)
def test_an_unknown_name_or_an_empty_selection_is_one_line(names, words):
    cfg = PolicyConfig(actor=MLPConfig(observations=names))
    with pytest.raises(ValueError) as err:
        _policy(cfg)
    msg = str(err.value)
    assert len(msg.splitlines()) == 1 and words in msg, msg
    assert msg.startswith("policy.actor.observations=")
    assert "'joint/vel'" in msg and "groups ['critic', 'policy']" in msg


def test_an_env_without_the_actors_default_group_is_one_line():
    layout = ObsLayout("Dict", (ObsPart("s", "box", (2,), 0, 2, group="critic"),), 2)
    with pytest.raises(
        ValueError, match=r"^policy.actor.observations=null reads group \['policy'\]"
    ):
        _policy(layout=layout)


def test_an_empty_list_in_the_config_is_refused_naming_the_key():
    with pytest.raises(ConfigError) as err:
        to_root_config(compose(["policy.critic.observations=[]"]))
    assert str(err.value).startswith("policy.critic.observations=[] must be null")


#: the image part: a 3x40x36 frame at the root ("pixels"), and one under "wrist" (group critic)
IMAGES = ObsLayout(
    "Dict",
    (
        ObsPart("", "image", (3, 40, 36), -1, 0, image_key="pixels", source_layout="hwc"),
        ObsPart("proprio", "box", (4,), 0, 4),
        ObsPart("priv", "box", (2,), 4, 2, group="critic"),
        ObsPart("wrist", "image", (1, 36, 36), -1, 0, group="critic", image_key="wrist"),
    ),
    6,
)
ENC = EncoderConfig(channels=[8, 16], kernel_sizes=[8, 4], strides=[4, 2], features_dim=24)


def _image_obs(n=4, seed=3):
    g = torch.Generator().manual_seed(seed)
    return TensorDict(
        {
            "vector": torch.randn(n, 6, generator=g),
            "pixels": torch.randint(0, 256, (n, 3, 40, 36), dtype=torch.uint8, generator=g),
            "wrist": torch.randint(0, 256, (n, 1, 36, 36), dtype=torch.uint8, generator=g),
        },
        batch_size=[n],
    )


def test_images_and_vectors_combined_with_a_shared_encoder():
    pol = _policy(PolicyConfig(encoder=ENC), layout=IMAGES)
    assert pol.obs_structured
    actor_enc = pol.actor_net.inputs.encoders
    critic_enc = pol.critic_net.inputs.encoders
    assert list(actor_enc) == ["pixels"] and list(critic_enc) == ["pixels", "wrist"]
    assert actor_enc["pixels"] is critic_enc["pixels"]  # shared: one module, both losses train it
    assert pol.actor_net.mlp[0].in_features == 4 + 24
    assert pol.critic_net.mlp[0].in_features == 6 + 24 + 24
    obs = _image_obs()
    norm = pol.normalizer(obs["vector"])
    want = pol.critic_net.mlp(
        torch.cat(
            [norm, critic_enc["pixels"](obs["pixels"]), critic_enc["wrist"](obs["wrist"])], -1
        )
    )
    torch.testing.assert_close(pol.critic_net(obs), want, rtol=0, atol=0)
    loc = pol.actor_net(obs)[0]
    want = pol.actor_net.mlp(torch.cat([norm[:, :4], actor_enc["pixels"](obs["pixels"])], -1))
    torch.testing.assert_close(loc, want, rtol=0, atol=0)
    # the critic's image and vector change; the actor's output does not
    other = obs.clone()
    other["wrist"] = 255 - other["wrist"]
    other["vector"][:, 4:] += 3.0
    assert torch.equal(pol.actor_net(other)[0], loc)
    assert not torch.equal(pol.critic_net(other), pol.critic_net(obs))
    # the collection sampler and TorchRL's modules take the TensorDict observation as it is
    td = TensorDict({"observation": obs}, batch_size=[4])
    out = pol.sampling_policy(deterministic=True)(td.clone())
    torch.testing.assert_close(out["action"], loc)
    assert pol.critic(td.clone())["state_value"].shape == (4, 1)
    assert numpy_sampler(pol.actor_net, lambda o: o) is None  # images: torch's sampler


def test_share_encoder_false_gives_the_critic_encoders_of_its_own():
    shared = _policy(PolicyConfig(encoder=ENC), layout=IMAGES)
    apart = _policy(PolicyConfig(encoder=ENC, share_encoder=False), layout=IMAGES)
    a, c = apart.actor_net.inputs.encoders, apart.critic_net.inputs.encoders
    assert a["pixels"] is not c["pixels"]
    actor_ids = {id(p) for p in apart.actor_net.parameters()}
    assert not actor_ids & {id(p) for p in c.parameters()}
    n_enc = sum(p.numel() for p in a["pixels"].parameters())
    count = lambda pol: sum(p.numel() for p in pol.parameters())  # noqa: E731
    assert count(apart) == count(shared) + n_enc
    # training the critic's pixel encoder leaves the actor alone
    obs = _image_obs()
    before = apart.actor_net(obs)[0]
    with torch.no_grad():
        for p in c["pixels"].parameters():
            p.add_(0.5)
    assert torch.equal(apart.actor_net(obs)[0], before)


@pytest.mark.parametrize("share", [True, False])
def test_the_critics_loss_reaches_the_actors_encoder_only_when_shared(share):
    pol = _policy(PolicyConfig(encoder=ENC, share_encoder=share), layout=IMAGES)
    pol.critic_net(_image_obs()).square().sum().backward()
    grads = [p.grad for p in pol.actor_net.inputs.encoders["pixels"].parameters()]
    if share:
        assert all(g is not None for g in grads) and any(g.abs().sum() > 0 for g in grads)
    else:
        assert all(g is None for g in grads)
    assert all(p.grad is None for p in pol.actor_net.mlp.parameters())


def test_state_dict_round_trip_of_a_grouped_image_policy():
    for share in (True, False):
        cfg = PolicyConfig(encoder=dataclasses.replace(ENC, name="nature"), share_encoder=share)
        a = _policy(cfg, layout=IMAGES, seed=1)
        b = _policy(cfg, layout=IMAGES, seed=2)
        obs = _image_obs()
        assert not torch.equal(a.critic_net(obs), b.critic_net(obs))
        b.load_state_dict(a.state_dict())  # strict
        assert torch.equal(a.critic_net(obs), b.critic_net(obs))
        assert torch.equal(a.actor_net(obs)[0], b.actor_net(obs)[0])
    # a flat policy keeps the keys it always had (old checkpoints load): nothing of the selection
    keys = _policy(PolicyConfig()).state_dict().keys()
    assert not any("inputs" in k for k in keys) and "actor_net.normalizer.mean" in keys


class _Base:
    def __init__(self, layout):
        self.obs_layout = layout


class _Wrapped:
    def __init__(self, layout):
        self.base_env = _Base(layout)


def test_a_saved_layout_without_groups_compares_as_group_policy():
    old = {"parts": [dict(p.record()) for p in GROUPED.parts], "dim": 11}
    for p in old["parts"]:
        p.pop("group", None)  # a checkpoint from before groups
    check_layout(
        {"parts": [{k: v for k, v in p.items()} for p in old["parts"][:3]], "dim": 6},
        _Wrapped(ObsLayout("Dict", GROUPED.parts[:3], 6)),
        "the checkpoint",
    )
    explicit = {"parts": [{**p.record(), "group": p.group} for p in GROUPED.parts], "dim": 11}
    check_layout(explicit, _Wrapped(GROUPED), "the checkpoint")
    with pytest.raises(ValueError, match="the observation space changed"):
        check_layout(old, _Wrapped(GROUPED), "the checkpoint")  # the critic parts' group differs
    assert "group" not in GROUPED.parts[0].record()
    assert GROUPED.parts[3].record()["group"] == "critic"


def test_layout_of_an_env_without_one():
    """A batched torch env records no layout: one plain part; a Composite spec: vector + images."""
    from torchrl.data import Composite, Unbounded

    class Env:
        observation_spec = Composite(observation=Unbounded(shape=(3, 7)), shape=(3,))

    layout = layout_of(Env())
    assert [(p.key, p.kind, p.size) for p in layout.parts] == [("", "box", 7)] and layout.plain

    class ImageEnv:
        observation_spec = Composite(
            observation=Composite(
                vector=Unbounded(shape=(2, 5)),
                pixels=Bounded(0, 255, shape=(2, 3, 8, 8), dtype=torch.uint8),
                shape=(2,),
            ),
            shape=(2,),
        )

    layout = layout_of(ImageEnv())
    assert layout.structured and layout.dim == 5
    assert [(p.kind, p.image_key, p.shape) for p in layout.parts] == [
        ("box", "", (5,)),
        ("image", "pixels", (3, 8, 8)),
    ]


PYPATH = {"PYTHONPATH": f"{REPO / 'src'}{os.pathsep}{TESTS}"}
DICT_GOAL = [
    "env=gym",
    "env.name=toy_envs:DictGoal-v0",
    "trainer.total_frames=256",
    "trainer.frames_per_batch=128",
    "trainer.eval_every=0",
    "trainer.save_every=0",
    "algorithm.num_epochs=1",
    "trainer.progress=false",
]


def test_a_run_whose_actor_reads_some_keys(tmp_path):
    """DictGoal's observation is phase (one-hot 3), pos (2), target/xy (2): an actor reading
    ``[pos, target]`` has 4 inputs, the critic all 7; the run trains and checkpoints them."""
    run_dir = tmp_path / "run"
    run_train(
        [*DICT_GOAL, f"hydra.run.dir={run_dir}", "policy.actor.observations=[pos,target]"],
        cwd=tmp_path,
        env_extra=PYPATH,
    )
    ckpt = load_checkpoint(latest_checkpoint(run_dir / "checkpoints"))
    assert ckpt["policy"]["actor_net.mlp.0.weight"].shape[-1] == 4
    assert ckpt["policy"]["critic_net.mlp.0.weight"].shape[-1] == 7


def test_an_unknown_key_exits_2_in_one_line_before_the_run_dir(tmp_path):
    run_dir = tmp_path / "run"
    proc = run_train(
        [*DICT_GOAL, f"hydra.run.dir={run_dir}", "policy.critic.observations=[pos,goal]"],
        cwd=tmp_path,
        env_extra=PYPATH,
        check=False,
    )
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr
    assert "policy.critic.observations=['pos', 'goal']: 'goal' names no observation" in lines[0]
    assert "keys ['phase', 'pos', 'target/xy'], groups ['policy']" in lines[0]
    assert not run_dir.exists()


def test_ppo_updates_a_grouped_policy_alike_on_the_fused_and_torchrl_paths():
    """An actor reading group policy and a critic reading every group: the fused minibatch step
    and TorchRL's ClipPPOLoss give the same update; only the critic's first layer has weights for
    the critic-only columns, and they learn."""
    pol = _policy()
    cfg = AlgorithmConfig(
        lr=3e-3, num_epochs=2, mini_batch_size=16, clip_epsilon=0.13, compile="false", **PLAIN_PPO
    )
    ref = make_algorithm(cfg, copy.deepcopy(pol), total_iterations=1_000_000)
    ref.use_fused_step = False
    fused = make_algorithm(cfg, pol, total_iterations=1_000_000)
    gen = torch.Generator().manual_seed(4)
    obs = torch.randn(2, 32, 11, generator=gen)
    with torch.no_grad():
        loc, scale, action, log_prob = pol.sampling_policy().sample(obs)
    done = torch.zeros(2, 32, 1, dtype=torch.bool)
    done[0, 9] = True
    batch = TensorDict(
        {
            "observation": obs,
            "action": action,
            "action_log_prob": log_prob + 0.3 * torch.randn(2, 32, generator=gen),
            "loc": loc,
            "scale": scale,
            "next": {
                "observation": torch.randn(2, 32, 11, generator=gen),
                "reward": torch.randn(2, 32, 1, generator=gen),
                "terminated": done,
                "truncated": torch.zeros_like(done),
                "done": done,
            },
        },
        batch_size=[2, 32],
    )
    first = pol.critic_net.mlp[0].weight.detach().clone()
    got, expected = update_both(fused, ref, batch, 11)
    assert_same(fused, ref, got, expected, tol=1e-6)
    assert (pol.critic_net.mlp[0].weight[:, CRITIC_ONLY] - first[:, CRITIC_ONLY]).abs().max() > 0
