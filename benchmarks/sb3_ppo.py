"""PPO on a Gymnasium task with Stable-Baselines3, from launch to exit: the SB3 side of
``benchmarks/end_to_end.py`` (issue #18: the benchmark measures what users wait for).

The script an SB3 user writes for the job ``python train.py`` does with rlexp's defaults; every
setting is a flag, and ``end_to_end.py`` fills them in from rlexp's composed config:

- the env through ``make_vec_env`` (``Monitor`` inside, so ``ep_info_buffer`` holds raw episode
  returns), wrapped in ``VecNormalize`` (observations, and rewards by the running std of the
  discounted return, each clipped);
- ``PPO("MlpPolicy")`` with separate pi / vf networks, the learning rate annealed linearly to 0;
- ``EvalCallback`` every ``--eval-every`` steps on a separate eval env, a ``VecNormalize`` that does
  not update its statistics or scale rewards, synced from the training env before each round (as
  rl-zoo does), deterministic actions; the best model (and its ``VecNormalize``) saved on
  improvement; when no round fell inside the run, one round after it (as rlexp does);
- ``CheckpointCallback`` every ``--save-every`` steps with the ``VecNormalize`` statistics, the final
  model and statistics saved at the end; TensorBoard and the console table with ``--tensorboard`` /
  ``--verbose 1``.

It writes ``<run dir>/result.json``: env steps done, the mean return of the last 100 training
episodes, the last evaluation's mean return, and, with ``--anchor``, the wall-clock time
(``time.time()``) and step of the first rollout end at which the mean of the last 100 training
episodes reached the anchor.

    python benchmarks/sb3_ppo.py --env-id HalfCheetah-v5 --steps 61440 --run-dir /tmp/sb3_run
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch
from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import (
    BaseCallback,
    CallbackList,
    CheckpointCallback,
    EvalCallback,
)
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.vec_env import VecNormalize, sync_envs_normalization

ACTIVATIONS = {
    "tanh": torch.nn.Tanh,
    "relu": torch.nn.ReLU,
    "elu": torch.nn.ELU,
    "gelu": torch.nn.GELU,
    "silu": torch.nn.SiLU,
    "swish": torch.nn.SiLU,
}


class TimeToResult(BaseCallback):
    """At each rollout end: the first time the mean of the last 100 training episodes >= anchor."""

    def __init__(self, anchor: float | None) -> None:
        super().__init__()
        self.anchor = anchor
        self.reached: dict[str, float] | None = None

    def _on_step(self) -> bool:
        return True

    def _on_rollout_end(self) -> None:
        buf = self.model.ep_info_buffer
        if self.anchor is None or self.reached is not None or not buf:
            return
        mean = float(np.mean([ep["r"] for ep in buf]))
        if mean >= self.anchor:
            self.reached = {"time": time.time(), "step": self.num_timesteps, "return": mean}


class SaveVecNormalize(BaseCallback):
    """Saves the training env's ``VecNormalize`` next to the best model (rl-zoo's callback)."""

    def __init__(self, path: Path) -> None:
        super().__init__()
        self.path = path

    def _on_step(self) -> bool:
        self.model.get_vec_normalize_env().save(str(self.path))
        return True


def sizes(text: str) -> list[int]:
    """``"64,64"`` -> ``[64, 64]``."""
    return [int(x) for x in text.split(",") if x]


def parse_args() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    on_off = argparse.BooleanOptionalAction
    p.add_argument("--env-id", default="HalfCheetah-v5", help="Gymnasium id")
    p.add_argument("--num-envs", type=int, default=1, help="training envs (DummyVecEnv)")
    p.add_argument("--steps", type=int, default=1_000_000, help="total_timesteps of learn()")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--eval-seed", type=int, default=1_000_000, help="seed of the eval env")
    p.add_argument("--threads", type=int, default=1, help="torch.set_num_threads")
    # PPO
    p.add_argument("--n-steps", type=int, default=2048, help="steps per env per rollout")
    p.add_argument("--batch-size", type=int, default=64, help="minibatch size")
    p.add_argument("--n-epochs", type=int, default=10)
    p.add_argument("--lr", type=float, default=3e-4)
    p.add_argument("--anneal-lr", action=on_off, default=True, help="linear to 0 over the run")
    p.add_argument("--adam-eps", type=float, default=1e-5)
    p.add_argument("--gamma", type=float, default=0.99)
    p.add_argument("--gae-lambda", type=float, default=0.95)
    p.add_argument("--clip-range", type=float, default=0.2)
    p.add_argument("--clip-range-vf", type=float, default=None)
    p.add_argument("--ent-coef", type=float, default=0.0)
    p.add_argument("--vf-coef", type=float, default=0.5)
    p.add_argument("--max-grad-norm", type=float, default=0.5)
    p.add_argument("--normalize-advantage", action=on_off, default=True)
    # policy
    p.add_argument("--pi-arch", type=sizes, default=[64, 64], help="actor hidden sizes")
    p.add_argument("--vf-arch", type=sizes, default=[64, 64], help="critic hidden sizes")
    p.add_argument("--activation", choices=list(ACTIVATIONS), default="tanh")
    p.add_argument("--log-std-init", type=float, default=0.0)
    p.add_argument("--ortho-init", action=on_off, default=True)
    # VecNormalize
    p.add_argument("--norm-obs", action=on_off, default=True)
    p.add_argument("--clip-obs", type=float, default=10.0)
    p.add_argument("--norm-reward", action=on_off, default=True)
    p.add_argument("--clip-reward", type=float, default=10.0)
    # evaluation, checkpoints, logging
    p.add_argument("--eval-every", type=int, default=50_000, help="env steps; 0: no evaluation")
    p.add_argument("--eval-episodes", type=int, default=10)
    p.add_argument("--eval-envs", type=int, default=1, help="eval env copies (rl-zoo: 1)")
    p.add_argument("--save-every", type=int, default=100_000, help="env steps; 0: only the end")
    p.add_argument("--tensorboard", action=on_off, default=True)
    p.add_argument("--verbose", type=int, default=1)
    p.add_argument("--run-dir", type=Path, required=True)
    p.add_argument("--anchor", type=float, default=None, help="train return for time to result")
    return p.parse_args()


def main() -> None:
    args = parse_args()
    torch.set_num_threads(args.threads)
    run_dir = args.run_dir
    run_dir.mkdir(parents=True, exist_ok=True)
    norm = {"norm_obs": args.norm_obs, "clip_obs": args.clip_obs, "gamma": args.gamma}
    env = VecNormalize(
        make_vec_env(args.env_id, n_envs=args.num_envs, seed=args.seed),
        norm_reward=args.norm_reward,
        clip_reward=args.clip_reward,
        **norm,
    )
    lr = args.lr
    model = PPO(
        "MlpPolicy",
        env,
        learning_rate=(lambda progress_remaining: lr * progress_remaining)
        if args.anneal_lr
        else lr,
        n_steps=args.n_steps,
        batch_size=args.batch_size,
        n_epochs=args.n_epochs,
        gamma=args.gamma,
        gae_lambda=args.gae_lambda,
        clip_range=args.clip_range,
        clip_range_vf=args.clip_range_vf,
        normalize_advantage=args.normalize_advantage,
        ent_coef=args.ent_coef,
        vf_coef=args.vf_coef,
        max_grad_norm=args.max_grad_norm,
        policy_kwargs={
            "net_arch": {"pi": args.pi_arch, "vf": args.vf_arch},
            "activation_fn": ACTIVATIONS[args.activation],
            "log_std_init": args.log_std_init,
            "ortho_init": args.ortho_init,
            "optimizer_kwargs": {"eps": args.adam_eps},
        },
        tensorboard_log=str(run_dir / "tensorboard") if args.tensorboard else None,
        device="cpu",
        seed=args.seed,
        verbose=args.verbose,
    )
    watch = TimeToResult(args.anchor)
    callbacks: list[BaseCallback] = [watch]
    if args.save_every > 0:
        callbacks.append(
            CheckpointCallback(
                save_freq=max(args.save_every // args.num_envs, 1),
                save_path=str(run_dir / "checkpoints"),
                save_vecnormalize=True,
            )
        )
    evaluator = None
    if args.eval_every > 0 and args.eval_episodes > 0:
        # The eval env: the same normalisation, frozen; EvalCallback syncs its statistics.
        eval_env = VecNormalize(
            make_vec_env(args.env_id, n_envs=args.eval_envs, seed=args.eval_seed),
            training=False,
            norm_reward=False,
            **norm,
        )
        evaluator = EvalCallback(
            eval_env,
            eval_freq=max(args.eval_every // args.num_envs, 1),
            n_eval_episodes=args.eval_episodes,
            deterministic=True,
            best_model_save_path=str(run_dir / "best"),
            callback_on_new_best=SaveVecNormalize(run_dir / "best" / "vecnormalize.pkl"),
            log_path=str(run_dir / "eval"),
            verbose=args.verbose,
        )
        callbacks.append(evaluator)
    model.learn(total_timesteps=args.steps, callback=CallbackList(callbacks))

    final_eval, eval_rounds = None, 0
    if evaluator is not None:
        eval_rounds = len(evaluator.evaluations_timesteps)
        if eval_rounds:
            final_eval = float(evaluator.last_mean_reward)
        else:  # no round inside the run: one after it, as rlexp does
            eval_rounds = 1
            sync_envs_normalization(env, evaluator.eval_env)
            mean, _ = evaluate_policy(
                model, evaluator.eval_env, n_eval_episodes=args.eval_episodes, deterministic=True
            )
            final_eval = float(mean)
    model.save(run_dir / "final_model")
    env.save(str(run_dir / "vecnormalize.pkl"))
    buf = model.ep_info_buffer
    result = {
        "steps": int(model.num_timesteps),
        "final_train_return": float(np.mean([ep["r"] for ep in buf])) if buf else None,
        "final_eval_return": final_eval,
        "eval_rounds": eval_rounds,
        "anchor": watch.reached,
    }
    (run_dir / "result.json").write_text(json.dumps(result))


if __name__ == "__main__":
    main()
