"""Fires a manager's ``step`` and ``reset`` events from inside the env, as a TorchRL transform.

Added to the training env only when the config has such events, so runs without them pay nothing
per step. ``step`` events are called twice per env step: with ``phase="action"`` on the env's
input (a shallow copy: changing the action there changes what the env executes, not what the
collector stores), and with ``phase="observation"`` on the step's output. ``reset`` events get the
ids of the envs being reset.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from tensordict import TensorDictBase
from torchrl.envs import Transform

from rlexp.events.manager import EventContext, EventManager


class EventTransform(Transform):
    def __init__(self, manager: EventManager, run_dir: Path | None = None) -> None:
        super().__init__(in_keys=[], out_keys=[])
        self.manager = manager
        self.run_dir = run_dir
        self.global_step = 0
        self._step_events = manager.has("step")
        self._reset_events = manager.has("reset")

    def _ctx(self, **kw) -> EventContext:
        return EventContext(
            env=self.parent, global_step=self.global_step, run_dir=self.run_dir, **kw
        )

    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase:
        if self._step_events:
            self.manager.fire("step", self._ctx(tensordict=tensordict, phase="action"))
        return tensordict

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        if self._step_events:
            self.manager.fire("step", self._ctx(tensordict=next_tensordict, phase="observation"))
        return next_tensordict

    def _reset(
        self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase
    ) -> TensorDictBase:
        if not self._reset_events:
            return tensordict_reset
        base = self.parent.base_env
        if getattr(base, "last_reset_was_restore", False):
            # A resumed env hands back its checkpointed episodes: nothing was reset, so no reset
            # events (an uninterrupted run fired none here either).
            return tensordict_reset
        mask = None if tensordict is None else tensordict.get("_reset", None)
        n = int(self.parent.batch_size.numel())
        ids = np.arange(n) if mask is None else np.flatnonzero(mask.reshape(n).cpu().numpy())
        if ids.size:
            self.manager.fire("reset", self._ctx(env_ids=ids, tensordict=tensordict_reset))
            if hasattr(
                base, "current_tensordict"
            ):  # events may have moved objects: fresh observation
                tensordict_reset.set("observation", base.current_tensordict().get("observation"))
        return tensordict_reset
