"""The training loop: collect a rollout, update the algorithm (PPO, GRPO), log, evaluate, checkpoint.
Read it top to bottom."""

from __future__ import annotations

import logging
import time
from collections import deque
from pathlib import Path
from types import MappingProxyType
from typing import Any

import numpy as np
import torch
from tensordict import TensorDictBase
from torchrl.envs import EnvBase, TransformedEnv

from rlexp.algorithms.base import Algorithm, NonFiniteError
from rlexp.checkpoint import (
    checkpoint_path,
    prune_checkpoints,
    rng_state,
    save_checkpoint,
    set_rng_state,
)
from rlexp.collector import RolloutCollector
from rlexp.config.schema import TrainerConfig
from rlexp.evaluation import run_episodes
from rlexp.events import EventContext, EventManager
from rlexp.events.transform import EventTransform
from rlexp.hooks import HookManager, HookState
from rlexp.launch.distributed import DistInfo, all_gather_object, all_reduce_sum
from rlexp.logging import MetricLogger
from rlexp.loop import (
    base_env,
    check_rollout_finite,
    crossed,
    one_torch_thread,
    parameter_digest,
)
from rlexp.policies.actor_critic import GaussianPolicy
from rlexp.progress import Progress

log = logging.getLogger(__name__)


class StopRequested(Exception):
    """Raised by ``train`` after it checkpointed at a safe point because ``request_stop`` was called."""


class Trainer:
    """Coordinates policy, algorithm and envs; owns the counters, windows and checkpoints."""

    def __init__(
        self,
        *,
        cfg: TrainerConfig,
        policy: GaussianPolicy,
        algorithm: Algorithm,
        env: EnvBase,
        eval_env: EnvBase | None,
        logger: MetricLogger,
        event_manager: EventManager,
        eval_event_manager: EventManager,
        run_dir: Path,
        config_dict: dict[str, Any],
        versions: dict[str, str] | None = None,
        dist: DistInfo | None = None,
        eval_seed: int = 0,
        console: bool = True,
        hooks: HookManager | None = None,
    ) -> None:
        self.cfg = cfg
        self.console = console  # logger.console: the [train] / [eval] summary lines
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
        self.versions = dict(versions or {})
        self.dist = dist or DistInfo()  # rank / world size; rank 0 alone logs, evaluates and saves
        self.eval_seed = eval_seed  # every eval round starts fresh episodes from this seed
        self.global_step = 0
        self.ret_window: deque[float] = deque(maxlen=100)
        self.len_window: deque[int] = deque(maxlen=100)
        self.last_eval: dict[str, float] = {}
        self.best_metric = -float("inf")
        self.last_checkpoint: Path | None = None
        self.resumed_from: str | None = None
        self._num_envs = int(env.batch_size.numel()) if len(env.batch_size) else 1
        self._ep_ret = np.zeros(self._num_envs)
        self._ep_len = np.zeros(self._num_envs, dtype=np.int64)
        self._term_means: dict[str, float] = {}
        self._timing = {"collect": 0.0, "update": 0.0, "eval": 0.0}
        self.collector: RolloutCollector | None = None  # built when training starts, after a resume
        self._event_transform: EventTransform | None = None
        self._resume_rng: dict[str, Any] | None = None
        self._resume_obs: torch.Tensor | None = None  # what the policy acts on next, on resume
        self.stop_reason: str | None = None  # set by request_stop (a signal handler)
        self.hooks = hooks or HookManager({})  # user code at the loop's hook points (docs/hooks.md)
        self.stopped_early: str | None = None  # why a hook ended the run (status stopped_early)
        self.total_steps = 0
        self._last_losses: dict[str, float] = {}
        self._last_metrics: dict[str, float] = {}
        self._hparams_set: dict[str, float] = {}  # set by hooks since the last log (logged)
        if event_manager.has("step", "reset"):  # only then: others pay nothing per step
            self._event_transform = EventTransform(event_manager, run_dir)
            self.env = TransformedEnv(env, self._event_transform)
        self.progress: Progress | None = None
        self.safe_point = True  # False from the start of a rollout until its update is applied

    # -- the loop ----------------------------------------------------------------------------------
    def train(self, total_timesteps: int) -> None:
        """Train until ``global_step`` reaches ``total_timesteps`` env steps (or a hook stops it)."""
        self.total_steps = total_timesteps
        if self.global_step == 0:
            self.event_manager.fire("startup", self._ctx())
        self._start_collector()
        if self._resume_rng is not None:  # after the collector's construction (it draws)
            set_rng_state(self._resume_rng)
            self._resume_rng = None
        self.progress = Progress(total_timesteps, enabled=self.cfg.progress, start=self.global_step)
        status = "failed"
        try:
            self._hook("train_start")
            self._apply_hook_decisions()
            with self.progress:
                while self.global_step < total_timesteps and self.stopped_early is None:
                    self._iteration()
            if self.dist.enabled:
                self.check_ranks_in_sync()
            self.save_checkpoint()
            status = "finished" if self.stopped_early is None else "stopped_early"
        except (StopRequested, KeyboardInterrupt):
            status = "interrupted"
            raise
        finally:
            self._hook_train_end(status)

    def _iteration(self) -> None:
        """One iteration: collect, update, log, evaluate and checkpoint when due, stop if asked."""
        before = self.global_step
        self.safe_point = False
        batch = self.collect_rollout()
        self._hook("rollout_end", batch=batch)
        self._apply_hook_decisions()  # e.g. a schedule's value for this update, on every rank
        losses = self.update(batch)
        self.safe_point = True  # the update is complete: a checkpoint now is consistent
        self._last_losses = dict(losses)
        self._hook("update_end")
        self.log_train(losses)
        self.event_manager.fire("interval", self._ctx(batch=batch))
        if crossed(before, self.global_step, self.cfg.eval_every):
            self.eval_once()
        if crossed(before, self.global_step, self.cfg.save_every):
            self.save_checkpoint()
        self._apply_hook_decisions()  # a hook's stop: the loop ends, the run saves and finishes
        if self.dist.enabled:  # a signal may reach one rank only: all stop together
            self._agree_on_stop()
        if self.stop_reason is not None:  # a safe point: checkpoint, then let the caller decide
            self.save_checkpoint()
            raise StopRequested(self.stop_reason)

    def _agree_on_stop(self) -> None:
        device = next(self.policy.parameters()).device  # nccl reduces GPU tensors only
        requested = torch.tensor([float(self.stop_reason is not None)], device=device)
        if all_reduce_sum(requested).item() > 0 and self.stop_reason is None:
            self.stop_reason = "stop requested on another rank"

    def check_ranks_in_sync(self) -> None:
        """Distributed: every rank must hold the same parameters (gradients were averaged)."""
        digest = parameter_digest(self.policy)
        digests = all_gather_object(digest)
        if len(set(digests)) != 1:
            raise RuntimeError(f"ranks diverged: parameter digests {digests}")
        log.info(
            "[dist] parameters identical on all %d ranks (sha256 %s)", self.dist.world_size, digest
        )

    def collect_rollout(self) -> TensorDictBase:
        """One batch of ``frames_per_batch`` env steps through the TorchRL collector."""
        t0 = time.perf_counter()
        with one_torch_thread():
            if self.algorithm.reset_each_rollout:  # GRPO: every env starts a new episode
                self.collector.reset()
                self._ep_ret[:] = 0.0  # the episodes in flight are dropped, not counted
                self._ep_len[:] = 0
            batch = next(self._rollouts)
        self._timing["collect"] = time.perf_counter() - t0
        self.global_step += batch.numel() * self.dist.world_size  # every rank collected as much
        if self._event_transform is not None:
            self._event_transform.global_step = self.global_step
        if self.cfg.nan_guard:  # every rank checks, and all raise together
            device = next(self.policy.parameters()).device  # where the backend reduces
            check_rollout_finite(batch, self.dist, device, self.global_step)
        self._track_episodes(batch)
        return batch

    def update(self, batch: TensorDictBase) -> dict[str, float]:
        """The algorithm's update on the rollout, then fold its observations into the normaliser."""
        t0 = time.perf_counter()
        try:
            losses = self.algorithm.update(batch)
        except NonFiniteError as exc:
            raise NonFiniteError(f"{exc} at step {self.global_step}") from None
        self.policy.normalizer.update(
            batch["observation"], all_reduce_sum if self.dist.enabled else None
        )
        self._timing["update"] = time.perf_counter() - t0
        return losses

    def log_train(self, losses: dict[str, float]) -> None:
        """Log losses, episode statistics, per-term rewards and throughput."""
        iteration = self.algorithm.iteration
        # Training throughput: an iteration that also evaluated is not slower at training (the
        # evaluation's time is perf/eval_time, and the run's wall time counts both).
        elapsed = self._timing["collect"] + self._timing["update"]
        sps = self.cfg.frames_per_batch * self.dist.world_size / max(elapsed, 1e-9)
        metrics = dict(losses)
        metrics["perf/sps"] = sps
        metrics["perf/collect_time"] = self._timing["collect"]
        metrics["perf/update_time"] = self._timing["update"]
        metrics["perf/eval_time"] = self._timing["eval"]
        self._timing["eval"] = 0.0
        if self.ret_window:
            metrics["train/episode_return"] = float(np.mean(self.ret_window))
            metrics["train/episode_length"] = float(np.mean(self.len_window))
        metrics.update(self._term_means)
        metrics.update({f"hparams/{k}": v for k, v in self._hparams_set.items()})
        self._hparams_set = {}
        if self.progress is not None:
            self.progress.update(self.global_step, sps, metrics.get("train/episode_return"))
        if iteration % self.cfg.log_every == 0:
            self._last_metrics = metrics
            self._hook("log", metrics=MappingProxyType(metrics))
            metrics.update(self.hooks.take_logged())  # rollout_end / update_end / log additions
            self.logger.log(metrics, self.global_step)
            ret = metrics.get("train/episode_return", float("nan"))
            if self.console:
                log.info("[train] step=%d sps=%.0f return(100)=%.2f", self.global_step, sps, ret)

    @torch.no_grad()
    def eval_once(self) -> dict[str, float]:
        """Deterministic evaluation over ``eval_episodes`` episodes spread over the eval envs."""
        if self.eval_env is None or self.cfg.eval_episodes <= 0 or not self.dist.is_main:
            return {}
        t_start = time.perf_counter()
        env = self.eval_env
        n = int(env.batch_size.numel())
        events = self.eval_event_manager

        def on_reset(td: TensorDictBase) -> TensorDictBase:
            events.fire("reset", self._ctx(env, env_ids=np.arange(n)))
            base = base_env(env)  # reset events may have moved objects: observe again
            if events.has("reset") and hasattr(base, "current_tensordict"):
                td.set("observation", base.current_tensordict().get("observation"))
            return td

        def on_step(td: TensorDictBase) -> None:
            events.fire("step", self._ctx(env, tensordict=td, phase="action"))
            events.fire("interval", self._ctx(env, tensordict=td))

        # Step / interval events (the eval video, noise) see each step's tensordict: TorchRL's loop.
        # Without them run_episodes takes the collector's lean loop (the same numbers, faster).
        per_step = on_step if events.has("step", "interval") else None
        policy = self.policy.sampling_policy(deterministic=True)
        # Fresh episodes from the same seed every round: rounds compare like with like, and a resumed
        # run evaluates exactly as an uninterrupted one (no eval episode spans two rounds).
        env.set_seed(self.eval_seed)
        with one_torch_thread():
            metrics = run_episodes(env, policy, self.cfg.eval_episodes, per_step, on_reset)
        episodes = int(metrics.pop("eval/episodes"))
        self.last_eval = metrics
        events.finalize(self._ctx(env))
        self._timing["eval"] += time.perf_counter() - t_start
        self.logger.log(metrics, self.global_step)
        if self.console:
            log.info(
                "[eval] step=%d return=%.2f +- %.2f length=%.1f success=%.2f (%d episodes)",
                self.global_step,
                metrics["eval/episode_return"],
                metrics["eval/episode_return_std"],
                metrics["eval/episode_length"],
                metrics["eval/success_rate"],
                episodes,
            )
        events.fire("trigger", self._ctx(env, metrics=metrics), signal="eval_end")
        self.event_manager.fire("trigger", self._ctx(metrics=metrics), signal="eval_end")
        self._hook("eval_end")
        self.logger.log(self.hooks.take_logged(), self.global_step)
        value = metrics.get(self.cfg.best_metric)
        if value is not None and value > self.best_metric:
            self.best_metric = value
            self._save_best()
        return metrics

    def save_checkpoint(self) -> Path:
        """Write everything needed to evaluate or continue this run to ``checkpoints/``."""
        path = checkpoint_path(self.ckpt_dir, self.cfg.exp_name, self.global_step)
        if self.last_checkpoint == path or not self.dist.is_main:
            return path
        save_checkpoint(path, self.state_dict())
        self.last_checkpoint = path
        prune_checkpoints(self.ckpt_dir, self.cfg.keep_last, newest=path)
        log.info("[ckpt] saved %s", path)
        self.event_manager.fire("trigger", self._ctx(), signal="checkpoint")
        self._hook("checkpoint", checkpoint=path)
        return path

    def request_stop(self, reason: str) -> None:
        """Ask the loop to checkpoint and stop at the end of the current iteration (signal-safe)."""
        self.stop_reason = reason

    # -- state ---------------------------------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        """Everything a bit-exact continuation needs (see docs/checkpoints.md)."""
        envs = {}  # the training envs mid-episode; eval rounds start from fresh resets
        base = base_env(self.env)
        if base is not None and hasattr(base, "env_state"):
            envs["train"] = base.env_state()
        return {
            "global_step": self.global_step,
            "policy": self.policy.state_dict(),
            "algorithm": self.algorithm.state_dict(),
            "windows": {
                "returns": list(self.ret_window),
                "lengths": list(self.len_window),
                "running_return": self._ep_ret.copy(),
                "running_length": self._ep_len.copy(),
            },
            "events": {
                "train": self.event_manager.state_dict(),
                "eval": self.eval_event_manager.state_dict(),
            },
            "envs": envs,
            "rng": rng_state(),
            "last_eval": dict(self.last_eval),
            "best_metric": self.best_metric,
            "hooks": self.hooks.state_dict(),
            "pending_observation": self._pending_observation(),
            "config": self.config_dict,
            "versions": self.versions,
        }

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        """Continue from a checkpoint: call before ``train``."""
        self.global_step = int(sd["global_step"])
        self.policy.load_state_dict(sd["policy"])
        self.algorithm.load_state_dict(sd["algorithm"])
        w = sd["windows"]
        self.ret_window.extend(w["returns"])
        self.len_window.extend(w["lengths"])
        if len(w.get("running_return", ())) == self._num_envs:
            self._ep_ret[:] = np.asarray(w["running_return"])
            self._ep_len[:] = np.asarray(w["running_length"])
        base = base_env(self.env)
        # The checkpoint holds rank 0's envs; other ranks continue with fresh episodes.
        if self.dist.is_main and "train" in sd.get("envs", {}) and hasattr(base, "load_env_state"):
            base.load_env_state(sd["envs"]["train"])
        self.event_manager.load_state_dict(sd["events"]["train"], self.env)
        self.eval_event_manager.load_state_dict(sd["events"]["eval"], self.eval_env)
        self.last_eval = dict(sd.get("last_eval", {}))
        self.best_metric = float(sd.get("best_metric", -float("inf")))
        self.hooks.load_state_dict(sd.get("hooks", {}))
        self._resume_rng = sd["rng"]
        if self.dist.is_main:  # with the env state it belongs to (rank 0's)
            self._resume_obs = sd.get("pending_observation")
        if not self.dist.is_main:  # rank 0's RNG would give every rank the same noise
            self._resume_rng = None
            torch.manual_seed(torch.initial_seed() + self.global_step)
        self.resumed_from = sd.get("path")
        log.info("[resume] continuing from %s at step %d", self.resumed_from, self.global_step)

    def close(self) -> None:
        """Shut the collector, envs and loggers down."""
        if self.collector is not None:
            self.collector.shutdown()
        for env in (self.env, self.eval_env):
            if env is not None and not env.is_closed:
                env.close()
        self.logger.close()

    # -- helpers -------------------------------------------------------------------------------------
    def _pending_observation(self) -> torch.Tensor | None:
        """The observation the policy acts on at the next step: the env's own one, or what a step
        event (observation noise) made of it, which the env state alone cannot give back."""
        if self.collector is None:
            return self._resume_obs
        return self.collector.next_observation()

    def _start_collector(self) -> None:
        if self.collector is None:
            self.collector = RolloutCollector(
                self.env,
                self.policy.sampling_policy(),
                frames_per_batch=self.cfg.frames_per_batch,
                total_frames=-1,
                trust_policy=True,
                track_traj_ids=False,
                auto_register_policy_transforms=False,  # the policy needs no env transforms
            )
            obs, self._resume_obs = self._resume_obs, None
            if obs is not None:  # resumed: act first on what the interrupted run would have
                self.collector.set_next_observation(obs)
            self._rollouts = iter(self.collector)

    def _hook(self, point: str, **kw: Any) -> None:
        """Fire the hooks of ``point`` with a read-only view of the run."""
        if not self.hooks:
            return
        state = HookState(
            point=point,
            global_step=self.global_step,
            iteration=self.algorithm.iteration,
            total_steps=self.total_steps,
            run_dir=self.run_dir,
            rank=self.dist.rank,
            world_size=self.dist.world_size,
            resumed=self.resumed_from is not None,
            losses=MappingProxyType(self._last_losses),
            metrics=kw.pop("metrics", MappingProxyType(self._last_metrics)),
            eval_metrics=MappingProxyType(self.last_eval),
            hyperparameters=MappingProxyType(self.algorithm.hyperparameters()),
            **kw,
        )
        self.hooks.fire(point, state)

    def _apply_hook_decisions(self) -> None:
        """Apply what hooks decided (rank 0's decisions, on every rank: all ranks call this at the
        same points of the loop): hyperparameters first, then a stop."""
        if not self.hooks:
            return
        decisions = self.hooks.apply(
            self.algorithm, all_gather_object if self.dist.enabled else None
        )
        self._hparams_set.update(decisions.set)
        if decisions.stop is not None and self.stopped_early is None:
            self.stopped_early = decisions.stop
            log.info("[hooks] stopping early at step %d: %s", self.global_step, decisions.stop)

    def _hook_train_end(self, status: str) -> None:
        """``train_end``; after a failure or a stop, a hook failing here is logged, not raised over
        how the run ended."""
        try:
            self._hook("train_end", status=status)
            self.logger.log(self.hooks.take_logged(), self.global_step)
        except Exception as exc:
            if status in ("finished", "stopped_early"):
                raise
            log.error("[hooks] train_end failed: %s", exc)

    def _save_best(self) -> None:
        path = save_checkpoint(self.ckpt_dir / "best.pt", self.state_dict())
        log.info("[ckpt] new best %s=%.3f -> %s", self.cfg.best_metric, self.best_metric, path)
        self.event_manager.fire("trigger", self._ctx(), signal="new_best")

    def _ctx(self, env: EnvBase | None = None, **kw: Any) -> EventContext:
        return EventContext(
            env=env if env is not None else self.env,
            global_step=self.global_step,
            run_dir=self.run_dir,
            **kw,
        )

    def _track_episodes(self, batch: TensorDictBase) -> None:
        """Update the return/length windows and per-term means from a [num_envs, T] rollout."""
        nxt = batch["next"]
        rewards = nxt["reward"].reshape(self._num_envs, -1).cpu().numpy()
        dones = nxt["done"].reshape(self._num_envs, -1).cpu().numpy()
        returns: list[float] = []
        lengths: list[int] = []
        for t in range(rewards.shape[1]):
            self._ep_ret += rewards[:, t]
            self._ep_len += 1
            finished = dones[:, t]
            if finished.any():
                returns += self._ep_ret[finished].tolist()
                lengths += self._ep_len[finished].tolist()
                self._ep_ret[finished] = 0.0
                self._ep_len[finished] = 0
        if self.dist.enabled:  # every rank's finished episodes, in rank order
            gathered = all_gather_object((returns, lengths))
            returns = [r for rets, _ in gathered for r in rets]
            lengths = [n for _, lens in gathered for n in lens]
        self.ret_window.extend(returns)
        self.len_window.extend(lengths)
        self._term_means = {}
        for group in ("rewards", "metrics"):
            if group in nxt.keys():
                for key, value in nxt[group].items():
                    self._term_means[f"{group}/{key}"] = float(value.float().mean())
