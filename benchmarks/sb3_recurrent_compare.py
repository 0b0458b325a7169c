"""Recurrent PPO on the velocity-hidden classic tasks: rlexp against sb3-contrib's ``RecurrentPPO``,
as whole processes (launch to exit), issue #48 "Measured" (docs/performance.md "Recurrent PPO").

Both sides run rl-baselines3-zoo's ``hyperparams/ppo_lstm.yml`` settings for the task (the presets
``conf/experiment/cart_pole_novel_lstm.yaml`` / ``pendulum_novel_lstm.yaml`` cite the file and
commit): the env is the Gymnasium task without its velocity entries (``env.observation_indices``:
CartPole-v1 keeps [0, 2], Pendulum-v1 keeps [0, 1]), observations normalised (rl-zoo's
``normalize: True``: VecNormalize of observations and rewards on the SB3 side), one LSTM of 64 units
for the actor and one for the critic (``enable_critic_lstm=True``), a [64] ReLU head each,
``ortho_init=False``, and the task's n_envs / n_steps / batch_size / n_epochs / gamma / gae_lambda /
learning rate / clip range (``--task``). rl-zoo's PendulumNoVel entry uses gSDE, which rlexp does not
have: both sides run without it here. One torch thread each.

rlexp is ``python train.py +experiment=<task>_lstm`` without evaluation (it still writes its final
checkpoint and TensorBoard scalars); SB3 runs in its own interpreter (``--sb3-python``, a venv with
sb3-contrib) inside ``VecMonitor``.

The runs alternate (rlexp, SB3, rlexp, SB3, ...) so a shared machine's load falls on both; each
line is one process: wall seconds from launch to exit, env steps / wall second, peak RSS, and the
mean return of the last episodes each side logged. The last line is the ratio of the median rates
(rlexp / SB3).

    python benchmarks/sb3_recurrent_compare.py --sb3-python /work/sb3venv/bin/python \\
        --task cart_pole_novel --steps 16384
"""

from __future__ import annotations

import argparse
import functools
import json
import os
from pathlib import Path

import alternate

#: rl-zoo's ppo_lstm.yml entries (DLR-RM/rl-baselines3-zoo 22e3ff2, hyperparams/ppo_lstm.yml):
#: the Gymnasium id, the kept observation indices, and RecurrentPPO's arguments. ``lin_`` values
#: are linear schedules from the value to 0 over the run (``learning_rate(remaining)``).
TASKS: dict[str, dict] = {
    "cart_pole_novel": {
        "env_id": "CartPole-v1",
        "keep": [0, 2],
        "n_envs": 8,
        "n_steps": 32,
        "batch_size": 256,
        "gae_lambda": 0.8,
        "gamma": 0.98,
        "n_epochs": 20,
        "ent_coef": 0.0,
        "learning_rate": ("lin", 0.001),
        "clip_range": ("lin", 0.2),
    },
    "pendulum_novel": {
        "env_id": "Pendulum-v1",
        "keep": [0, 1],
        "n_envs": 4,
        "n_steps": 1024,
        "batch_size": 128,  # not in the entry: RecurrentPPO's default
        "gae_lambda": 0.95,
        "gamma": 0.9,
        "n_epochs": 10,
        "ent_coef": 0.0,
        "learning_rate": ("const", 0.001),
        "clip_range": ("const", 0.2),
    },
}


def _schedule(spec: tuple[str, float]):
    kind, value = spec
    return (lambda remaining: value * remaining) if kind == "lin" else value


def sb3_worker(args: argparse.Namespace) -> None:
    """The SB3 side, run in the SB3 interpreter: what an sb3-contrib user writes for this job."""
    import gymnasium as gym
    import numpy as np
    import torch
    from sb3_contrib import RecurrentPPO
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import VecMonitor, VecNormalize

    torch.set_num_threads(args.threads)
    task = TASKS[args.task]
    keep = np.asarray(task["keep"])

    class KeepIndices(gym.ObservationWrapper):
        """The observation's entries ``keep`` (rlexp's env.observation_indices)."""

        def __init__(self, env: gym.Env) -> None:
            super().__init__(env)
            box = env.observation_space
            self.observation_space = gym.spaces.Box(box.low[keep], box.high[keep], dtype=box.dtype)

        def observation(self, observation):
            return observation[keep]

    env = make_vec_env(
        task["env_id"], n_envs=task["n_envs"], seed=args.seed, wrapper_class=KeepIndices
    )
    env = VecNormalize(VecMonitor(env), gamma=task["gamma"])
    model = RecurrentPPO(
        "MlpLstmPolicy",
        env,
        n_steps=task["n_steps"],
        batch_size=task["batch_size"],
        gae_lambda=task["gae_lambda"],
        gamma=task["gamma"],
        n_epochs=task["n_epochs"],
        ent_coef=task["ent_coef"],
        learning_rate=_schedule(task["learning_rate"]),
        clip_range=_schedule(task["clip_range"]),
        policy_kwargs={
            "ortho_init": False,
            "activation_fn": torch.nn.ReLU,
            "lstm_hidden_size": 64,
            "enable_critic_lstm": True,
            "net_arch": {"pi": [64], "vf": [64]},
        },
        device="cpu",
        seed=args.seed,
        verbose=0,
    )
    model.learn(total_timesteps=args.steps)
    buf = model.ep_info_buffer
    ret = float(np.mean([ep["r"] for ep in buf])) if buf else None
    print(json.dumps({"steps": int(model.num_timesteps), "return": ret}))


def _sb3_return(out: str) -> float | None:
    for line in reversed(out.splitlines()):
        if line.startswith("{"):
            return json.loads(line).get("return")
    return None


def _rlexp_return(run_dir: Path) -> float | None:
    """The last training-episode return rlexp logged (metrics.jsonl)."""
    found = None
    path = run_dir / "metrics.jsonl"
    if path.exists():
        for line in path.read_text().splitlines():
            row = json.loads(line)
            for key in ("train/episode_return", "train/return_mean", "episode_return"):
                if row.get(key) is not None:
                    found = row[key]
    return found


def one_run(args: argparse.Namespace, side: str, r: int, tmp: Path) -> tuple[dict, dict, dict]:
    """One process of ``side``; its line's entries: the task, then the return and the load."""
    if side == "rlexp":
        run_dir = tmp / f"rlexp_{r}"
        res = alternate.run(alternate.rlexp_cmd(args, run_dir, f"{args.task}_lstm"), rlexp=True)
        ret = _rlexp_return(run_dir)
    else:
        res = alternate.run(alternate.sb3_cmd(args, __file__, f"--task={args.task}"))
        ret = _sb3_return(res["out"])
    after = {
        "return": None if ret is None else round(float(ret), 1),
        "load": round(os.getloadavg()[0], 2),
    }
    return res, {"task": args.task}, after


def main() -> None:
    p = alternate.parser(__doc__, "the interpreter with sb3-contrib")
    p.add_argument("--task", choices=sorted(TASKS), default="cart_pole_novel")
    args = alternate.parse(p, sb3_worker)
    if args is not None:
        alternate.alternate(args, "sb3_rnn_", functools.partial(one_run, args))


if __name__ == "__main__":
    main()
