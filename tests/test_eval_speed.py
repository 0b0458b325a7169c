"""Evaluation at collector speed (issue #18): the lean loop gives the same numbers as TorchRL's loop
on the same env copies and seed, every round alike; eval events that need each step's tensordict
(step / interval) still run through TorchRL's loop and fire; reset events and a native task's
success rate work on the lean loop."""

from __future__ import annotations

import functools
from pathlib import Path

import pytest
import torch

import rlexp.training.evaluation as evaluation_mod
from conftest import compose
from rlexp.config.validate import to_root_config
from rlexp.envs.factory import make_env
from rlexp.events import register_event
from rlexp.policies.actor_critic import make_policy
from rlexp.training.evaluation import run_episodes

#: (conf/env, copies, episodes, overrides): uneven quotas, terminations, truncations, success.
CASES = [
    ("hopper", 3, 7, []),
    ("half_cheetah", 3, 4, ["env.max_episode_steps=60"]),
    ("cart_pole", 4, 10, ["env.max_episode_steps=40"]),  # some episodes balance: success 0.2
    ("push_cube", 4, 6, ["env.max_episode_steps=30"]),
]


def _no_torchrl_loop(*args, **kwargs):
    raise AssertionError("the lean loop should not call step_and_maybe_reset")


@pytest.mark.parametrize(("name", "copies", "episodes", "overrides"), CASES)
def test_lean_loop_gives_the_torchrl_loops_numbers(name, copies, episodes, overrides):
    e = to_root_config(compose([f"env={name}", *overrides])).env
    torch.manual_seed(0)

    def env():
        return make_env(e, copies, seed=5)

    probe = env()
    policy = make_policy(
        to_root_config(compose()).policy,
        probe.observation_spec["observation"].shape[-1],
        probe.action_spec.shape[-1],
        probe.action_spec,
    ).sampling_policy(deterministic=True)
    reference = run_episodes(env(), policy, episodes, lean=False)
    lean_env = env()
    lean_env.step_and_maybe_reset = _no_torchrl_loop  # the lean loop is really the one taken
    lean = run_episodes(lean_env, policy, episodes)  # lean=None: picked where it applies
    assert lean == reference
    assert reference["eval/episodes"] == episodes
    lean_env.set_seed(5)  # a second round on the same env, reseeded as eval_once does
    assert run_episodes(lean_env, policy, episodes, lean=True) == reference
    if name == "cart_pole":
        assert 0.0 < reference["eval/success_rate"] < 1.0


def test_lean_is_refused_where_it_cannot_apply():
    e = to_root_config(compose(["env=hopper"])).env
    env = make_env(e, 1, seed=0)
    policy = make_policy(
        to_root_config(compose()).policy,
        env.observation_spec["observation"].shape[-1],
        env.action_spec.shape[-1],
        env.action_spec,
    ).sampling_policy(deterministic=True)
    with pytest.raises(ValueError, match="lean=True"):
        run_episodes(env, policy, 1, on_step=lambda td: None, lean=True)


SMALL = [
    "trainer.frames_per_batch=256",
    "trainer.total_frames=256",
    "trainer.eval_every=256",
    "algorithm.num_epochs=1",
    "logger=none",
    "trainer.progress=false",
]


def _trainer(tmp_path: Path, overrides: list[str], eval_events: dict | None = None):
    """A Trainer of a small config; ``eval_events``: name -> (func, mode, params) in events.eval."""
    from rlexp.config.native_task import EventTermConfig
    from rlexp.run.metrics import MetricLogger
    from rlexp.training.build import build

    config = to_root_config(compose([*SMALL, *overrides]))
    for name, (func, mode, params) in (eval_events or {}).items():
        config.events.eval[name] = EventTermConfig(func=func, mode=mode, params=params)
    run_dir = tmp_path / f"run{len(list(tmp_path.iterdir()))}"
    run_dir.mkdir()
    torch.manual_seed(0)
    objects = build(config, run_dir, "cpu", config.trainer.total_frames)
    return objects.trainer(MetricLogger([]), {}, {})


def _torchrl_only(monkeypatch):
    """Make eval_once run TorchRL's loop (today's path before the lean one)."""
    monkeypatch.setattr(evaluation_mod, "run_episodes", functools.partial(run_episodes, lean=False))


@pytest.mark.parametrize(
    "overrides",
    [
        ["env=hopper", "env.num_eval_envs=3", "trainer.eval_episodes=5"],
        ["env=cart_pole", "env.num_eval_envs=4", "env.max_episode_steps=40"],  # 10 episodes
    ],
)
def test_eval_once_takes_the_lean_loop_same_numbers_every_round(tmp_path, monkeypatch, overrides):
    lean = _trainer(tmp_path, overrides)
    lean.eval_env.step_and_maybe_reset = _no_torchrl_loop
    first = lean.eval_once()
    assert lean.eval_once() == first  # each round reseeds: the same policy, the same numbers
    assert set(first) == {
        "eval/episode_return",
        "eval/episode_return_std",
        "eval/episode_length",
    } | ({"eval/success_rate"} if "env=cart_pole" in overrides else set())  # Hopper: no success
    _torchrl_only(monkeypatch)
    assert _trainer(tmp_path, overrides).eval_once() == first
    if "env=cart_pole" in overrides:
        assert 0.0 < first["eval/success_rate"] < 1.0


PROBED: list[tuple[str | None, bool]] = []


@register_event("test_eval_speed_probe")
def _probe(ctx, **params) -> None:
    """Records each call's phase and whether it saw the step's action."""
    PROBED.append((ctx.phase, ctx.tensordict is not None and "action" in ctx.tensordict.keys()))


def test_step_and_interval_eval_events_run_through_torchrl_loop_every_step(tmp_path):
    base = ["env=hopper", "env.num_eval_envs=2", "trainer.eval_episodes=3"]
    plain = _trainer(tmp_path, base).eval_once()
    PROBED.clear()
    trainer = _trainer(
        tmp_path,
        base,
        {
            "probe": ("test_eval_speed_probe", "step", {}),
            "tick": ("test_eval_speed_probe", "interval", {}),
            "noise": ("action_noise", "step", {"std": 0.5}),
        },
    )
    calls: list[int] = []
    step = trainer.eval_env.step_and_maybe_reset

    def counted(td):
        calls.append(1)
        return step(td)

    trainer.eval_env.step_and_maybe_reset = counted
    noisy = trainer.eval_once()
    assert calls and PROBED == [("action", True), (None, True)] * len(calls)
    assert noisy["eval/episode_return"] != plain["eval/episode_return"]  # the noise acted


def test_reset_eval_events_keep_the_lean_loop_and_its_numbers(tmp_path, monkeypatch):
    overrides = ["env=hopper", "env.num_eval_envs=3", "trainer.eval_episodes=4"]
    events = {"physics": ("randomize_physics", "reset", {"mass_range": [0.5, 1.5]})}
    plain = _trainer(tmp_path, overrides).eval_once()
    lean = _trainer(tmp_path, overrides, events)
    lean.eval_env.step_and_maybe_reset = _no_torchrl_loop
    randomised = lean.eval_once()
    assert randomised != plain
    _torchrl_only(monkeypatch)
    assert _trainer(tmp_path, overrides, events).eval_once() == randomised
