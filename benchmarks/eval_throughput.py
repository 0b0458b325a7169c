"""Env-steps/s of an evaluation round: TorchRL's loop against the lean loop, over numbers of env copies.

A round is what ``Trainer.eval_once`` times: ``env.set_seed(eval seed)`` then
``run_episodes(env, deterministic sampling policy, episodes)`` with one torch thread. Env-steps/s
counts the steps of the episodes that make the metrics (``episodes x mean length``); copies that
have finished their quota keep stepping until the round ends, and that work is not counted. The
policy is a freshly initialised one from ``conf/policy`` (``--seed``): on tasks whose episodes end
early (Hopper) a trained policy gives other lengths. Each (loop, copies) pair builds its env once;
the pairs are interleaved over ``--repeats`` rounds (after one untimed warm-up round each) and the
table gives medians with min and max. Returns must agree between the loops for the same copies.

    PYTHONPATH=src .venv/bin/python benchmarks/eval_throughput.py --env half_cheetah \
        --copies 1,2,5,10 --episodes 10 --repeats 5
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))
os.environ.setdefault("MUJOCO_GL", "egl")


def compose(env: str, seed: int):
    """rlexp's typed config with ``env=<env>``, composed from conf/ as ``python train.py`` does."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir

    from rlexp.config.schema import register_configs
    from rlexp.config.validate import to_root_config

    register_configs()
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        return to_root_config(hydra_compose("config", overrides=[f"env={env}", f"seed={seed}"]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="half_cheetah", help="conf/env/<env>.yaml")
    parser.add_argument("--copies", default="1,2,5,10", help="numbers of eval env copies")
    parser.add_argument("--loops", default="torchrl,lean", help="torchrl and/or lean")
    parser.add_argument("--episodes", type=int, default=10, help="episodes per round")
    parser.add_argument("--repeats", type=int, default=5, help="timed rounds per (loop, copies)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    import torch

    from rlexp.envs.factory import make_env
    from rlexp.policies.actor_critic import make_policy
    from rlexp.training.build import EVAL_SEED_OFFSET
    from rlexp.training.evaluation import run_episodes
    from rlexp.training.loop import one_torch_thread

    torch.manual_seed(args.seed)
    config = compose(args.env, args.seed)
    e = config.env
    eval_seed = config.seed + EVAL_SEED_OFFSET
    copies = [int(c) for c in args.copies.split(",")]
    loops = args.loops.split(",")
    envs = {n: make_env(e, n, eval_seed) for n in copies}
    env0 = envs[copies[0]]
    policy = make_policy(
        config.policy,
        env0.observation_spec["observation"].shape[-1],
        env0.action_spec.shape[-1],
        env0.action_spec,
        e.normalize_observations,
        e.clip_observations,
    ).sampling_policy(deterministic=True)

    def round_(loop: str, n: int) -> tuple[float, dict[str, float]]:
        env = envs[n]
        start = time.perf_counter()
        env.set_seed(eval_seed)
        with one_torch_thread():
            metrics = run_episodes(env, policy, args.episodes, lean=loop == "lean")
        return time.perf_counter() - start, metrics

    pairs = [(loop, n) for n in copies for loop in loops]
    times: dict[tuple[str, int], list[float]] = {p: [] for p in pairs}
    results: dict[tuple[str, int], dict[str, float]] = {}
    for p in pairs:
        results[p] = round_(*p)[1]  # warm-up
    for _ in range(args.repeats):
        for p in pairs:
            seconds, metrics = round_(*p)
            if metrics != results[p]:
                raise RuntimeError(f"{p}: a repeated round gave other numbers: {metrics}")
            times[p].append(seconds)
    for n in copies:
        got = {loop: results[(loop, n)] for loop in loops}
        if len({tuple(m.items()) for m in got.values()}) > 1:
            raise RuntimeError(f"{n} copies: the loops disagree: {got}")

    base = statistics.median(times[(loops[0], copies[0])])
    print(
        f"{config.env.name}, {args.episodes} episodes per round, {args.repeats} repeats; "
        f"{platform.node()} ({os.cpu_count()} cores), torch {torch.__version__}\n"
    )
    print("| loop | copies | mean length | round s (median) | min-max s | env-steps/s | vs first |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for loop, n in pairs:
        t = times[(loop, n)]
        m = results[(loop, n)]
        steps = m["eval/episodes"] * m["eval/episode_length"]
        med = statistics.median(t)
        print(
            f"| {loop} | {n} | {m['eval/episode_length']:.0f} | {med:.3f} | "
            f"{min(t):.3f}-{max(t):.3f} | {steps / med:,.0f} | {base / med:.2f}x |"
        )
    for env in envs.values():
        env.close()


if __name__ == "__main__":
    main()
