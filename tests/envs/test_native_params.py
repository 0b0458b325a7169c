"""Native task term parameters: every one has a rule (and a row in docs/native_tasks.md), and a bad
one fails when the env is built, naming the term's key and the value."""

from __future__ import annotations

import inspect
import re
import subprocess
import sys

import pytest

from conftest import REPO
from rlexp.envs.native import (
    ACTIONS,
    EVENTS,
    OBSERVATIONS,
    REWARDS,
    TASKS,
    default_task_config,
    make_native_env,
)


def _set(section: str, key: str, **params):
    def change(cfg):
        getattr(cfg, section)[key].params.update(params)

    return change


BAD = [
    ("push_cube", _set("rewards", "goal_distance_reward", sigma=0), ValueError, "rewards.goal_distance_reward.params.sigma=0 must be a finite number > 0"),
    ("push_cube", _set("rewards", "goal_distance_reward", sigma=float("nan")), ValueError, "params.sigma=nan must be a finite number"),
    ("push_cube", _set("rewards", "goal_distance_reward", sigm=0.1), TypeError, "params.sigm: unknown parameter(s) ['sigm'] for distance_to_target; it accepts"),
    ("push_cube", _set("rewards", "goal_distance_reward", exponential="yes"), TypeError, "params.exponential='yes' must be true or false"),
    ("push_cube", _set("rewards", "reaching_reward", distance_scale=-8.0), ValueError, "rewards.reaching_reward.params.distance_scale=-8.0 must be a finite number > 0"),
    ("push_cube", _set("rewards", "reaching_reward", behind_offset=-0.1), ValueError, "params.behind_offset=-0.1 must be a finite number >= 0"),
    ("push_cube", _set("rewards", "reaching_reward", object_cfg={"uid": "cub"}), KeyError, "params.object_cfg.uid='cub' is not a rigid object of push_cube; choose from ['cube']; did you mean 'cube'?"),
    ("push_cube", _set("rewards", "reaching_reward", object_cfg={"uid": "cube", "typ": 1}), KeyError, "params.object_cfg.typ is not a key"),
    ("push_cube", _set("rewards", "reaching_reward", part_name="hand"), KeyError, "params.part_name='hand' is not a control part of push_cube"),
    ("push_cube", lambda c: setattr(c.rewards["success_bonus"], "weight", float("inf")), ValueError, "rewards.success_bonus.weight=inf must be a finite number"),
    ("push_cube", _set("events", "randomize_cube", position_range=[[0.2, 0, 0], [-0.2, 0, 0]]), ValueError, "events.randomize_cube.params.position_range=[[0.2, 0, 0], [-0.2, 0, 0]] must be [[x, y, z], [x, y, z]] (finite numbers, low <= high on every axis): x low 0.2 > high -0.2"),
    ("push_cube", _set("events", "randomize_goal", position_range=[[0, 0], [1, 1]]), ValueError, "events.randomize_goal.params.position_range[0]=[0, 0] must be [x, y, z] (3 values, got 2)"),
    ("push_cube", _set("events", "randomize_goal", relative_position=1), TypeError, "params.relative_position=1 must be true or false"),
    ("push_cube", lambda c: setattr(c.events["randomize_goal"], "interval_step", 0), ValueError, "events.randomize_goal.interval_step=0 must be an integer >= 1"),
    ("push_cube", _set("actions", "delta_qpos", scale=0), ValueError, "actions.delta_qpos.params.scale=0 must be a finite number > 0"),
    ("push_cube", _set("actions", "delta_qpos", scal=0.1), TypeError, "unknown parameter(s) ['scal'] for DeltaQposTerm; it accepts ['scale', 'part_name']; did you mean 'scale'?"),
    ("push_cube", _set("observations", "robot_qpos", joint_ids=[0, 1, 9]), ValueError, "observations.robot_qpos.params.joint_ids=[0, 1, 9]: joint index 9 is out of range (the task has 6"),
    ("push_cube", _set("observations", "robot_qpos", joint_ids=[0, 0]), ValueError, "has repeated joint indices"),
    ("push_cube", _set("observations", "robot_qpos", range=[1, 0]), ValueError, "params.range=[1, 0] must be [low, high] with low < high: low 1 > high 0"),
    ("push_cube", _set("observations", "robot_qpos", limit="qvel_limits"), ValueError, "params.limit='qvel_limits' must be one of ['qpos_limits']"),
    ("push_cube", _set("observations", "robot_ee_pos", position_only="no"), TypeError, "params.position_only='no' must be true or false"),
    ("push_cube", lambda c: c.extensions.update(success_threshold=0), ValueError, "env.native.extensions.success_threshold=0 must be a finite number > 0"),
    ("push_cube", lambda c: c.scene.update(cube_mass=0.0), ValueError, "env.native.scene.cube_mass=0.0 must be a finite number > 0 (kg)"),
    ("push_cube", lambda c: c.scene.update(cube_size=[0.1, 0.1, -0.1]), ValueError, "env.native.scene.cube_size=[0.1, 0.1, -0.1] must be [x, y, z] (finite numbers, each > 0; m, full edge lengths): z=-0.1"),
    ("push_cube", lambda c: c.scene.update(cube_friction=[0.8, -1]), ValueError, "env.native.scene.cube_friction[1]=-1 must be a finite number >= 0"),
    ("push_cube", lambda c: c.scene.update(init_qpos=[0, 0, 0, 0, 0, 9]), ValueError, "env.native.scene.init_qpos=[0.0, 0.0, 0.0, 0.0, 0.0, 9.0]: wrist_3_joint=9 is outside the joint's range"),
    ("push_cube", lambda c: c.scene.update(init_qpos=[0, 0, 0, 0, 0, "x"]), TypeError, "env.native.scene.init_qpos[5]='x' must be a number"),
    ("cart_pole", _set("events", "randomize_start", position_range=[0.05, -0.05]), ValueError, "events.randomize_start.params.position_range=[0.05, -0.05] must be [low, high] with low <= high: low 0.05 > high -0.05"),
    ("cart_pole", _set("events", "randomize_start", joint_ids=[2]), ValueError, "events.randomize_start.params.joint_ids=[2]: joint index 2 is out of range (the task has 2: ['slider_to_cart', 'cart_to_pole'])"),
    ("cart_pole", _set("events", "randomize_start", velocity_range=[0.1]), ValueError, "params.velocity_range=[0.1] must be [low, high] (2 values, got 1)"),
    ("cart_pole", _set("rewards", "upright", joint_ids=[]), TypeError, "rewards.upright.params.joint_ids=[] must be a non-empty list"),
    ("cart_pole", _set("rewards", "velocity_penalty", part_name="leg"), KeyError, "params.part_name='leg' is not a control part of cart_pole; choose from ['arm', 'hand']"),
    ("cart_pole", lambda c: c.extensions.update(pole_angle_limit=-0.4), ValueError, "env.native.extensions.pole_angle_limit=-0.4 must be a finite number > 0 (rad)"),
]  # fmt: skip


@pytest.mark.parametrize(("task", "change", "kind", "message"), BAD)
def test_bad_term_params_fail_at_build_naming_the_key(task, change, kind, message):
    cfg = default_task_config(task)
    change(cfg)
    with pytest.raises(kind) as err:
        make_native_env(cfg, 1, seed=0)
    assert message in str(err.value.args[0]), err.value.args[0]


def test_a_reset_event_that_fails_when_fired_is_named():
    cfg = default_task_config("push_cube")
    cfg.events["randomize_goal"].params.update(relative_position=True, store_key="elsewhere")
    with pytest.raises(KeyError) as err:
        make_native_env(cfg, 1, seed=0)
    assert err.value.args[0].startswith(
        "events.randomize_goal: target pose 'elsewhere' is not stored"
    )


def _doc_rows() -> dict[tuple[str, str], str]:
    rows = {}
    for line in (REPO / "docs" / "native_tasks.md").read_text().splitlines():
        m = re.match(r"\| `(\w+)`( extensions)? \| `(\w+)` \| [^|]* \| (.*?) \|$", line)
        if m:
            rows[(m.group(1), m.group(3))] = m.group(4)
    return rows


def test_every_term_parameter_has_a_rule_and_a_docs_row():
    rows = _doc_rows()
    expected = set()
    for registry in (EVENTS, OBSERVATIONS, REWARDS, ACTIONS):
        for name in registry.names():
            func = registry.get(name)
            target = func.__init__ if isinstance(func, type) else func
            skip = 2 if isinstance(func, type) or registry is EVENTS else 1
            names = list(inspect.signature(target).parameters)[skip:]
            if name == "normalize_robot_joint_data":  # mode modify: (env, data, ...)
                names = names[1:]
            assert list(func.PARAMS) == names, f"{name}: rules {list(func.PARAMS)} != {names}"
            for key, rule in func.PARAMS.items():
                assert rows.get((name, key)) == rule.text, f"docs/native_tasks.md row {name}.{key}"
                expected.add((name, key))
    for name in TASKS.names():
        task = TASKS.get(name)
        assert set(task.extension_rules) == set(task.extensions)
        for key, rule in task.extension_rules.items():
            assert rows.get((name, key)) == rule.text
            expected.add((name, key))
    assert set(rows) == expected


def test_the_package_imports_without_mujoco_or_torch():
    """``rlexp.envs.native.render.gl_problem`` must be askable before anything imports MuJoCo."""
    code = (
        "import sys; from rlexp.envs.native.render import gl_problem; gl_problem(); "
        "import rlexp.envs.native as n; n.EVENTS; "
        "print(sorted(m for m in ('mujoco', 'torch', 'torchrl') if m in sys.modules))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        check=True,
        env={"PYTHONPATH": str(REPO / "src"), "PATH": "/usr/bin:/bin"},
    )
    assert out.stdout.strip() == "[]", out.stderr
