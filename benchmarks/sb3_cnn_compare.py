"""CNN PPO on Atari Pong (EnvPool): rlexp against Stable-Baselines3's ``PPO("CnnPolicy")``, as whole
processes (launch to exit), issue #47 "Measured" (docs/performance.md "CNN PPO").

Both sides run CleanRL's ``ppo_atari_envpool.py`` settings (``conf/experiment/pong_ppo.yaml``): 8
EnvPool envs of ``Pong-v5`` (84x84x4 uint8, frame skip 4, ``episodic_life`` and ``reward_clip``),
128 steps per env per rollout, 4 minibatches of 256, 4 epochs, the Nature CNN shared by linear
actor and critic heads, Adam lr 2.5e-4 annealed, eps 1e-5, clip 0.1 (the value clipped too), ent
0.01, vf 0.5, grad norm 0.5, one torch thread; EnvPool's thread pool on every CPU (rlexp's
``env.num_threads=0``, EnvPool's default for SB3). rlexp is ``python train.py +experiment=pong_ppo``
without evaluation (it still writes its final checkpoint and TensorBoard scalars); SB3 runs in its
own interpreter (``--sb3-python``, a venv with stable-baselines3 and envpool) through a small SB3
``VecEnv`` over EnvPool (EnvPool's documented SB3 adapter: a finished env is reset at once, its last
observation in ``terminal_observation``) inside ``VecMonitor``.

The runs alternate (rlexp, SB3, rlexp, SB3, ...) so a shared machine's load falls on both; each
line is one process: wall seconds from launch to exit, env steps / wall second, peak RSS. The last
line is the ratio of the median rates (rlexp / SB3). Each line also has the machine's 1-minute load
average at the run's end and the run's phases, summed over its iterations: rlexp's own
``perf/collect_time`` (EnvPool's steps and the policy's forward) and ``perf/update_time`` (GAE and
the minibatch steps); SB3's ``collect_rollouts`` (its ``env_s``: EnvPool's steps inside it) and
``train``. The rest of the wall time is start-up, logging and exit.

    python benchmarks/sb3_cnn_compare.py --sb3-python /work/sb3venv/bin/python --steps 16384
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import time
from pathlib import Path

import alternate


def sb3_worker(args: argparse.Namespace) -> None:
    """The SB3 side, run in the SB3 interpreter: what an SB3 user writes for this job."""
    import envpool
    import numpy as np
    import torch
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import VecEnvWrapper, VecMonitor

    torch.set_num_threads(args.threads)
    phases = {"env_s": 0.0, "collect_rollouts_s": 0.0, "train_s": 0.0}

    class VecAdapter(VecEnvWrapper):
        """EnvPool (gymnasium API) as an SB3 VecEnv: a finished env is reset in the same step."""

        def __init__(self, venv) -> None:
            super().__init__(venv=venv)  # num_envs and the spaces from EnvPool's own attributes

        def step_async(self, actions) -> None:
            self.actions = actions

        def reset(self):
            return self.venv.reset()[0]

        def step_wait(self):
            t0 = time.perf_counter()
            obs, rewards, terms, truncs, _ = self.venv.step(self.actions)
            dones = terms | truncs
            infos = [{} for _ in range(self.num_envs)]
            for i in np.flatnonzero(dones):
                infos[i]["terminal_observation"] = obs[i].copy()
                infos[i]["TimeLimit.truncated"] = bool(truncs[i] and not terms[i])
                obs[i] = self.venv.reset(np.array([i]))[0][0]
            phases["env_s"] += time.perf_counter() - t0
            return obs, rewards, dones, infos

    pool = envpool.make_gymnasium(
        "Pong-v5",
        num_envs=args.num_envs,
        seed=args.seed,
        episodic_life=True,
        reward_clip=True,
    )
    env = VecMonitor(VecAdapter(pool))
    lr = 2.5e-4
    model = PPO(
        "CnnPolicy",
        env,
        learning_rate=lambda remaining: lr * remaining,
        n_steps=128,
        batch_size=256,
        n_epochs=4,
        gamma=0.99,
        gae_lambda=0.95,
        clip_range=0.1,
        clip_range_vf=0.1,
        ent_coef=0.01,
        vf_coef=0.5,
        max_grad_norm=0.5,
        normalize_advantage=True,
        policy_kwargs={"optimizer_kwargs": {"eps": 1e-5}},
        device="cpu",
        seed=args.seed,
        verbose=0,
    )
    for name in ("collect_rollouts", "train"):  # each phase's seconds, summed over the run
        setattr(model, name, timed(getattr(model, name), phases, f"{name}_s"))
    model.learn(total_timesteps=args.steps)
    buf = model.ep_info_buffer
    ret = float(np.mean([ep["r"] for ep in buf])) if buf else None
    phases = {k: round(v, 2) for k, v in phases.items()}
    print("PHASES " + json.dumps({"steps": int(model.num_timesteps), "return": ret, **phases}))


def timed(fn, phases: dict[str, float], key: str):
    """``fn`` adding its seconds to ``phases[key]``."""

    def run(*a, **kw):
        t0 = time.perf_counter()
        try:
            return fn(*a, **kw)
        finally:
            phases[key] += time.perf_counter() - t0

    return run


def rlexp_phases(run_dir: Path) -> dict[str, float]:
    """rlexp's own per-iteration timings of a run (metrics.jsonl), summed: collection (EnvPool's
    steps and the policy's forward) and update (GAE and the minibatch steps)."""
    rows = [json.loads(x) for x in (run_dir / "metrics.jsonl").read_text().splitlines() if x]
    collect = sum(r.get("perf/collect_time", 0.0) for r in rows)
    update = sum(r.get("perf/update_time", 0.0) for r in rows)
    return {"collect_s": round(collect, 2), "update_s": round(update, 2)}


def one_run(args: argparse.Namespace, side: str, r: int, tmp: Path) -> tuple[dict, dict, dict]:
    """One process of ``side``; its line's entries after the common ones: the load, the phases."""
    if side == "rlexp":
        run_dir = tmp / f"rlexp_{r}"
        cmd = alternate.rlexp_cmd(args, run_dir, "pong_ppo", f"env.num_envs={args.num_envs}")
        res = alternate.run(cmd, rlexp=True)
        phases = rlexp_phases(run_dir)
    else:
        res = alternate.run(alternate.sb3_cmd(args, __file__, f"--num-envs={args.num_envs}"))
        tail = res["out"].split("PHASES ")[-1].splitlines()[0]
        phases = {k: v for k, v in json.loads(tail).items() if k.endswith("_s")}
    return res, {}, {"load_avg_1m": round(os.getloadavg()[0], 1), **phases}


def main() -> None:
    p = alternate.parser(__doc__, "the interpreter with stable-baselines3 and envpool")
    p.add_argument("--num-envs", type=int, default=8)
    args = alternate.parse(p, sb3_worker)
    if args is not None:
        alternate.alternate(args, "sb3_cnn_", functools.partial(one_run, args))


if __name__ == "__main__":
    main()
