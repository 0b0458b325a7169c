"""Typed schema of a native (batched MuJoCo) task: the term lists of our users' task files.

The names mirror the JSON task format (``gym_config``) so that the JSON loader maps one onto the other
key by key: ``events``, ``observations``, ``rewards``, ``actions``, ``extensions``, plus ``scene`` for
the parts of the file that shape the MJCF rebuild (cube size / mass / start, initial joint positions).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any


@dataclass
class EventTermConfig:
    """One event term: ``func(env, env_ids, **params)`` fired in ``mode``."""

    func: str = "???"  # registered event function name
    mode: str = "reset"  # startup | reset | interval | step | trigger
    interval_step: int = 1  # for mode=interval: fire every this many calls
    params: dict[str, Any] = field(default_factory=dict)


@dataclass
class ObservationTermConfig:
    """One observation term; its output is stored under ``name`` ("group/key")."""

    func: str = "???"  # registered observation function name
    mode: str = "add"  # add | modify
    name: str = "???"  # "group/key" in the observation dict (flattened with sorted keys)
    params: dict[str, Any] = field(default_factory=dict)


@dataclass
class RewardTermConfig:
    """One reward term; the env's reward is the sum of ``weight * func(...)``."""

    func: str = "???"  # registered reward function name
    mode: str = "add"  # add | replace
    weight: float = 1.0  # multiplies the term
    params: dict[str, Any] = field(default_factory=dict)


@dataclass
class ActionTermConfig:
    """The action term that maps the policy's action to actuator targets."""

    func: str = "DeltaQposTerm"  # registered action term name
    params: dict[str, Any] = field(default_factory=dict)


@dataclass
class NativeTaskConfig:
    """A native task: which MJCF scene (``task``) plus its term configuration."""

    task: str = "???"  # registered native task: push_cube | cart_pole
    events: dict[str, EventTermConfig] = field(default_factory=dict)
    observations: dict[str, ObservationTermConfig] = field(default_factory=dict)
    rewards: dict[str, RewardTermConfig] = field(default_factory=dict)
    actions: dict[str, ActionTermConfig] = field(default_factory=dict)
    extensions: dict[str, Any] = field(default_factory=dict)  # free values, e.g. success_threshold
    scene: dict[str, Any] = field(
        default_factory=dict
    )  # scene overrides (cube size/mass/init_pos, init_qpos)
