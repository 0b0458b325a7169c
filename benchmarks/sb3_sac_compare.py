"""SB3's SAC against rlexp's SAC on HalfCheetah-v5 with rl-zoo's settings (hyperparams/sac.yml:
256x256, batch 256, buffer 1e6, one gradient step per env step, one env), timed after
``learning_starts``, where both run at a flat rate (docs/performance.md, "SAC"). Each side runs in
its own process, alternating ``--rounds`` times; the machine's load (``os.getloadavg``) is printed
with each figure. ``--threads N``: both sides run N torch threads (SB3's ``torch.set_num_threads``,
rlexp's ``trainer.torch_threads``; rlexp steps its env with one either way).

    python benchmarks/sb3_sac_compare.py --learning-starts 500 --steps 1500 --rounds 2 --threads 1 \\
        --sb3-python /work/sb3venv/bin/python

The figure is env steps (= gradient steps) per second between ``learning_starts`` and the end; a
1M-step run's time is ~1e6 / that rate (plus its evaluations).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import textwrap
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent

SB3 = textwrap.dedent(
    """
    import sys, time, torch, gymnasium as gym
    from stable_baselines3 import SAC
    from stable_baselines3.common.callbacks import BaseCallback
    starts, steps = int(sys.argv[1]), int(sys.argv[2])
    torch.set_num_threads(int(sys.argv[3]))
    class Clock(BaseCallback):
        t0 = None
        def _on_step(self):
            if self.num_timesteps == starts + 1:
                Clock.t0 = time.perf_counter()
            return True
    model = SAC("MlpPolicy", gym.make("HalfCheetah-v5"), learning_starts=starts, seed=0,
                device="cpu", verbose=0)
    model.learn(starts + steps, callback=Clock())
    print((steps - 1) / (time.perf_counter() - Clock.t0))
    """
)


def mujoco_shim() -> str:
    """A folder to put on the SB3 interpreter's PYTHONPATH with this interpreter's MuJoCo and
    the packages Gymnasium's MuJoCo envs import (the SB3 venv here has none of them)."""
    import importlib.util

    shim = Path(tempfile.mkdtemp(prefix="mujoco-shim-"))
    site = Path(importlib.util.find_spec("mujoco").origin).parent.parent
    for pattern in ("mujoco", "absl", "etils", "glfw", "OpenGL", "imageio", "mujoco-*.dist-info",
                    "imageio-*.dist-info"):  # fmt: skip
        for path in site.glob(pattern):
            (shim / path.name).symlink_to(path)
    return str(shim)


def sb3_rate(python: str, starts: int, steps: int, threads: int) -> float:
    env = {**os.environ, "PYTHONPATH": mujoco_shim()}
    out = subprocess.run([python, "-c", SB3, str(starts), str(steps), str(threads)], capture_output=True,
                         text=True, check=True, timeout=3600, env=env)  # fmt: skip
    return float(out.stdout.strip().splitlines()[-1])


def rlexp_rate(starts: int, steps: int, threads: int, extra: list[str]) -> float:
    with tempfile.TemporaryDirectory() as tmp:
        run = Path(tmp) / "run"
        args = ["env=half_cheetah", "+experiment=sac", f"algorithm.learning_starts={starts}",
                f"trainer.total_frames={starts + steps}", "trainer.eval_every=0",
                "trainer.save_every=0", "trainer.log_every=100", "trainer.progress=false",
                "logger=none", f"trainer.torch_threads={threads}", f"hydra.run.dir={run}",
                *extra]  # fmt: skip
        env = {**os.environ, "PYTHONPATH": str(REPO / "src")}
        subprocess.run([sys.executable, str(REPO / "train.py"), *args], cwd=tmp, env=env,
                       check=True, capture_output=True, timeout=3600)  # fmt: skip
        rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
        rows = [r for r in rows if "perf/sps" in r and r["step"] > starts]
        first, last = rows[0], rows[-1]
        return (last["step"] - first["step"]) / (last["time"] - first["time"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--learning-starts", type=int, default=1000)
    parser.add_argument("--steps", type=int, default=2000, help="env steps timed after it")
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--sb3-python", default="/work/sb3venv/bin/python")
    parser.add_argument("--threads", type=int, default=1, help="torch threads, both sides")
    parser.add_argument("--rlexp-arg", action="append", default=[], help="an extra override")
    args = parser.parse_args()
    print(f"torch threads: {args.threads} (SB3 and rlexp); learning_starts {args.learning_starts}, "
          f"{args.steps} timed steps", flush=True)  # fmt: skip
    for r in range(args.rounds):
        load = os.getloadavg()[0]
        sb3 = sb3_rate(args.sb3_python, args.learning_starts, args.steps, args.threads)
        mid = os.getloadavg()[0]
        mine = rlexp_rate(args.learning_starts, args.steps, args.threads, args.rlexp_arg)
        print(f"round {r}, {args.threads} thread(s): SB3 {sb3:.1f} steps/s ({1e3 / sb3:.2f} ms), "
              f"rlexp {mine:.1f} steps/s ({1e3 / mine:.2f} ms), ratio {mine / sb3:.2f}x "
              f"(load {load:.1f} -> {mid:.1f} -> {os.getloadavg()[0]:.1f})", flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
