"""reach_lab's rlexp plugin: rlexp calls ``register()`` once at start-up.

Declared in pyproject.toml::

    [project.entry-points."rlexp.plugins"]
    reach_lab = "reach_lab.plugin:register"

Configs then name what it registers (conf/env/point_reach.yaml, conf/events/eval_history.yaml,
conf/env/grid_reach.yaml): ``env.native.task: point_reach``, ``func: goal_proximity``,
``func: eval_history``, and the Gymnasium id ``env.name: GridReach-v0``.
"""

from __future__ import annotations


def register() -> None:
    """Add PointReach, the goal_proximity reward term and the eval_history event to rlexp, and
    GridReach-v0 to Gymnasium's registry."""
    from rlexp.envs.native import REWARDS, TASKS
    from rlexp.events import register_event

    from reach_lab import gridworld
    from reach_lab.events import EVAL_HISTORY_PARAMS, eval_history
    from reach_lab.task import POINT_REACH
    from reach_lab.terms import GOAL_PROXIMITY_PARAMS, goal_proximity

    TASKS.register("point_reach")(POINT_REACH)
    REWARDS.register("goal_proximity", params=GOAL_PROXIMITY_PARAMS)(goal_proximity)
    register_event(
        "eval_history", params=EVAL_HISTORY_PARAMS, modes=("trigger",), managers=("train",)
    )(eval_history)
    gridworld.register()  # env.name=GridReach-v0 (also registered when the module is imported)
