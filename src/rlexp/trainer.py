"""The training loop: collect a rollout, update PPO, log, evaluate, checkpoint. Read it top to bottom."""

from __future__ import annotations

import logging
import time
from collections import deque
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import TensorDictBase
from torchrl.collectors import Collector
from torchrl.envs import EnvBase

from rlexp.algorithms.ppo import PPO
from rlexp.checkpoint import checkpoint_path, rng_state, save_checkpoint, set_rng_state
from rlexp.config.schema import TrainerConfig
from rlexp.events import EventContext, EventManager
from rlexp.logging import MetricLogger
from rlexp.policies.actor_critic import ActorCritic
from rlexp.progress import Progress

log = logging.getLogger(__name__)


def crossed(before: int, after: int, every: int) -> bool:
    """True when the step count went past a multiple of ``every`` (not only on exact equality)."""
    return every > 0 and after // every > before // every


class Trainer:
    """Coordinates policy, algorithm and envs; owns the counters, windows and checkpoints."""

    def __init__(
        self,
        *,
        cfg: TrainerConfig,
        policy: ActorCritic,
        algorithm: PPO,
        env: EnvBase,
        eval_env: EnvBase | None,
        logger: MetricLogger,
        event_manager: EventManager,
        eval_event_manager: EventManager,
        run_dir: Path,
        config_dict: dict[str, Any],
    ) -> None:
        self.cfg = cfg
        self.policy = policy
        self.algorithm = algorithm
        self.env = env
        self.eval_env = eval_env
        self.logger = logger
        self.event_manager = event_manager
        self.eval_event_manager = eval_event_manager
        self.run_dir = run_dir
        self.ckpt_dir = run_dir / "checkpoints"
        self.config_dict = config_dict
        self.global_step = 0
        self.ret_window: deque[float] = deque(maxlen=100)
        self.len_window: deque[int] = deque(maxlen=100)
        self.last_eval: dict[str, float] = {}
        self.last_checkpoint: Path | None = None
        self._num_envs = int(env.batch_size.numel()) if len(env.batch_size) else 1
        self._ep_ret = np.zeros(self._num_envs)
        self._ep_len = np.zeros(self._num_envs, dtype=np.int64)
        self._term_means: dict[str, float] = {}
        self.collector = Collector(
            env,
            policy.sampling_policy(),
            frames_per_batch=cfg.frames_per_batch,
            total_frames=-1,
            trust_policy=True,
            track_traj_ids=False,
        )
        self._rollouts = iter(self.collector)
        self.progress: Progress | None = None
        self._timing = {"collect": 0.0, "update": 0.0}

    # -- the loop ----------------------------------------------------------------------------------
    def train(self, total_timesteps: int) -> None:
        """Train until ``global_step`` reaches ``total_timesteps`` env steps."""
        self.event_manager.fire("startup", self._ctx())
        self.progress = Progress(total_timesteps, enabled=self.cfg.progress, start=self.global_step)
        with self.progress:
            while self.global_step < total_timesteps:
                before = self.global_step
                batch = self.collect_rollout()
                t0 = time.perf_counter()
                losses = self.algorithm.update(batch)
                self.policy.normalizer.update(batch["observation"])
                self._timing["update"] = time.perf_counter() - t0
                self.log_train(losses)
                self.event_manager.fire("interval", self._ctx())
                if crossed(before, self.global_step, self.cfg.eval_every):
                    self.eval_once()
                if crossed(before, self.global_step, self.cfg.save_every):
                    self.save_checkpoint()
        self.save_checkpoint()

    def collect_rollout(self) -> TensorDictBase:
        """One batch of ``frames_per_batch`` env steps through the TorchRL collector."""
        t0 = time.perf_counter()
        batch = next(self._rollouts)
        self._timing["collect"] = time.perf_counter() - t0
        self.global_step += batch.numel()
        self._track_episodes(batch)
        return batch

    def log_train(self, losses: dict[str, float]) -> None:
        """Log losses, episode statistics, per-term rewards and throughput."""
        iteration = self.algorithm.iteration
        elapsed = self._timing["collect"] + self._timing["update"]
        sps = self.cfg.frames_per_batch / max(elapsed, 1e-9)
        metrics = dict(losses)
        metrics["perf/sps"] = sps
        metrics["perf/collect_time"] = self._timing["collect"]
        metrics["perf/update_time"] = self._timing["update"]
        if self.ret_window:
            metrics["train/episode_return"] = float(np.mean(self.ret_window))
            metrics["train/episode_length"] = float(np.mean(self.len_window))
        metrics.update(self._term_means)
        if self.progress is not None:
            self.progress.update(self.global_step, sps, metrics.get("train/episode_return"))
        if iteration % self.cfg.log_every == 0:
            self.logger.log(metrics, self.global_step)
            ret = metrics.get("train/episode_return", float("nan"))
            log.info("[train] step=%d sps=%.0f return(100)=%.2f", self.global_step, sps, ret)

    @torch.no_grad()
    def eval_once(self) -> dict[str, float]:
        """Deterministic evaluation over ``eval_episodes`` episodes on the eval env."""
        if self.eval_env is None or self.cfg.eval_episodes <= 0:
            return {}
        env = self.eval_env
        n = int(env.batch_size.numel())
        quota = np.full(n, self.cfg.eval_episodes // n)
        quota[: self.cfg.eval_episodes % n] += 1
        policy = self.policy.sampling_policy(deterministic=True)
        returns: list[float] = []
        lengths: list[int] = []
        successes: list[float] = []
        ep_ret = np.zeros(n)
        ep_len = np.zeros(n, dtype=np.int64)
        ep_success = np.zeros(n)
        done_count = np.zeros(n, dtype=np.int64)
        td = env.reset()
        self.eval_event_manager.fire("reset", self._ctx(env))
        while (done_count < quota).any():
            td = policy(td)
            self.eval_event_manager.fire("step", self._ctx(env))
            out, td = env.step_and_maybe_reset(td)
            nxt = out["next"]
            ep_ret += nxt["reward"].reshape(n).cpu().numpy()
            ep_len += 1
            if "metrics" in nxt.keys() and "success" in nxt["metrics"].keys():
                ep_success = np.maximum(ep_success, nxt["metrics", "success"].reshape(n).cpu().numpy())
            done = nxt["done"].reshape(n).cpu().numpy()
            for i in np.flatnonzero(done):
                if done_count[i] < quota[i]:
                    returns.append(float(ep_ret[i]))
                    lengths.append(int(ep_len[i]))
                    successes.append(float(ep_success[i]))
                    done_count[i] += 1
                ep_ret[i], ep_len[i], ep_success[i] = 0.0, 0, 0.0
        metrics = {
            "eval/episode_return": float(np.mean(returns)),
            "eval/episode_return_std": float(np.std(returns)),
            "eval/episode_length": float(np.mean(lengths)),
            "eval/success_rate": float(np.mean(successes)),
        }
        self.last_eval = metrics
        self.logger.log(metrics, self.global_step)
        log.info(
            "[eval] step=%d return=%.2f +- %.2f length=%.1f success=%.2f (%d episodes)",
            self.global_step, metrics["eval/episode_return"], metrics["eval/episode_return_std"],
            metrics["eval/episode_length"], metrics["eval/success_rate"], len(returns),
        )
        self.eval_event_manager.fire("trigger", self._ctx(env), signal="eval_end")
        return metrics

    def save_checkpoint(self) -> Path:
        """Write everything needed to evaluate or continue this run to ``checkpoints/``."""
        path = checkpoint_path(self.ckpt_dir, self.cfg.exp_name, self.global_step)
        if self.last_checkpoint == path:
            return path
        save_checkpoint(path, self.state_dict())
        self.last_checkpoint = path
        log.info("[ckpt] saved %s", path)
        self.event_manager.fire("trigger", self._ctx(), signal="checkpoint")
        return path

    # -- state ---------------------------------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        return {
            "global_step": self.global_step,
            "policy": self.policy.state_dict(),
            "algorithm": self.algorithm.state_dict(),
            "windows": {"returns": list(self.ret_window), "lengths": list(self.len_window)},
            "events": {"train": self.event_manager.state_dict(), "eval": self.eval_event_manager.state_dict()},
            "rng": rng_state(),
            "last_eval": dict(self.last_eval),
            "config": self.config_dict,
        }

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        self.global_step = int(sd["global_step"])
        self.policy.load_state_dict(sd["policy"])
        self.algorithm.load_state_dict(sd["algorithm"])
        self.ret_window.extend(sd["windows"]["returns"])
        self.len_window.extend(sd["windows"]["lengths"])
        self.event_manager.load_state_dict(sd["events"]["train"])
        self.eval_event_manager.load_state_dict(sd["events"]["eval"])
        set_rng_state(sd["rng"])

    def close(self) -> None:
        """Shut the collector, envs and loggers down."""
        self.collector.shutdown()
        for env in (self.env, self.eval_env):
            if env is not None and not env.is_closed:
                env.close()
        self.logger.close()

    # -- helpers -------------------------------------------------------------------------------------
    def _ctx(self, env: EnvBase | None = None) -> EventContext:
        return EventContext(env=env if env is not None else self.env, global_step=self.global_step)

    def _track_episodes(self, batch: TensorDictBase) -> None:
        """Update the return/length windows and per-term means from a [num_envs, T] rollout."""
        nxt = batch["next"]
        rewards = nxt["reward"].reshape(self._num_envs, -1).cpu().numpy()
        dones = nxt["done"].reshape(self._num_envs, -1).cpu().numpy()
        for t in range(rewards.shape[1]):
            self._ep_ret += rewards[:, t]
            self._ep_len += 1
            finished = dones[:, t]
            if finished.any():
                self.ret_window.extend(self._ep_ret[finished].tolist())
                self.len_window.extend(self._ep_len[finished].tolist())
                self._ep_ret[finished] = 0.0
                self._ep_len[finished] = 0
        self._term_means = {}
        for group in ("rewards", "metrics"):
            if group in nxt.keys():
                for key, value in nxt[group].items():
                    self._term_means[f"{group}/{key}"] = float(value.float().mean())
