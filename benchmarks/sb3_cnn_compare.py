"""CNN PPO env-steps/s: rlexp against Stable-Baselines3's ``PPO("CnnPolicy")``, whole processes
(issue #47, "Speed": goal rlexp >= 1.5x SB3; docs/performance.md).

Both train the same Atari game through EnvPool (84x84 greyscale, 4 frames stacked, frame skip 4:
``conf/env/pong.yaml``'s settings) with CleanRL's Atari PPO settings (``cleanrl/ppo_atari_envpool.py``,
rlexp's ``+experiment=pong_ppo``): 8 envs x 128 steps, 4 minibatches of 256, 4 epochs, the Nature
CNN (32x8x8/4, 64x4x4/2, 64x3x3/1, Linear 512) shared by a linear actor and critic, lr 2.5e-4
annealed, clip 0.1 (value clipped too), entropy 0.01, value 0.5, max grad norm 0.5, Adam eps 1e-5.
Evaluation and checkpoints are off on both sides (rlexp: ``trainer.eval_episodes=0``, saving past
the budget, only the final checkpoint; SB3: no callbacks), so
the number is the training loop's own. Each contender runs as its own process, launch to exit
(imports, env start, the first compile included: what a user waits for), ``--rounds`` times in
alternating order; the table gives env steps / wall seconds, median over rounds.

SB3 is not in rlexp's venv: give its interpreter. A venv for it, once:

    python -m venv /tmp/sb3venv
    /tmp/sb3venv/bin/pip install "stable-baselines3>=2.3" envpool torch numpy

then (``--steps``: env steps per run; 8 envs x 128 steps = 1024 per PPO iteration):

    PYTHONPATH=src python benchmarks/sb3_cnn_compare.py --sb3-python /tmp/sb3venv/bin/python \
        --steps 102400 --rounds 3 --threads 4 --device auto

``--device``: rlexp's ``trainer.device`` and SB3's ``device`` (auto: CUDA when present). A smoke
run (``--steps 2048 --rounds 1``) checks both sides start and finish. Prints the table and one JSON
line; nothing is written outside ``--work`` (a temporary folder by default).
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

#: CleanRL's ppo_atari_envpool.py settings (rlexp: conf/experiment/pong_ppo.yaml holds the same).
NUM_ENVS, NUM_STEPS, MINIBATCHES, EPOCHS = 8, 128, 4, 4

#: The SB3 side, run by the SB3 interpreter: EnvPool behind SB3's VecEnv (EnvPool's own SB3
#: example's adapter: a finished copy is reset at once, its last observation in the info), PPO with
#: the CnnPolicy (SB3's NatureCNN, /255 inside, shared by pi and vf: share_features_extractor).
SB3_SCRIPT = r"""
import json, sys, time
import envpool, numpy as np, torch
from stable_baselines3 import PPO
from stable_baselines3.common.vec_env import VecEnvWrapper, VecMonitor

a = json.loads(sys.argv[1])
torch.set_num_threads(a["threads"])


class VecAdapter(VecEnvWrapper):
    def __init__(self, venv):
        venv.num_envs = venv.spec.config.num_envs
        super().__init__(venv=venv)

    def step_async(self, actions):
        self.actions = actions

    def reset(self):
        return self.venv.reset()[0]

    def seed(self, seed=None):
        pass

    def step_wait(self):
        obs, rewards, terms, truncs, info = self.venv.step(self.actions)
        dones = terms | truncs
        infos = []
        for i in range(self.num_envs):
            infos.append({"TimeLimit.truncated": bool(truncs[i] and not terms[i])})
            if dones[i]:
                infos[i]["terminal_observation"] = obs[i]
                obs[i] = self.venv.reset(np.array([i]))[0]
        return obs, rewards, dones, infos


env = envpool.make(a["env_id"], env_type="gymnasium", num_envs=a["num_envs"], seed=a["seed"],
                   episodic_life=True, reward_clip=True)
env = VecMonitor(VecAdapter(env))
model = PPO(
    "CnnPolicy", env, n_steps=a["num_steps"], batch_size=a["batch_size"], n_epochs=a["epochs"],
    learning_rate=lambda f: 2.5e-4 * f, clip_range=0.1, clip_range_vf=0.1, ent_coef=0.01,
    vf_coef=0.5, max_grad_norm=0.5, gamma=0.99, gae_lambda=0.95, normalize_advantage=True,
    seed=a["seed"], device=a["device"], verbose=0,
)
start = time.time()
model.learn(total_timesteps=a["steps"])
print(json.dumps({"steps": int(model.num_timesteps), "learn_s": time.time() - start}))
"""


def rlexp_cmd(args: argparse.Namespace, run_dir: Path) -> list[str]:
    """``python train.py +experiment=pong_ppo`` on ``--env-id`` for ``--steps``, eval and saving
    past the budget (off), console quiet."""
    never = args.steps * 10
    return [
        sys.executable, str(REPO / "train.py"), "+experiment=pong_ppo",
        f"env.name={args.env_id}", f"env.num_envs={NUM_ENVS}",
        f"trainer.total_frames={args.steps}", f"trainer.frames_per_batch={NUM_ENVS * NUM_STEPS}",
        f"algorithm.mini_batch_size={NUM_ENVS * NUM_STEPS // MINIBATCHES}",
        f"algorithm.num_epochs={EPOCHS}", f"trainer.eval_every={never}", "trainer.eval_episodes=0",
        f"trainer.save_every={never}", f"trainer.torch_threads={args.threads}",
        f"trainer.device={args.device}", "trainer.progress=false", f"seed={args.seed}",
        f"hydra.run.dir={run_dir}",
    ]  # fmt: skip


def sb3_cmd(args: argparse.Namespace) -> list[str]:
    device = args.device
    settings = {
        "env_id": args.env_id, "num_envs": NUM_ENVS, "num_steps": NUM_STEPS,
        "batch_size": NUM_ENVS * NUM_STEPS // MINIBATCHES, "epochs": EPOCHS,
        "steps": args.steps, "threads": args.threads, "device": device, "seed": args.seed,
    }  # fmt: skip
    return [args.sb3_python, "-c", SB3_SCRIPT, json.dumps(settings)]


def timed(cmd: list[str], log: Path, env: dict[str, str]) -> float:
    """Wall seconds of ``cmd`` from launch to exit; its output to ``log``; exit code checked."""
    start = time.perf_counter()
    with open(log, "w") as out:
        proc = subprocess.run(cmd, stdout=out, stderr=subprocess.STDOUT, env=env, check=False)
    wall = time.perf_counter() - start
    if proc.returncode != 0:
        tail = log.read_text().strip().splitlines()[-5:]
        raise SystemExit(f"{cmd[0]} exited {proc.returncode}; {log}:\n" + "\n".join(tail))
    return wall


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sb3-python", help="the interpreter of a venv with SB3 + envpool")
    p.add_argument("--only", choices=("rlexp", "sb3"), help="run one side (a smoke test)")
    p.add_argument("--env-id", default="Pong-v5", help="an EnvPool Atari id")
    p.add_argument("--steps", type=int, default=102_400, help="env steps per run (x 1024)")
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--threads", type=int, default=1, help="torch threads, both sides")
    p.add_argument("--device", default="cpu", help="cpu | cuda | auto, both sides")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--work", type=Path, default=None, help="run dirs and logs (default: a tmp dir)")
    args = p.parse_args()
    if args.steps % (NUM_ENVS * NUM_STEPS):
        raise SystemExit(f"--steps {args.steps}: give a multiple of {NUM_ENVS * NUM_STEPS}")
    sides = (args.only,) if args.only else ("rlexp", "sb3")
    if "sb3" in sides and not (args.sb3_python and Path(args.sb3_python).is_file()):
        raise SystemExit(f"--sb3-python {args.sb3_python!r} does not exist (see this file's doc)")
    work = args.work or Path(tempfile.mkdtemp(prefix="sb3_cnn_"))
    work.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "PYTHONPATH": str(REPO / "src")}
    sb3_env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    walls: dict[str, list[float]] = {"rlexp": [], "sb3": []}
    for r in range(args.rounds):
        order = sides if r % 2 == 0 else sides[::-1]
        for who in order:
            log = work / f"{who}_{r}.log"
            if who == "rlexp":
                wall = timed(rlexp_cmd(args, work / f"rlexp_{r}"), log, env)
            else:
                wall = timed(sb3_cmd(args), log, sb3_env)
            walls[who].append(wall)
            print(
                f"round {r} {who}: {args.steps / wall:,.0f} env-steps/s ({wall:.1f} s)", flush=True
            )
    sps = {who: args.steps / statistics.median(w) for who, w in walls.items() if w}
    print(f"\n| {args.env_id}, {args.steps} env steps, median of {args.rounds} | env-steps/s |")
    print("|---|---|")
    for who in sps:
        print(f"| {who} | {sps[who]:,.0f} |")
    if len(sps) == 2:
        print(f"| rlexp / SB3 | {sps['rlexp'] / sps['sb3']:.2f}x |")
    print()
    print(json.dumps({"env_id": args.env_id, "steps": args.steps, "walls": walls, "sps": sps}))


if __name__ == "__main__":
    main()
