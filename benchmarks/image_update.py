"""Memory and update time of an image rollout (issue #47, docs/performance.md "Image observations").

One process per measurement (its peak RSS is the measurement's own): collect a rollout of
``--envs`` x ``--steps`` from the test image env (``tests/image_envs.py``: a float vector beside a
uint8 ``--shape`` image, the observation a TensorDict), then run PPO's update on it with the Nature
CNN policy (``policy=cnn``). ``--rollout float32`` converts the rollout's images to float32 before
the update (the float32 rollout that uint8 storage replaces); ``--step clipppo`` takes TorchRL's
ClipPPOLoss path instead of the fused step. Prints one JSON line.

    PYTHONPATH=src python benchmarks/image_update.py --rollout uint8 --step fused
    PYTHONPATH=src python benchmarks/image_update.py --rollout float32 --step fused
    PYTHONPATH=src python benchmarks/image_update.py --rollout uint8 --step clipppo
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--envs", type=int, default=8)
    p.add_argument("--steps", type=int, default=128)
    p.add_argument("--shape", type=int, nargs=3, default=(4, 84, 84))
    p.add_argument("--mb", type=int, default=256)
    p.add_argument("--epochs", type=int, default=1)
    p.add_argument("--rollout", choices=("uint8", "float32"), default="uint8")
    p.add_argument("--step", choices=("fused", "clipppo"), default="fused")
    p.add_argument("--threads", type=int, default=1)
    args = p.parse_args()
    sys.path.insert(0, str(REPO / "tests"))
    import torch
    from hydra import compose, initialize_config_dir
    from image_envs import ImageReach

    from rlexp.algorithms import make_algorithm
    from rlexp.config.paths import CONF_DIR
    from rlexp.config.schema import register_configs
    from rlexp.config.validate import to_root_config
    from rlexp.policies.actor_critic import policy_for_env
    from rlexp.training.collector import RolloutCollector

    torch.set_num_threads(args.threads)
    register_configs()
    overrides = [
        "env=hopper", "policy=cnn", f"env.num_envs={args.envs}",
        f"trainer.frames_per_batch={args.envs * args.steps}",
        f"algorithm.mini_batch_size={args.mb}", f"algorithm.num_epochs={args.epochs}",
        "algorithm.compile=false",
    ]  # fmt: skip
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        config = to_root_config(compose(config_name="config", overrides=overrides))
    c, h, w = args.shape
    env = ImageReach(args.envs, seed=0, channels=c, height=h, width=w, max_len=50)
    torch.manual_seed(0)
    policy = policy_for_env(config.policy, config.env, env)
    algo = make_algorithm(config.algorithm, policy, 10)
    algo.use_fused_step = args.step == "fused"
    col = RolloutCollector(
        env, policy.sampling_policy(), frames_per_batch=args.envs * args.steps, total_frames=-1,
        trust_policy=True, auto_register_policy_transforms=False,
    )  # fmt: skip
    t0 = time.perf_counter()
    batch = col.rollout()
    collect_s = time.perf_counter() - t0
    col.shutdown()
    if args.rollout == "float32":
        for key in (("observation", "pixels"), ("next", "observation", "pixels")):
            batch.set(key, batch.get(key).float())
    images = sum(
        batch.get(k).nbytes for k in (("observation", "pixels"), ("next", "observation", "pixels"))
    )
    rss_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0 = time.perf_counter()
    algo.compute_advantages(batch.clone())  # GAE alone (the update runs it again)
    gae_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    algo.update(batch)
    update_s = time.perf_counter() - t0
    minibatches = args.epochs * (args.envs * args.steps // args.mb)
    print(
        json.dumps(
            {
                **vars(args),
                "shape": list(args.shape),
                "rollout_image_mb": round(images / 2**20, 1),
                "collect_s": round(collect_s, 2),
                "update_s": round(update_s, 2),
                "gae_s": round(gae_s, 2),
                "per_minibatch_ms": round(1000 * (update_s - gae_s) / minibatches, 1),
                "peak_rss_before_update_mb": round(rss_before / 1024, 1),
                "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
                "step_taken": "fused" if algo.fused is not None else "clipppo",
            }
        )
    )


if __name__ == "__main__":
    main()
