"""The floors of a PPO run on one core (issue #32), each timed alone in plain code:

- ``physics_us``: MuJoCo's ``mj_step`` x frame_skip per env step (random actions in the box);
- ``gym_step_us``: Gymnasium's ``env.step`` (the registered env with its wrappers; resets counted);
- ``numpy_actor_us``: the actor's forward and a Gaussian draw for one observation as numpy matmuls
  (``numpy_actor_critic_us``: actor and critic, the issue's "three numpy matmuls per net");
- ``plain_loop_us``: a plain collection loop, ``env.step`` of the numpy policy's action (the
  collection floor: the env's own cost and the policy's math, interleaved as they run);
- ``compiled_step_us``: one PPO minibatch step (actor and critic forward, clipped loss, backward,
  gradient clip, Adam) in plain torch, the whole step one ``torch.compile``d function
  (``benchmarks/ppo_floor.py``'s); ``eager_step_us`` the same uncompiled;
- ``sac_compiled_step_us``: one SAC gradient step (twin critics, tanh-Gaussian actor, alpha, three
  Adam steps, the soft target update; 256x256, batch 256) in plain torch, its losses one
  ``torch.compile``d function (``benchmarks/sac_floor.py``); ``sac_eager_step_us`` uncompiled.

Each figure is the median of ``--repeats`` blocks. One torch thread. ``--json`` writes them for
``end_to_end.py``, which runs this in the same invocation as rlexp and SB3 and prints rlexp's phases
as ratios to these floors.

    python benchmarks/floors.py --env HalfCheetah-v5 --repeats 5
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent


def _mlp_np(rng: np.random.Generator, sizes: list[int]) -> list[tuple[np.ndarray, np.ndarray]]:
    return [
        (rng.standard_normal((a, b)).astype(np.float32) / np.sqrt(a), np.zeros(b, np.float32))
        for a, b in zip(sizes[:-1], sizes[1:], strict=True)
    ]


def _forward(layers: list[tuple[np.ndarray, np.ndarray]], x: np.ndarray) -> np.ndarray:
    for i, (w, b) in enumerate(layers):
        x = x @ w + b
        if i < len(layers) - 1:
            x = np.tanh(x)
    return x


def _median_us(fn, calls: int, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(calls):
            fn()
        times.append((time.perf_counter() - t0) / calls * 1e6)
    return statistics.median(times)


def measure(
    env_id: str, hidden: int, repeats: int, steps: int, mb_steps: int, threads: int = 1
) -> dict:
    import gymnasium as gym
    import mujoco
    import torch

    torch.set_num_threads(threads)  # the networks' steps (the env's physics runs one thread)
    env = gym.make(env_id)
    obs, _ = env.reset(seed=0)
    space = env.action_space
    obs_dim, act_dim = obs.shape[0], space.shape[0]
    rng = np.random.default_rng(0)
    actions = rng.uniform(space.low, space.high, size=(steps, act_dim))
    sim = env.unwrapped
    out: dict[str, float] = {"env": env_id, "hidden": hidden, "torch_threads": threads}

    i = 0

    def physics() -> None:
        nonlocal i
        sim.data.ctrl[:] = actions[i % steps]
        mujoco.mj_step(sim.model, sim.data, nstep=sim.frame_skip)
        i += 1

    out["physics_us"] = _median_us(physics, steps, repeats)
    env.reset(seed=0)

    def gym_step() -> None:
        nonlocal i
        _, _, term, trunc, _ = env.step(actions[i % steps])
        i += 1
        if term or trunc:
            env.reset()

    out["gym_step_us"] = _median_us(gym_step, steps, repeats)

    actor = _mlp_np(rng, [obs_dim, hidden, hidden, act_dim])
    critic = _mlp_np(rng, [obs_dim, hidden, hidden, 1])
    std = np.full(act_dim, 0.5, np.float32)
    x = obs.astype(np.float32)[None]

    def numpy_actor() -> np.ndarray:
        loc = _forward(actor, x)
        return loc + std * rng.standard_normal(loc.shape, dtype=np.float32)

    out["numpy_actor_us"] = _median_us(numpy_actor, steps, repeats)
    out["numpy_actor_critic_us"] = _median_us(
        lambda: (numpy_actor(), _forward(critic, x)), steps, repeats
    )

    env.reset(seed=0)
    current = [x]

    def plain_loop() -> None:
        loc = _forward(actor, current[0])
        action = np.clip(loc + std * rng.standard_normal(loc.shape, dtype=np.float32), -1, 1)
        o, _, term, trunc, _ = env.step(action[0])
        if term or trunc:
            o, _ = env.reset()
        current[0] = o.astype(np.float32)[None]

    out["plain_loop_us"] = _median_us(plain_loop, steps, repeats)
    env.close()

    sys.path.insert(0, str(HERE))
    import ppo_floor  # noqa: E402  (benchmarks/ is not a package)

    ppo_floor.OBS, ppo_floor.ACT, ppo_floor.HIDDEN = obs_dim, act_dim, hidden
    for compiled, key in ((True, "compiled_step_us"), (False, "eager_step_us")):
        call = ppo_floor.plain_step_fn(compiled)
        t0 = time.perf_counter()
        for _ in range(20):  # the first compiles
            call()
        if compiled:
            out["compile_s"] = time.perf_counter() - t0
        out[key] = _median_us(call, mb_steps, repeats)
    import sac_floor  # noqa: E402  (the SAC update's floor: 256x256, batch 256)

    sac_floor.OBS, sac_floor.ACT = obs_dim, act_dim
    for compiled, key in ((True, "sac_compiled_step_us"), (False, "sac_eager_step_us")):
        call = sac_floor.plain_step_fn(compiled)
        for _ in range(20):  # the first compiles
            call()
        out[key] = _median_us(call, mb_steps, repeats)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--env", default="HalfCheetah-v5")
    parser.add_argument("--hidden", type=int, default=64, help="width of both hidden layers")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--steps", type=int, default=2000, help="env steps per block")
    parser.add_argument("--mb-steps", type=int, default=300, help="minibatch steps per block")
    parser.add_argument("--threads", type=int, default=1, help="torch threads of the steps")
    parser.add_argument("--json", type=Path, help="write the figures here")
    args = parser.parse_args()
    out = measure(args.env, args.hidden, args.repeats, args.steps, args.mb_steps, args.threads)
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))
    for key, value in out.items():
        print(f"{key}: {value:.1f}" if isinstance(value, float) else f"{key}: {value}")


if __name__ == "__main__":
    main()
