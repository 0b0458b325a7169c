"""``rlexp`` command: ``rlexp train [overrides]``, ``rlexp eval CHECKPOINT [--episodes N]``,
``rlexp report SWEEP_DIR``."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

log = logging.getLogger("rlexp")


def evaluate(checkpoint: str, episodes: int, num_envs: int | None, seed: int) -> dict[str, float]:
    """Rebuild the run's env and policy from a checkpoint and evaluate it deterministically."""
    from rlexp.app import seed_everything
    from rlexp.checkpoint import load_checkpoint
    from rlexp.config.validate import to_root_config
    from rlexp.envs.factory import make_env
    from rlexp.evaluation import run_episodes
    from rlexp.policies.actor_critic import make_policy

    ckpt = load_checkpoint(checkpoint)
    config = to_root_config(ckpt["config"])
    e = config.env
    seed_everything(seed)
    n = num_envs or max(1, e.num_eval_envs)
    env = make_env(e, n, seed)
    obs_dim = env.observation_spec["observation"].shape[-1]
    policy = make_policy(
        config.policy,
        obs_dim,
        env.action_spec.shape[-1],
        env.action_spec,
        e.normalize_observations,
        e.clip_observations,
    )
    policy.load_state_dict(ckpt["policy"])
    metrics = run_episodes(env, policy.sampling_policy(deterministic=True), episodes)
    env.close()
    return {
        "path": ckpt["path"],
        "global_step": int(ckpt["global_step"]),
        "mean_return": metrics["eval/episode_return"],
        "std_return": metrics["eval/episode_return_std"],
        "episodes": int(metrics["eval/episodes"]),
    }


def main(argv: list[str] | None = None) -> None:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] == "train":  # exactly `python train.py ...` (--config-json, --distributed)
        from rlexp.launch.json_entry import main as train_main

        train_main(argv[1:])
        return
    parser = argparse.ArgumentParser(prog="rlexp", description="rlexp experiment tools")
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("train", help="train (same as python train.py; Hydra overrides follow)")
    ev = sub.add_parser(
        "eval", help="evaluate a checkpoint: mean return over N deterministic episodes"
    )
    ev.add_argument("checkpoint", help="a checkpoint file, or a run dir (its newest checkpoint)")
    ev.add_argument("--episodes", type=int, default=10)
    ev.add_argument("--num-envs", type=int, default=None)
    ev.add_argument("--seed", type=int, default=12345)
    rep = sub.add_parser(
        "report", help="a sweep's per-configuration statistics: report.md, report.csv, curves.png"
    )
    rep.add_argument("sweep_dir", help="a multirun dir, e.g. multirun/2026-11-22/10-00-00")
    rep.add_argument("--metric", default="eval/episode_return", help="score and curve metric")
    rep.add_argument("--no-plot", action="store_true", help="skip curves.png")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if args.command == "report":
        from rlexp.report import report

        try:
            print(report(Path(args.sweep_dir), args.metric, plot=not args.no_plot), end="")
        except FileNotFoundError as exc:
            print(f"rlexp report: {exc}", file=sys.stderr)
            sys.exit(2)
        return
    if args.command == "eval":
        try:
            res = evaluate(args.checkpoint, args.episodes, args.num_envs, args.seed)
        except (FileNotFoundError, ValueError) as exc:
            print(f"rlexp eval: {exc}", file=sys.stderr)
            sys.exit(2)
        print(
            f"checkpoint {res['path']} (step {res['global_step']}): mean return "
            f"{res['mean_return']:.3f} +- {res['std_return']:.3f} over {res['episodes']} episodes"
        )


if __name__ == "__main__":
    main()
