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
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

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


def run(cmd: list[str], env: dict[str, str] | None = None) -> dict:
    """Launch to exit: wall seconds and the child's peak RSS (MiB)."""
    start = time.perf_counter()
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    out = proc.stdout.read() if proc.stdout else b""
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - start
    if os.waitstatus_to_exitcode(status) != 0:
        sys.stderr.write(out.decode(errors="replace")[-3000:])
        raise SystemExit(f"failed: {' '.join(cmd)}")
    return {"wall_s": wall, "peak_rss_mib": usage.ru_maxrss / 1024, "out": out.decode()}


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


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sb3-python", help="the interpreter with sb3-contrib")
    p.add_argument("--task", choices=sorted(TASKS), default="cart_pole_novel")
    p.add_argument("--steps", type=int, default=16384, help="env steps per run (both sides)")
    p.add_argument("--rounds", type=int, default=2, help="rlexp/SB3 pairs, alternating")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--threads", type=int, default=1, help="torch threads (both sides)")
    p.add_argument("--only", choices=("rlexp", "sb3"), help="run one side only")
    p.add_argument("--rlexp-arg", action="append", default=[], help="extra train.py override")
    p.add_argument("--sb3-worker", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.sb3_worker:
        sb3_worker(args)
        return
    if args.only != "rlexp" and not args.sb3_python:
        p.error("--sb3-python is required (or --only rlexp)")
    env = dict(os.environ, PYTHONPATH=str(REPO / "src"))
    rates: dict[str, list[float]] = {"rlexp": [], "sb3": []}
    with tempfile.TemporaryDirectory(prefix="sb3_rnn_") as tmp:
        for r in range(args.rounds):
            for side in ("rlexp", "sb3"):
                if args.only and side != args.only:
                    continue
                if side == "rlexp":
                    run_dir = Path(tmp) / f"rlexp_{r}"
                    cmd = [
                        sys.executable,
                        str(REPO / "train.py"),
                        f"+experiment={args.task}_lstm",
                        f"seed={args.seed}",
                        f"trainer.total_frames={args.steps}",
                        "trainer.eval_every=0",
                        "trainer.save_every=0",
                        f"trainer.torch_threads={args.threads}",
                        f"hydra.run.dir={run_dir}",
                        *args.rlexp_arg,
                    ]
                    res = run(cmd, env)
                    ret = _rlexp_return(run_dir)
                else:
                    cmd = [
                        args.sb3_python,
                        str(Path(__file__).resolve()),
                        "--sb3-worker",
                        f"--task={args.task}",
                        f"--steps={args.steps}",
                        f"--seed={args.seed}",
                        f"--threads={args.threads}",
                    ]
                    res = run(cmd)
                    ret = _sb3_return(res["out"])
                rate = args.steps / res["wall_s"]
                rates[side].append(rate)
                line = {
                    "side": side,
                    "task": args.task,
                    "round": r,
                    "steps": args.steps,
                    "wall_s": round(res["wall_s"], 1),
                    "steps_per_s": round(rate, 1),
                    "peak_rss_mib": round(res["peak_rss_mib"]),
                    "return": None if ret is None else round(float(ret), 1),
                    "load": round(os.getloadavg()[0], 2),
                }
                print(json.dumps(line), flush=True)
    if rates["rlexp"] and rates["sb3"]:
        ratio = statistics.median(rates["rlexp"]) / statistics.median(rates["sb3"])
        print(json.dumps({"ratio_rlexp_over_sb3": round(ratio, 2)}), flush=True)


if __name__ == "__main__":
    main()
