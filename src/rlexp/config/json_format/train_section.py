"""The train file's ``trainer``, ``policy`` and ``algorithm`` sections: their keys (PPO_KEYS,
GRPO_KEYS: the format's algorithm keywords -> rlexp's names) and their mapping onto RootConfig
leaves."""

from __future__ import annotations

import math
import re
from typing import Any

from rlexp.config.json_format.leaves import _Mapped
from rlexp.config.json_format.trainer_events import _events
from rlexp.config.json_format.typed_reads import _File, _join
from rlexp.config.schema import VARIANT_OPTIONS

ACTIVATIONS = ("relu", "elu", "tanh", "gelu", "silu", "swish")
POLICIES = ("actor_critic", "actor_only")
ALGORITHMS = ("ppo", "grpo")
#: The format's policy / algorithm name -> the conf/ group option whose schema it is (the schema's).
GROUP_OPTIONS = VARIANT_OPTIONS
NET_TYPES = ("mlp",)
TRAIN_SECTIONS = ("trainer", "policy", "algorithm", "rlexp")
TRAINER_KEYS = (
    "exp_name", "gym_config", "seed", "device", "headless", "gpu_id", "renderer", "enable_rt", "num_envs",
    "iterations", "buffer_size", "rollout_steps", "enable_eval", "num_eval_envs", "num_eval_episodes",
    "eval_freq", "save_freq", "use_wandb", "wandb_project_name", "events",
)  # fmt: skip
#: Trainer keys that choose the simulator's window, GPU and ray tracer: nothing to do on MuJoCo/CPU.
TRAINER_NOT_APPLICABLE = ("headless", "gpu_id", "renderer", "enable_rt")
POLICY_KEYS = ("name", "actor", "critic", "action_dim")
NET_KEYS = ("type", "network_cfg")
NETWORK_CFG_KEYS = ("hidden_sizes", "activation")
ALGORITHM_KEYS = ("name", "cfg")
#: PPO keyword of the format -> AlgorithmConfig field, and the format's default.
PPO_KEYS = {
    "learning_rate": ("lr", 3e-4),
    "n_epochs": ("num_epochs", 10),
    "batch_size": ("mini_batch_size", 64),
    "gamma": ("gamma", 0.99),
    "gae_lambda": ("lmbda", 0.95),
    "clip_coef": ("clip_epsilon", 0.2),
    "ent_coef": ("entropy_coeff", 0.01),
    "vf_coef": ("critic_coeff", 0.5),
    "max_grad_norm": ("max_grad_norm", 0.5),
}
#: GRPO keyword of the format -> GRPOConfig field (None: accepted, unused), and the format's default.
GRPO_KEYS = {
    "learning_rate": ("lr", 3e-4),
    "n_epochs": ("num_epochs", 10),
    "batch_size": ("mini_batch_size", 64),
    "gamma": ("gamma", 0.99),
    "gae_lambda": (None, 0.95),
    "clip_coef": ("clip_epsilon", 0.2),
    "ent_coef": ("entropy_coeff", 0.0),
    "kl_coef": ("kl_coeff", 0.02),
    "group_size": ("group_size", 4),
    "eps": ("epsilon", 1e-8),
    "reset_every_rollout": ("reset_every_rollout", True),
    "truncate_at_first_done": ("truncate_at_first_done", True),
    "max_grad_norm": ("max_grad_norm", 0.5),
}
ALGORITHM_FORMAT_KEYS = {"ppo": PPO_KEYS, "grpo": GRPO_KEYS}
#: What the format's PPO did and has no key for, set explicitly so that rlexp's own PPO defaults
#: (reward scaling, LR annealing: docs/results.md) do not change what a JSON file means.
PPO_FORMAT_FIXED = {"anneal_lr": False, "normalize_rewards": False, "clip_rewards": None}


def _map_trainer(
    tf: _File, gf: _File, t: dict[str, Any], g: dict[str, Any], genv: dict[str, Any], m: _Mapped
) -> None:
    """trainer.*: budget, evaluation, checkpoints, device, W&B, events."""
    out = m.leaves
    out["trainer.exp_name"] = tf.get(t, "exp_name", "trainer", "str", "generic_exp")
    out["seed"] = tf.get(t, "seed", "trainer", "int", 1, low=0)
    device = tf.get(t, "device", "trainer", "str", "cpu")
    if not re.fullmatch(r"auto|cpu|cuda(:\d+)?", device):
        raise tf.error(f"trainer.device={device!r}: choose cpu, cuda, cuda:N (or auto)")
    out["trainer.device"] = device
    kinds = {"headless": "bool", "enable_rt": "bool", "gpu_id": "int", "renderer": "str"}
    for key in TRAINER_NOT_APPLICABLE:
        if key in t:
            tf.get(t, key, "trainer", kinds[key])
            m.not_applicable.append(f"trainer.{key}")

    if "buffer_size" in t and "rollout_steps" in t:
        raise tf.error(
            "trainer.rollout_steps is the older name of trainer.buffer_size: give only buffer_size"
        )
    old = "rollout_steps" in t
    buffer_size = tf.get(
        t, "rollout_steps" if old else "buffer_size", "trainer", "int", 2048, low=1
    )
    if old:
        m.notes.append("trainer.rollout_steps read as trainer.buffer_size (its older name)")

    # num_envs: the train file's, else the task file's (top level, or inside env in older files), else 1
    num_envs, source = 1, None
    for f, d, where in ((gf, genv, "env"), (gf, g, ""), (tf, t, "trainer")):  # the last found wins
        if "num_envs" in d:
            num_envs = f.get(d, "num_envs", where, "int", low=1)
            source = f"{f.shown}: {_join(where, 'num_envs')}"
    if source is not None and "num_envs" not in t:
        m.notes.append(f"num_envs={num_envs} from the task file ({source})")
    out["env.num_envs"] = num_envs
    out["trainer.frames_per_batch"] = buffer_size * num_envs
    out["trainer.iterations"] = tf.get(t, "iterations", "trainer", "int", 250, low=1)

    enable_eval = tf.get(t, "enable_eval", "trainer", "bool", False)
    num_eval_envs = tf.get(t, "num_eval_envs", "trainer", "int", 4, low=1)
    num_eval_episodes = tf.get(t, "num_eval_episodes", "trainer", "int", 5, low=1)
    eval_freq = tf.get(t, "eval_freq", "trainer", "int", 10000, low=0)
    out["env.num_eval_envs"] = num_eval_envs if enable_eval else 0
    out["trainer.eval_every"] = eval_freq if enable_eval else 0
    out["trainer.eval_episodes"] = num_eval_episodes * num_eval_envs
    out["trainer.save_every"] = tf.get(t, "save_freq", "trainer", "int", 50000, low=0)
    out["logger.wandb.enabled"] = tf.get(t, "use_wandb", "trainer", "bool", False)
    if "wandb_project_name" in t:
        out["logger.wandb.project"] = tf.get(t, "wandb_project_name", "trainer", "str")

    events = tf.get(t, "events", "trainer", "object", {})
    events = tf.obj(events, "trainer.events", ("train", "eval"))
    for phase in ("train", "eval"):
        where = f"trainer.events.{phase}"
        out[f"events.{phase}"] = _events(
            tf, tf.get(events, phase, "trainer.events", "object", {}), where
        )


def _named_section(
    tf: _File,
    train: dict[str, Any],
    section: str,
    keys: tuple[str, ...],
    choices: tuple[str, ...],
    m: _Mapped,
) -> dict[str, Any]:
    """The ``policy`` / ``algorithm`` object: its keys checked, its ``name`` one rlexp supports
    (mapped to ``<section>.name``)."""
    obj = tf.obj(tf.get(train, section, "", "object"), section, keys)
    name = tf.get(obj, "name", section, "str", choices=choices)
    m.leaves[f"{section}.name"] = name
    m.groups[section] = GROUP_OPTIONS[section][name]
    return obj


def _map_policy(tf: _File, train: dict[str, Any], m: _Mapped) -> None:
    """policy.*: the actor's (and the actor-critic's critic's) MLP."""
    p = _named_section(tf, train, "policy", POLICY_KEYS, POLICIES, m)
    parts = ("actor", "critic") if m.leaves["policy.name"] == "actor_critic" else ("actor",)
    if "critic" in p and "critic" not in parts:
        m.notes.append(
            "warning: policy.critic is not used: policy.name='actor_only' has no critic (ignored)"
        )
    for part in parts:
        where = f"policy.{part}"
        net = tf.obj(tf.get(p, part, "policy", "object"), where, NET_KEYS)
        tf.get(net, "type", where, "str", "mlp", choices=NET_TYPES)
        cfg = tf.get(net, "network_cfg", where, "object")
        cfg = tf.obj(cfg, f"{where}.network_cfg", NETWORK_CFG_KEYS)
        m.leaves[f"{where}.hidden_sizes"] = tf.get(
            cfg, "hidden_sizes", f"{where}.network_cfg", "ints", low=1
        )
        m.leaves[f"{where}.activation"] = tf.get(
            cfg, "activation", f"{where}.network_cfg", "str", "relu", choices=ACTIVATIONS
        )
    m.action_dim = tf.get(p, "action_dim", "policy", "int", None, low=1)


def _map_algorithm(tf: _File, train: dict[str, Any], m: _Mapped) -> None:
    """algorithm.*: PPO's or GRPO's keyword arguments under rlexp's (TorchRL's) names."""
    a = _named_section(tf, train, "algorithm", ALGORITHM_KEYS, ALGORITHMS, m)
    name = m.leaves["algorithm.name"]
    format_keys = ALGORITHM_FORMAT_KEYS[name]
    c = tf.obj(tf.get(a, "cfg", "algorithm", "object", {}), "algorithm.cfg", tuple(format_keys))
    frames, num_envs = m.leaves["trainer.frames_per_batch"], m.leaves["env.num_envs"]
    if name == "ppo" and m.leaves["policy.name"] != "actor_critic":
        raise tf.error(
            f"algorithm.name='ppo' needs a critic, but policy.name={m.leaves['policy.name']!r} has "
            'none; use policy "actor_critic" (or algorithm "grpo")'
        )
    ranges: dict[str, tuple[str, float | None, float | None]] = {  # kind, low, high (low None: > 0)
        "learning_rate": ("number", 0.0, None),  # 0: a policy that does not learn (a baseline)
        "n_epochs": ("int", 1, None),
        "batch_size": ("int", 1, frames),
        "gamma": ("number", 0.0, 1.0),
        "gae_lambda": ("number", 0.0, 1.0),
        "clip_coef": ("number", None, None),
        "ent_coef": ("number", -math.inf, None),
        "vf_coef": ("number", 0.0, None),
        "max_grad_norm": ("number", -math.inf, None),
        "kl_coef": ("number", 0.0, None),
        "group_size": ("int", 2, None),
        "eps": ("number", None, None),
        "reset_every_rollout": ("bool", None, None),
        "truncate_at_first_done": ("bool", None, None),
    }
    batch = c.get("batch_size")
    if isinstance(batch, int) and not isinstance(batch, bool) and batch > frames:
        raise tf.error(
            f"algorithm.cfg.batch_size={batch} is larger than a rollout: trainer.buffer_size x "
            f"num_envs = {frames // num_envs} x {num_envs} = {frames}"
        )
    for key, (target, default) in format_keys.items():
        kind, low, high = ranges[key]
        positive = low is None and kind == "number"
        value = tf.get(c, key, "algorithm.cfg", kind, default, low, high, positive=positive)
        if target is not None:
            m.leaves[f"algorithm.{target}"] = value
    if name == "ppo":
        m.leaves.update({f"algorithm.{key}": value for key, value in PPO_FORMAT_FIXED.items()})
    group = m.leaves.get("algorithm.group_size")
    if group is not None and num_envs % group:
        raise tf.error(
            f"algorithm.cfg.group_size={group} must divide trainer.num_envs={num_envs}: groups are "
            "blocks of consecutive envs"
        )
