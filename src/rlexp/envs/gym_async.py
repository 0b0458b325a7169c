"""``env.backend=gymnasium_async``: any Gymnasium env, one worker process per copy (Gymnasium's own
``AsyncVectorEnv``), as the same rlexp env as the in-process ``GymnasiumEnv``.

- Observations come back through shared memory, flattened in the workers (``gym_worker.py``);
  autoreset is Gymnasium's ``SAME_STEP`` mode: a finished copy is reset inside the step and its true
  final observation comes in the step's infos, so truncated episodes bootstrap as in-process.
- Same seeding as in-process (copy ``i`` seeded ``seed + i`` at the first full reset, its own RNG
  stream after): the same rollouts, value for value (tested).
- Workers start with ``forkserver`` (``spawn`` where there is none): the training process has torch
  and its thread pools, which ``fork`` copies half-initialised; a forkserver child starts from a
  clean single-threaded process (which has imported Gymnasium, MuJoCo and the main module).
- Resume: exact where the env offers state (MuJoCo integration state, or its
  ``get_state``/``set_state``), saved and restored inside the workers with each copy's RNG and
  time-limit counter; else the documented restart.
- Workers are always closed: by ``close()``, when the env is garbage-collected or the process
  exits; a worker that dies or fails is one error naming it, and the others are closed.
"""

from __future__ import annotations

import builtins
import contextlib
import functools
import logging
import multiprocessing
import multiprocessing.connection
import os
import signal
import weakref
from collections.abc import Iterator

import numpy as np
import torch
from gymnasium.vector import AsyncVectorEnv, AutoresetMode

from rlexp.config.rules import first_line
from rlexp.envs.adapter import GymShapedEnv
from rlexp.envs.gym_ids import check_gym_id, mujoco_build_warnings, render_refusal
from rlexp.envs.gym_worker import HELD_SIGNALS, WorkerEnvError, make_worker_env
from rlexp.envs.images import as_obs
from rlexp.envs.masks import MASK_KEY, MaskSpec, env_mask
from rlexp.envs.spaces import action_coding, obs_layout
from rlexp.runtime.signals import blocked

log = logging.getLogger(__name__)


def start_method() -> str:
    """``forkserver`` where the platform has it (Linux, macOS), else ``spawn``; never ``fork``.
    The forkserver (one per process, started with the first workers) imports Gymnasium and MuJoCo
    once, so that each worker it forks starts with them."""
    if "forkserver" not in multiprocessing.get_all_start_methods():
        return "spawn"
    multiprocessing.get_context("forkserver").set_forkserver_preload(
        ["__main__", "gymnasium", "mujoco"]  # (__main__: multiprocessing's default)
    )
    return "forkserver"


@contextlib.contextmanager
def default_start_method(method: str) -> Iterator[None]:
    """While workers start: ``method`` as multiprocessing's default where the default is not one
    of the standard library's. A worker starts by setting its parent's default start method by
    name, and a local sweep's job runs in a joblib worker whose default, ``loky``, a forkserver
    child does not know."""
    current = multiprocessing.get_start_method(allow_none=True)
    if current in (None, "fork", "spawn", "forkserver"):
        yield
        return
    multiprocessing.set_start_method(method, force=True)
    try:
        yield
    finally:
        multiprocessing.set_start_method(current, force=True)


class WorkerError(RuntimeError):
    """A worker died or its env raised; the message is one line naming the env and the worker."""


def _resolve_mask(env_id: str, kwargs: dict, mode: str, key: str) -> MaskSpec | None:
    """``env.action_mask`` resolved once here, from a copy made in this process (the workers
    get the answer: none of them probes)."""
    if mode == "off":
        return None
    import gymnasium as gym

    make = functools.partial(gym.make, env_id, **kwargs)
    env = make()
    try:
        coding = action_coding(env.action_space, f"env.name={env_id!r}")
        return env_mask(env, make, coding, mode, key, f"env.name={env_id!r}")
    finally:
        env.close()


class AsyncGymnasiumEnv(GymShapedEnv):
    """``num_envs`` copies of a Gymnasium env, each in a worker process, as one TorchRL env."""

    backend = "gymnasium_async"

    def __init__(
        self,
        env_id: str,
        num_envs: int = 1,
        max_episode_steps: int | None = None,
        make_kwargs: dict | None = None,
        image_keys: tuple[str, ...] | list[str] = (),
        frame_stack: int = 0,
        action_mask: str = "auto",
        action_mask_key: str = MASK_KEY,
        observation_indices: tuple[int, ...] | list[int] = (),
    ) -> None:
        check_gym_id(env_id)
        os.environ.setdefault("MUJOCO_GL", "egl")  # (the workers inherit it)
        kwargs = dict(make_kwargs or {})
        if max_episode_steps is not None:
            kwargs["max_episode_steps"] = max_episode_steps
        mask = _resolve_mask(env_id, kwargs, action_mask, action_mask_key)
        kept = tuple(observation_indices)
        make = functools.partial(
            make_worker_env, env_id, kwargs, os.getpid(), tuple(image_keys), frame_stack, mask, kept
        )
        self._where = f"env.name={env_id!r} (env.backend=gymnasium_async)"
        method = start_method()
        # (AsyncVectorEnv builds one copy here for the spaces)
        vec = None
        try:
            # The stop signals blocked meanwhile: the forkserver and the workers start with them
            # blocked (the mask is inherited). A Ctrl-C to the terminal's process group before a
            # worker has left that group (``make_worker_env``) used to kill it with
            # ``KeyboardInterrupt``, and the run failed as a config error (exit 2) instead of
            # stopping (130); now the training process takes it once the workers run.
            held = blocked(HELD_SIGNALS)
            with mujoco_build_warnings(env_id), default_start_method(method), held:
                vec = AsyncVectorEnv(
                    [make] * num_envs,
                    shared_memory=True,
                    copy=False,  # observations are copied out of the shared buffer once, in step
                    context=method,
                    daemon=True,
                    autoreset_mode=AutoresetMode.SAME_STEP,
                )
            obs_space, act_space, kind = self._guarded(vec, vec.call, "rlexp_info")[0]
            where = f"env.name={env_id!r}"
            layout = obs_layout(
                obs_space, where, tuple(image_keys), frame_stack, mask, indices=kept
            )
            coding = action_coding(act_space, where)
        except (EOFError, ConnectionError) as exc:  # (AsyncVectorEnv terminates the others)
            if vec is not None:
                shutdown(vec, graceful=False)
            raise WorkerError(
                f"{self._where}: a worker failed to start ({exc!r}; its traceback is above)"
            ) from None
        except BaseException:  # (a Ctrl-C held while they started is taken here)
            if vec is not None:
                shutdown(vec, graceful=False)
            raise
        super().__init__(env_id, num_envs, layout, coding)
        self._used = False  # a copy has been reset, stepped or restored since they were made
        self._vec = vec
        self.state_kind = kind
        if layout.frame_stack > 1:
            self.no_state_reason = "env.frame_stack's frame history is not saved"
        self._close_workers = weakref.finalize(self, shutdown, vec)

    def _guarded(self, vec: AsyncVectorEnv, fn, *args, **kwargs):
        """``fn(*args)`` on the workers; a worker that died or raised ends every worker and is
        one ``WorkerError``."""
        try:
            return fn(*args, **kwargs)
        except (EOFError, BrokenPipeError, ConnectionError) as exc:
            message = f"{self._where}: {dead_worker(vec) or f'a worker pipe broke ({exc!r})'}"
        except BaseException as exc:  # the env raised in a worker, or Ctrl-C mid-call
            shutdown(vec, graceful=False)
            if not isinstance(exc, Exception):
                raise
            what = first_line(exc)  # a WorkerEnvError's names the type already
            if not isinstance(exc, WorkerEnvError):
                what = f"{type(exc).__name__}: {what}"
            message = f"{self._where}: a worker failed: {what}"
        shutdown(vec, graceful=False)
        raise WorkerError(f"{message}; all workers are closed") from None

    def _call(self, fn, *args, **kwargs):
        return self._guarded(self._vec, fn, *args, **kwargs)

    # -- stepping ----------------------------------------------------------------------------------
    def step_tensors(self, action: torch.Tensor) -> dict[str, torch.Tensor]:
        """One step of every copy (the workers step in parallel); finished copies were reset in
        their worker: the final observation from the infos goes to ``"next"``."""
        obs, reward, terminated, truncated, info = self._call(
            self._vec.step, self.env_actions(action)
        )
        obs = as_obs(self.obs_layout, obs)  # out of the shared buffer the next step rewrites
        done = np.flatnonzero(terminated | truncated)
        if done.size:
            self._reset_obs[done] = obs[done]
            final = info["final_obs"]
            for i in done:
                obs[i] = final[i]
            self._pending_reset[done] = True
        return self.vector_output(obs, reward, terminated, truncated)

    def _set_seed(self, seed: int | None) -> None:
        super()._set_seed(seed)
        if self._used:  # fresh copies, as in-process (GymnasiumEnv._set_seed says why)
            self._call(self._vec.call, "rlexp_remake")
            self._used = False

    def _seeds(self, ids) -> list[int | None]:
        return [None if self._seed is None else self._seed + int(i) for i in ids]

    def _reset_copies(self, ids: np.ndarray) -> np.ndarray:
        self._used = True
        mask = np.zeros(self.num_envs, dtype=bool)
        mask[ids] = True
        seeds = self._seeds(range(self.num_envs))
        obs, _ = self._call(self._vec.reset, seed=seeds, options={"reset_mask": mask})
        return as_obs(self.obs_layout, obs)[ids]

    def _full_reset(self) -> np.ndarray:
        restored = self._restored
        self._used = True
        if not restored.any():
            obs, _ = self._call(self._vec.reset, seed=self._seeds(range(self.num_envs)))
            self._seed = None  # seeded once: further resets draw from each copy's own stream
            return as_obs(self.obs_layout, obs)
        # Restored from a checkpoint: the restored copies continue (the others are reset).
        obs = self._live.obs_now.copy()  # the checkpoint's ("state": what each copy showed)
        if self.state_kind == "mujoco":
            current = self._call(self._vec.call, "rlexp_current_obs")
            for i in np.flatnonzero(restored):
                obs[i] = current[i]
        pending = restored & self._pending_reset
        obs[pending] = self._reset_obs[pending]
        fresh = np.flatnonzero(~restored)
        if fresh.size:
            obs[fresh] = self._reset_copies(fresh)
        return obs

    # -- resume (GymShapedEnv.env_state / load_env_state), inside the workers ----------------------
    def _copy_states(self, kind: str) -> list[dict]:
        copies = list(self._call(self._vec.call, "rlexp_copy_state", kind))
        for entry in copies:
            if isinstance(entry, tuple) and entry[0] == "error":  # raised in the worker
                kind_of = getattr(builtins, entry[1], None)
                if isinstance(kind_of, type) and issubclass(kind_of, Exception):
                    raise kind_of(entry[2])
                raise RuntimeError(f"{entry[1]}: {entry[2]}")
        return copies

    def _restore_copies(self, kind: str, copies: list[dict]) -> np.ndarray:
        self._used = True
        self._call(self._vec.set_attr, "rlexp_restore", [(kind, c) for c in copies])
        return np.array(self._call(self._vec.get_attr, "rlexp_restore"), dtype=bool)

    # -- extras ------------------------------------------------------------------------------------
    def render(self, env_id: int = 0, **camera) -> np.ndarray:
        """An RGB frame of copy ``env_id`` (``env.kwargs.render_mode=rgb_array``; as in-process)."""
        if self._vec.render_mode != "rgb_array":
            refusal = render_refusal(self.env_id, "render")
            if refusal is not None:  # render_mode=rgb_array would not help: one line saying so
                raise ValueError(refusal)
            raise ValueError(
                f"env.name={self.env_id!r}: rendering needs env.kwargs.render_mode=rgb_array "
                "(e.g. +env.kwargs.render_mode=rgb_array on the command line)"
            )
        return self._call(self._vec.call, "render")[env_id]

    def close(self, *, raise_if_closed: bool = True) -> None:
        self._close_workers()
        super().close(raise_if_closed=raise_if_closed)


def dead_worker(vec: AsyncVectorEnv) -> str | None:
    """Which worker died and how ("worker 3 (pid 1234) died: killed by SIGKILL"), else None."""
    for _ in range(50):  # the pipe can break a moment before the process is reaped
        for i, process in enumerate(vec.processes):
            process.join(timeout=0)
            code = process.exitcode
            if code is not None:
                how = f"killed by {signal.Signals(-code).name}" if code < 0 else f"exit code {code}"
                return f"worker {i} (pid {process.pid}) died: {how}"
        multiprocessing.connection.wait([p.sentinel for p in vec.processes], timeout=0.02)
    return None


def shutdown(vec: AsyncVectorEnv, graceful: bool = True, timeout: float = 10.0) -> None:
    """Close every worker: ask each to close (``graceful``), then SIGKILL any still running after
    ``timeout`` seconds, and reap them. Safe to call again, and on a broken vec env."""
    if getattr(vec, "closed", True):
        return
    vec.closed = True
    pipes = [p for p in vec.parent_pipes if p is not None and not p.closed]
    if graceful:
        try:
            for pipe in pipes:
                pipe.send(("close", None))
            for pipe in pipes:
                if pipe.poll(timeout):
                    pipe.recv()
        except (OSError, EOFError):
            pass  # a worker already gone: killed below
    for process in vec.processes:
        process.join(timeout=timeout if graceful else 0)
        if process.exitcode is None:
            process.kill()
            process.join(timeout=timeout)
    for pipe in pipes:
        pipe.close()
