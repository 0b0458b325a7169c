"""Every field of the schema has a rule; each rule refuses what it should, naming the key."""

from __future__ import annotations

import dataclasses
import typing
from pathlib import Path

import pytest

from conftest import REPO, compose
from rlexp.config.rules import FIELD_RULES, rules_markdown
from rlexp.config.schema import RootConfig
from rlexp.config.validate import ConfigError, to_root_config

#: Sections checked by building them, not field by field.
BUILT_SECTIONS = ("env.kwargs", "env.native", "events.train", "events.eval")


def _fields(tp):
    """The fields of ``tp`` and of every schema a section typed ``tp`` may hold (GRPO's, PPO's)."""
    from rlexp.config.schema import VARIANTS

    seen = {f.name: f for f in dataclasses.fields(tp)}
    for variants in VARIANTS.values():
        for cls in variants.values():
            if issubclass(cls, tp) and cls is not tp:
                seen.update({f.name: (f, cls) for f in dataclasses.fields(cls)})
    for f in seen.values():
        yield (f if isinstance(f, tuple) else (f, tp))


def _leaves(tp, prefix=""):
    for f, owner in _fields(tp):
        key = f"{prefix}{f.name}"
        hint = typing.get_type_hints(owner)[f.name]
        inner = [a for a in typing.get_args(hint) if a is not type(None)] or [hint]
        if key not in BUILT_SECTIONS and dataclasses.is_dataclass(inner[0]):
            yield from _leaves(inner[0], key + ".")
        else:
            yield key


def test_every_field_of_the_schema_has_a_rule():
    leaves = list(_leaves(RootConfig))
    assert sorted(leaves) == sorted(FIELD_RULES), set(leaves) ^ set(FIELD_RULES)


def test_the_docs_table_is_the_rules():
    assert rules_markdown() in (REPO / "docs" / "config_rules.md").read_text()


BAD = {
    "trainer.total_frames": 0,
    "trainer.iterations": 0,
    "trainer.frames_per_batch": 0,
    "trainer.eval_every": -1,
    "trainer.eval_episodes": -3,
    "trainer.save_every": -1,
    "trainer.best_metric": "eval/reward",
    "trainer.log_every": 0,
    "trainer.torch_threads": 100000,
    "policy.name": "transformer",
    "policy.actor.hidden_sizes": "[64,0]",
    "policy.critic.hidden_sizes": "[-1]",
    "policy.min_log_std": -50.0,
    "policy.max_log_std": 50.0,
    "algorithm.name": "dqn",
    "algorithm.gamma": 1.5,
    "algorithm.lmbda": -0.1,
    "algorithm.clip_epsilon": 0.0,
    "algorithm.entropy_coeff": -0.01,
    "algorithm.critic_coeff": -1.0,
    "algorithm.loss_critic_type": "huber",
    "algorithm.clip_value": 0.0,
    "algorithm.lr": -1e-4,  # 0 is allowed: a policy that does not learn (a baseline)
    "algorithm.adam_eps": -1e-8,
    "algorithm.num_epochs": 0,
    "algorithm.mini_batch_size": 0,
    "algorithm.compile": "maybe",
    "env.backend": "brax",
    "env.num_envs": 0,
    "env.num_eval_envs": -1,
    "env.max_episode_steps": 0,
    "env.clip_observations": 0.0,
    "logger.wandb.project": "a/b",
    "logger.wandb.mode": "sometimes",
    "logger.wandb.tags": "['']",
    "seed": -1,
}


@pytest.mark.parametrize("key", sorted(BAD))
def test_a_bad_value_is_refused_naming_the_key(key):
    with pytest.raises(ConfigError) as err:
        to_root_config(compose([f"{key}={BAD[key]}"]))
    assert str(err.value).startswith(f"{key}="), str(err.value)


def test_rules_between_fields():
    with pytest.raises(ConfigError, match="policy.init_log_std=3.0 must be in"):
        to_root_config(compose(["policy.init_log_std=3.0"]))
    with pytest.raises(ConfigError, match="policy.min_log_std=1.0 must be below"):
        to_root_config(compose(["policy.min_log_std=1.0", "policy.max_log_std=1.0"]))


def test_render_mode_human_without_a_display_is_refused(monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    with pytest.raises(ConfigError, match="env.kwargs.render_mode='human' cannot work here"):
        to_root_config(compose(["+env.kwargs.render_mode=human"]))


def test_the_defaults_pass():
    for env in sorted(p.stem for p in (Path(REPO) / "conf" / "env").glob("*.yaml")):
        named = ["env.name=Acrobot-v1"] if env == "gym" else []  # env=gym: the user names the id
        to_root_config(compose([f"env={env}", *named]))
