"""Action terms: map the policy's action in [-1, 1] onto actuator controls, for all envs at once."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from rlexp.config.native_task import Number, OrNull, Part
from rlexp.envs.native.registry import Registry

if TYPE_CHECKING:
    from rlexp.envs.native.state import SimState

ACTIONS: Registry = Registry("action term")


@ACTIONS.register(
    params={
        "scale": Number(gt=0, note=" (rad per unit action)"),
        "part_name": OrNull(Part(), "every actuator"),
    }
)
class DeltaQposTerm:
    """Joint position targets ``qpos + scale * action`` for the actuated joints of ``part_name``.

    One action dimension per position actuator of the part; targets are clipped to the actuators'
    control ranges. The target is taken from the measured joint positions, not the previous target.
    """

    def __init__(self, env: SimState, scale: float = 0.1, part_name: str | None = None) -> None:
        self.scale = float(scale)
        self.actuators = env.actuators_of_part(part_name)  # actuator ids, in action order
        self.joint_qpos_adr = env.actuator_qpos_adr[self.actuators]
        ctrlrange = env.model.actuator_ctrlrange[self.actuators]
        limited = env.model.actuator_ctrllimited[self.actuators].astype(bool)
        self.low = np.where(limited, ctrlrange[:, 0], -np.inf)
        self.high = np.where(limited, ctrlrange[:, 1], np.inf)

    @property
    def action_dim(self) -> int:
        return len(self.actuators)

    def __call__(self, env: SimState, action: np.ndarray, ctrl: np.ndarray) -> None:
        """Write the controls for ``action`` [N, A] (already clipped to [-1, 1]) into ``ctrl`` [N, nu]."""
        target = env.qpos[:, self.joint_qpos_adr] + self.scale * action
        np.clip(target, self.low, self.high, out=target)
        ctrl[:, self.actuators] = target
