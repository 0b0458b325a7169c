"""``env.backend=envpool``: EnvPool's C++ thread pool (``envpool.make_gymnasium``, the ``envpool``
extra) as the same rlexp env as the in-process Gymnasium adapter.

- Tasks: EnvPool's own, under Gymnasium's names (``HalfCheetah-v5``, ``Hopper-v5``, ...); EnvPool
  ships its own MuJoCo build and task code (docs/envs.md, "Vectorised backends" compares them).
  Atari (``Pong-v5``, ...): 84x84 greyscale frames, 4 stacked (``[4, 84, 84]`` uint8), emitted as
  the uint8 ``pixels`` entry of a TensorDict observation; ``env.frame_stack=N`` is EnvPool's own
  ``stack_num``.
- Threads: ``env.num_threads`` (0: every CPU this process may use), never more than those CPUs nor
  than ``num_envs``.
- Autoreset: EnvPool resets a finished env at its NEXT step; rlexp resets it right away
  (``reset(env_id=...)``), so the step returns the true final observation in ``"next"`` (truncated
  episodes bootstrap) and the reset one is what ``autoreset_observation`` hands out.
- Seeds: EnvPool fixes them when the pool is built (env ``i``: ``seed + i``), so ``set_seed``
  followed by a full ``reset()`` rebuilds the pool (~1 ms per 10 envs): every eval round starts
  from the same episodes, as with the Gymnasium backends.
- Resume: EnvPool exposes no env state, so checkpoints hold the documented ``restart`` kind.
"""

from __future__ import annotations

import difflib
import logging

import numpy as np
import torch

from rlexp.config.rules import available_cpus
from rlexp.envs.adapter import GymShapedEnv
from rlexp.envs.gym_ids import GYM_MUJOCO_TASKS
from rlexp.envs.spaces import UnsupportedSpace, action_coding, obs_layout
from rlexp.extras import require

log = logging.getLogger(__name__)


def check_envpool_id(name: str) -> None:
    """KeyError naming close matches when EnvPool has no task ``name``."""
    import envpool

    if ":" in name:
        raise KeyError(
            f"env.name={name!r}: env.backend=envpool runs EnvPool's own tasks, not a module:EnvId "
            "env; use env.backend=gymnasium_async (worker processes) for your own env"
        )
    known = envpool.list_all_envs()
    if name in known:
        return
    close = difflib.get_close_matches(name, known, n=3)
    hint = f"; did you mean {close[0]!r}?" if close else ""
    mujoco = [k for k in GYM_MUJOCO_TASKS if k in known]
    raise KeyError(
        f"env.name={name!r} is not an EnvPool task (env.backend=envpool){hint}; its Gymnasium "
        f"MuJoCo tasks include {mujoco}; any Gymnasium env: env.backend=gymnasium_async"
    )


def pool_threads(requested: int, num_envs: int) -> int:
    """EnvPool's thread count: ``requested`` (0: every CPU this process may use), capped at those
    CPUs and at ``num_envs`` (a thread steps whole envs; more threads than envs only wait)."""
    cpus = available_cpus()
    threads = min(cpus if requested == 0 else requested, cpus, num_envs)
    if requested > cpus:
        log.warning(
            "env.num_threads=%d but this process may use %d CPUs: EnvPool runs %d threads",
            requested,
            cpus,
            threads,
        )
    return max(1, threads)


class EnvPoolEnv(GymShapedEnv):
    """``num_envs`` copies of an EnvPool task stepped by its thread pool, as one TorchRL env."""

    backend = "envpool"
    no_state_reason = "EnvPool offers no env state"

    def __init__(
        self,
        name: str,
        num_envs: int = 1,
        seed: int = 0,
        max_episode_steps: int | None = None,
        kwargs: dict | None = None,
        num_threads: int = 0,
        image_keys: tuple[str, ...] | list[str] = (),
        frame_stack: int = 0,
        observation_indices: tuple[int, ...] | list[int] = (),
    ) -> None:
        require("envpool", "env.backend=envpool")
        check_envpool_id(name)
        self._options = dict(kwargs or {})
        if max_episode_steps is not None:
            self._options["max_episode_steps"] = max_episode_steps
        where = f"env.name={name!r}"
        if frame_stack > 1:
            self._options.update(_stack_option(name, frame_stack, self._options, where))
        self._name, self._num_envs = name, num_envs
        self.num_threads = pool_threads(num_threads, num_envs)
        pool = self._make_pool(seed)
        try:
            layout = obs_layout(
                pool.observation_space,
                where,
                tuple(image_keys),
                frame_stack,
                indices=tuple(observation_indices),
            )
        except UnsupportedSpace:
            pool.close()
            raise
        super().__init__(name, num_envs, layout, action_coding(pool.action_space, where))
        self._pool = pool
        self._pool_seed = seed  # the seed the pool was built with
        self._pool_fresh = True  # not reset or stepped since it was built
        log.debug("envpool %s x%d on %d threads", name, num_envs, self.num_threads)

    def _make_pool(self, seed: int):
        import envpool

        try:
            return envpool.make_gymnasium(
                self._name,
                num_envs=self._num_envs,
                batch_size=self._num_envs,  # synchronous: every step returns every env, in order
                num_threads=self.num_threads,
                seed=int(seed),
                **self._options,
            )
        except TypeError:
            fields = envpool.make_spec(self._name).config._fields
            unknown = [k for k in self._options if k not in fields]
            if not unknown:
                raise
            raise TypeError(
                f"env.kwargs.{unknown[0]} is not an option of EnvPool's {self._name} (its options: "
                f"{[f for f in fields if f not in _POOL_FIELDS]})"
            ) from None

    # -- stepping ----------------------------------------------------------------------------------
    def step_tensors(self, action: torch.Tensor) -> dict[str, torch.Tensor]:
        """One step of every env on EnvPool's threads; finished envs are reset right away (their
        true final observation goes to ``"next"``)."""
        obs, reward, terminated, truncated, _ = self._pool.step(self.env_actions(action))
        obs = self.obs_layout.encode_batch(obs)
        done = np.flatnonzero(terminated | truncated)
        if done.size:
            reset_obs, _ = self._pool.reset(env_id=done.astype(np.int32))
            self._reset_obs[done] = self.obs_layout.encode_batch(reset_obs)
            self._pending_reset[done] = True
        return self.vector_output(obs, reward, terminated, truncated)

    def _reset_copies(self, ids: np.ndarray) -> np.ndarray:
        obs, _ = self._pool.reset(env_id=np.asarray(ids, dtype=np.int32))
        return self.obs_layout.encode_batch(obs)

    def _full_reset(self) -> np.ndarray:
        # A seed set since the pool was built (set_seed, a restart): a new pool of that seed.
        if self._seed is not None and not (self._pool_fresh and self._pool_seed == self._seed):
            self._pool.close()
            self._pool = self._make_pool(self._seed)
            self._pool_seed = self._seed
        self._seed = None
        self._pool_fresh = False
        obs, _ = self._pool.reset()
        return self.obs_layout.encode_batch(obs)

    # -- extras ------------------------------------------------------------------------------------
    def render(self, env_id: int = 0, **camera) -> np.ndarray:
        """EnvPool's renderer needs an OpenGL context it cannot make here: refused in one line."""
        raise ValueError(
            f"env.name={self.env_id!r}: env.backend=envpool does not render in rlexp; record videos "
            "with env.backend=gymnasium (same task names)"
        )

    def close(self, *, raise_if_closed: bool = True) -> None:
        self._pool.close()
        super().close(raise_if_closed=raise_if_closed)


def _stack_option(name: str, n: int, options: dict, where: str) -> dict:
    """``env.frame_stack=n`` as EnvPool's own ``stack_num`` option (Atari stacks frames in C++);
    ValueError (one line) for a task without it, or with ``env.kwargs.stack_num`` set too."""
    import envpool

    if "stack_num" not in envpool.make_spec(name).config._fields:
        raise ValueError(
            f"{where}: env.frame_stack={n}, but EnvPool's {name} has no stack_num option to stack "
            "frames with (EnvPool stacks frames for its Atari tasks); use env.frame_stack=0"
        )
    if "stack_num" in options and int(options["stack_num"]) != n:
        raise ValueError(
            f"{where}: env.frame_stack={n} and env.kwargs.stack_num={options['stack_num']} "
            "disagree; set one of them"
        )
    return {"stack_num": n}


#: EnvPool's pool settings (rlexp sets them from env.num_envs, env.num_threads and the seed).
_POOL_FIELDS = (
    "num_envs",
    "batch_size",
    "num_threads",
    "max_num_players",
    "thread_affinity_offset",
    "base_path",
    "seed",
    "env_seed",
    "gym_reset_return_info",
)
