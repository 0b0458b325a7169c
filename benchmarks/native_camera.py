"""ms per batched step of native push_cube with and without the camera observation term
(docs/performance.md "Native camera term").

    PYTHONPATH=src python benchmarks/native_camera.py [--envs 16] [--size 64] [--steps 100]
"""

from __future__ import annotations

import argparse
import os
import time

import torch

from rlexp.config.native_task import ObservationTermConfig
from rlexp.envs.native import NativeEnv
from rlexp.envs.native.tasks import default_task_config


def ms_per_step(num_envs: int, size: int | None, steps: int) -> float:
    """Mean ms over ``steps`` random-action steps after 10 warm-up steps."""
    cfg = default_task_config("push_cube")
    if size:
        params = {
            "width": size,
            "height": size,
            "eye": [-0.25, -0.15, 1.5],
            "target": [-0.25, -0.14, 0.0],
        }
        cfg.observations["camera"] = ObservationTermConfig(
            "camera_image", name="camera/top", params=params
        )
    env = NativeEnv(cfg, num_envs)
    env.set_seed(0)
    env.reset()
    gen = torch.Generator().manual_seed(0)
    for _ in range(10):
        env.step_action(torch.rand(num_envs, 6, generator=gen) * 2 - 1)
    start = time.perf_counter()
    for _ in range(steps):
        env.step_action(torch.rand(num_envs, 6, generator=gen) * 2 - 1)
    elapsed = time.perf_counter() - start
    env.close()
    return elapsed / steps * 1e3


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--envs", type=int, default=16)
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--steps", type=int, default=100)
    args = ap.parse_args()
    state = ms_per_step(args.envs, None, args.steps)
    camera = ms_per_step(args.envs, args.size, args.steps)
    print(f"MUJOCO_GL={os.environ.get('MUJOCO_GL')} envs={args.envs} size={args.size}")
    print(f"state only: {state:.2f} ms/step; with camera: {camera:.2f} ms/step "
          f"({(camera - state) / args.envs:.2f} ms per rendered frame)")  # fmt: skip


if __name__ == "__main__":
    main()
