"""rlexp's phases against their floors (issue #32), for ``end_to_end.py``: runs ``floors.py`` in
a subprocess of the same invocation, sums each rlexp run's ``perf/collect_time``,
``perf/update_time`` and ``perf/eval_time`` from its metrics.jsonl, and prints each phase as a
ratio to its floor:

- collection: the plain loop (``env.step`` of a numpy policy's action) x env steps; also the
  Gymnasium step alone and the physics alone x env steps;
- update: the plain compiled PPO minibatch step x the run's minibatch steps (iterations x epochs x
  minibatches per epoch); GAE and the normaliser's fold are in rlexp's update time, not in the floor;
- the rest of launch to exit (start-up, evaluation in the training process, checkpoints, logging,
  exit): wall minus collection and update.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent


def measure_floors(gym_id: str, hidden: int, repeats: int = 5) -> dict:
    """``floors.py``'s figures, measured in a child process (one torch thread)."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "floors.json"
        cmd = [sys.executable, str(HERE / "floors.py"), "--env", gym_id, "--hidden", str(hidden)]
        cmd += ["--repeats", str(repeats), "--json", str(out)]
        env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
        subprocess.run(cmd, check=True, env=env, stdout=subprocess.DEVNULL)
        return json.loads(out.read_text())


def phase_sums(run_dir: Path) -> dict:
    """Seconds of collection, update and in-process evaluation summed over a run's iterations."""
    rows = [json.loads(x) for x in (run_dir / "metrics.jsonl").read_text().splitlines() if x]
    rows = [r for r in rows if "perf/collect_time" in r]
    return {
        "collect_s": sum(r["perf/collect_time"] for r in rows),
        "update_s": sum(r["perf/update_time"] for r in rows),
        "eval_s": sum(r.get("perf/eval_time", 0.0) for r in rows),
        "iterations": len(rows),
    }


def minibatch_steps(config, iterations: int) -> int:
    """The run's PPO minibatch steps: iterations x epochs x whole minibatches per rollout."""
    samples = config.trainer.frames_per_batch * config.env.num_envs
    return iterations * config.algorithm.num_epochs * (samples // config.algorithm.mini_batch_size)


def floor_table(floors: dict, runs: dict[str, list[dict]], labels: list[str], config) -> str:
    """Markdown: per rlexp contender (medians over rounds), each phase, its floor and the ratio."""
    lines = [
        f"Floors, measured in this invocation (`benchmarks/floors.py`, {floors['env']}, "
        f"{floors['hidden']}x{floors['hidden']} tanh, one torch thread): physics "
        f"{floors['physics_us']:.1f} us/step, Gymnasium `env.step` {floors['gym_step_us']:.1f} "
        f"us, numpy actor + draw {floors['numpy_actor_us']:.1f} us (actor + critic "
        f"{floors['numpy_actor_critic_us']:.1f} us), the plain loop (step + numpy policy) "
        f"{floors['plain_loop_us']:.1f} us; the plain PPO minibatch step "
        f"{floors['compiled_step_us']:.0f} us compiled ({floors['compile_s']:.1f} s to compile), "
        f"{floors['eager_step_us']:.0f} us eager.",
        "",
        "| run | collection s | plain loop floor s | x floor | x Gymnasium step | update s "
        "| compiled step floor s | x floor | rest of launch to exit s |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for label in labels:
        rs = runs[label]
        med = {k: statistics.median(r[k] for r in rs) for k in ("collect_s", "update_s", "wall")}
        steps = statistics.median(r["steps"] for r in rs)
        iters = statistics.median(r["iterations"] for r in rs)
        collect_floor = floors["plain_loop_us"] * steps / 1e6
        env_floor = floors["gym_step_us"] * steps / 1e6
        update_floor = floors["compiled_step_us"] * minibatch_steps(config, int(iters)) / 1e6
        rest = med["wall"] - med["collect_s"] - med["update_s"]
        lines.append(
            f"| {label} | {med['collect_s']:.1f} | {collect_floor:.1f} "
            f"| {med['collect_s'] / collect_floor:.2f} | {med['collect_s'] / env_floor:.2f} "
            f"| {med['update_s']:.1f} | {update_floor:.1f} | {med['update_s'] / update_floor:.2f} "
            f"| {rest:.1f} |"
        )
    return "\n".join(lines)
