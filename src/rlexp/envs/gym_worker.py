"""What runs inside a ``gymnasium_async`` worker process: the env, built there, behind a wrapper
that flattens its observations (``spaces.py``, so shared memory holds one float32 vector per copy,
or with images a Dict of that vector and uint8 ``[C, H, W]`` images; ``env.frame_stack`` stacks
them here, per copy; ``env.observation_indices`` keeps chosen Box entries here),
drops the per-step infos (rlexp reads none of them: less to pickle through the pipe), and answers
the adapter's checkpoint calls (``env_state.copy_state`` / ``restore_copy``, run in the worker).

No torch here: each worker imports this module, and torch would cost every worker a second and
~200 MB.
"""

from __future__ import annotations

import functools
import os
import signal
from typing import Any

import gymnasium as gym
import numpy as np

from rlexp.envs.env_state import copy_state, env_state_kind, restore_copy
from rlexp.envs.gym_ids import mujoco_build_warnings
from rlexp.envs.images import encoded_space
from rlexp.envs.masks import MaskSpec
from rlexp.envs.spaces import frame_stacked, obs_layout
from rlexp.runtime.signals import STOP_SIGNALS, die_with_parent
from rlexp.runtime.user_code import describe

#: Blocked while the workers start (``gym_async``: ``signals.blocked``), unblocked in each worker.
HELD_SIGNALS = STOP_SIGNALS


class WorkerEnvError(RuntimeError):
    """What user code raised in a worker, as one line (its type, message and place): an exception
    class Gymnasium cannot rebuild from its value alone (numpy's ``_ArrayMemoryError`` wants a
    shape and a dtype) came back as a garbled ``TypeError``, and ``SystemExit`` ended the worker."""


def _die_with_parent(training_pid: int) -> None:
    """SIGKILL this worker when its parent (the forkserver, or the training process) ends, even
    where an env step hangs and the closed pipe is never read; either gone already: end now."""
    die_with_parent(os.getppid())
    try:
        os.kill(training_pid, 0)
    except ProcessLookupError:
        os._exit(1)
    except PermissionError:
        pass


def _plain_errors(fn: Any) -> Any:
    """``fn``, with whatever it raises (``SystemExit`` and ``KeyboardInterrupt`` too) turned into
    one :class:`WorkerEnvError` that pickles and rebuilds as it is."""

    @functools.wraps(fn)
    def wrapped(*args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except WorkerEnvError:
            raise
        except BaseException as exc:
            raise WorkerEnvError(describe(exc)) from None

    return wrapped


def make_worker_env(
    env_id: str,
    kwargs: dict,
    parent_pid: int,
    image_keys: tuple = (),
    frame_stack: int = 0,
    mask: MaskSpec | None = None,
    observation_indices: tuple = (),
) -> WorkerEnv:
    """Build the env in a worker (``AsyncVectorEnv`` also calls this once in the training process,
    ``parent_pid``, for the spaces). ``module:EnvId`` imports its module here; an id an rlexp
    plugin registers needs the plugins loaded here too."""
    if os.getpid() != parent_pid:
        # A worker leads a process group of its own: Ctrl-C (SIGINT to the terminal's process
        # group) and ``kill -TERM -PGID`` are the training process's to handle; it finishes its
        # iteration, checkpoints and closes the workers. A worker still exits when its pipe closes.
        # It started with the stop signals blocked (``gym_async``, ``signals.blocked``): one that came
        # before this point was meant for the training process; SIGINT stays ignored here.
        os.setpgrp()
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.pthread_sigmask(signal.SIG_UNBLOCK, HELD_SIGNALS)
        _die_with_parent(parent_pid)
    if ":" not in env_id and env_id not in gym.registry:
        from rlexp.plugins import load_plugins

        load_plugins()
    return WorkerEnv(None, env_id, kwargs, image_keys, frame_stack, mask, observation_indices)


class WorkerEnv(gym.Wrapper):
    """A worker's env as the adapter drives it: flat float32 observations, no infos, and the
    ``rlexp_*`` calls (``AsyncVectorEnv.call`` / ``get_attr`` / ``set_attr``) for resume."""

    def __init__(
        self,
        env: gym.Env | None,
        env_id: str,
        kwargs: dict | None = None,
        image_keys: tuple = (),
        frame_stack: int = 0,
        mask: MaskSpec | None = None,
        observation_indices: tuple = (),
    ) -> None:
        self.env_id = env_id
        self.kwargs = dict(kwargs or {})
        self._stacking = (tuple(image_keys), int(frame_stack))
        super().__init__(env if env is not None else self._make())
        self.layout = obs_layout(
            self.env.observation_space,
            self._where,
            *self._stacking,
            mask,
            indices=tuple(observation_indices),
        )
        # what shared memory holds: the flat vector, or a Dict of it and the uint8 CHW images
        self.observation_space = encoded_space(self.layout)
        self.kind = env_state_kind(self.env)
        if self.layout.frame_stack > 1:  # the stacked frames live in a wrapper no state covers
            self.kind = "restart"
        self._restored = False

    @_plain_errors
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        obs, info = self.env.reset(seed=seed, options=options or None)
        return self.layout.encode(obs, info), {}

    @_plain_errors
    def step(self, action: Any):
        obs, reward, terminated, truncated, info = self.env.step(action)
        return self.layout.encode(obs, info), reward, terminated, truncated, {}

    @_plain_errors
    def rlexp_remake(self) -> None:
        """Replace the env by one made now (``GymnasiumEnv._set_seed``: a reseeded env starts from
        fresh copies, whatever state the old ones kept across resets)."""
        self.env.close()
        self.env = self._make()
        self._restored = False

    @property
    def _where(self) -> str:
        return f"env.name={self.env_id!r}"

    def _make(self) -> gym.Env:
        """The env as configured: ``gym.make`` of the id and kwargs, frames stacked
        (``env.frame_stack``)."""
        with mujoco_build_warnings(self.env_id):
            env = gym.make(self.env_id, **self.kwargs)
        keys, stack = self._stacking
        return frame_stacked(env, stack, keys, self._where)

    @_plain_errors
    def rlexp_info(self) -> tuple[gym.Space, gym.Space, str]:
        """The env's own observation and action spaces and its ``state_kind``."""
        return self.env.observation_space, self.env.action_space, self.kind

    def rlexp_copy_state(self, kind: str) -> dict | tuple[str, str, str]:
        """This copy's checkpoint entry; an env whose ``get_state()`` fails answers
        ``("error", type name, message)`` instead of raising (an exception ends a worker)."""
        try:
            return copy_state(self.env, kind, self.env_id)
        except Exception as exc:
            return ("error", type(exc).__name__, str(exc))

    @property
    def rlexp_restore(self) -> bool:
        """Whether the last ``(kind, entry)`` set here restored this copy (``restore_copy``)."""
        return self._restored

    @rlexp_restore.setter
    @_plain_errors
    def rlexp_restore(self, value: tuple[str, dict]) -> None:
        kind, entry = value
        self._restored = restore_copy(self.env, entry, kind)

    @_plain_errors
    def rlexp_current_obs(self) -> np.ndarray:
        """The flattened observation of a MuJoCo env's current (restored) state."""
        return self.layout.encode(self.env.unwrapped._get_obs())
