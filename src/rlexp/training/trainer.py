"""The training loop: collect a rollout, update the algorithm (PPO, GRPO, SAC, TD3), log, evaluate,
checkpoint. Read it top to bottom."""

from __future__ import annotations

import copy
import functools
import logging
import time
from pathlib import Path
from types import MappingProxyType
from typing import Any

import torch
from tensordict import TensorDictBase
from torchrl.envs import EnvBase, TransformedEnv

from rlexp.algorithms.base import Algorithm, NonFiniteError
from rlexp.checkpoints.files import (
    checkpoint_path,
    prune_checkpoints,
    rng_state,
    save_checkpoint,
    set_rng_state,
)
from rlexp.common.observations import from_plain, to_plain, vector_of
from rlexp.config.schema import TrainerConfig
from rlexp.events import EventContext, EventManager
from rlexp.events.transform import EventTransform
from rlexp.hooks import HookManager, HookState
from rlexp.policies.actor_critic import Policy
from rlexp.run.metrics import MetricLogger
from rlexp.run.progress import Progress
from rlexp.runtime.devices import module_device
from rlexp.runtime.distributed import DistInfo, all_gather_object, all_reduce_sum
from rlexp.training import ckpt_state, loop, overlap
from rlexp.training.collector import RolloutCollector
from rlexp.training.episodes import EpisodeStats
from rlexp.training.eval_worker import EvalRound, EvalWorker, record
from rlexp.training.evaluation import eval_line, run_round
from rlexp.training.loop import check_rollout_finite, collection_threads, crossed, one_torch_thread

log = logging.getLogger(__name__)


class StopRequested(Exception):
    """Raised by ``train`` after it checkpointed at a safe point because ``request_stop`` was called."""


class Trainer:
    """Coordinates policy, algorithm and envs; owns the counters, windows and checkpoints."""

    def __init__(
        self,
        *,
        cfg: TrainerConfig,
        policy: Policy,
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
        eval_worker: EvalWorker | None = None,
        overlap: bool = False,
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
        self.last_eval: dict[str, float] = {}
        self.best_metric = -float("inf")
        self.last_checkpoint: Path | None = None
        self.resumed_from: str | None = None
        #: how the training envs came back on resume (docs/envs.md), for status.json
        self.env_resume: str | None = None
        self.episodes = EpisodeStats(int(env.batch_size.numel()) if len(env.batch_size) else 1)
        self._timing = {"collect": 0.0, "update": 0.0, "eval": 0.0}
        self.collector: RolloutCollector | None = None  # built when training starts, after a resume
        self._event_transform: EventTransform | None = None
        self._resume_rng: dict[str, Any] | None = None
        self._resume_obs = self._resume_carry = None  # on resume: obs to act on, recurrent state
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
        self.eval_worker = eval_worker  # eval_async: rounds run there beside training (None: here)
        self.overlap = overlap  # algorithm.overlap: rollouts collected in a child during updates
        self._resume_rollout: dict[str, Any] | None = None  # collected, not learned from, on resume
        self._resume_round: EvalRound | None = None  # in flight when the resumed run stopped
        # A step checkpoint holds its step's eval: written when the result is in (_eval_done), or
        # after waiting for it where hooks or events act on eval results or checkpoints.
        self._defer_saves = not event_manager.has("trigger") and not any(
            {"eval_end", "checkpoint"} & set(points) for _, points, _ in self.hooks.hooks
        )

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
        if self.eval_worker is not None:
            self.eval_worker.start()  # it imports and builds its env while the first rollouts run
        self.progress = Progress(total_timesteps, enabled=self.cfg.progress, start=self.global_step)
        status = "failed"
        try:
            self._hook("train_start")
            self._apply_hook_decisions()
            self._resume_eval_round()
            with self.progress:
                while self.global_step < total_timesteps and self.stopped_early is None:
                    self._iteration()
            self._collect_eval()  # the last round's result, before the final checkpoint
            if self.dist.enabled:
                loop.check_ranks_in_sync(self.policy, self.dist.world_size)
            self.save_checkpoint()
            status = "finished" if self.stopped_early is None else self.hooks.stop_status
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
        if self.overlap and self.global_step < self.total_steps and self.stopped_early is None:
            self.collector.start()  # the next rollout, collected while this one's update runs
        losses = self.update(batch)
        self.safe_point = True  # the update is complete: a checkpoint now is consistent
        self._last_losses = dict(losses)
        self._hook("update_end")
        self._collect_eval()  # last iteration's round, logged before this iteration's metrics
        self.log_train(losses)
        self.event_manager.fire("interval", self._ctx(batch=batch))
        if crossed(before, self.global_step, self.cfg.eval_every):
            self.evaluate()
        if crossed(before, self.global_step, self.cfg.save_every):
            self._save_step_checkpoint()
        self._apply_hook_decisions()  # a hook's stop: the loop ends, the run saves and finishes
        if self.dist.enabled and loop.stop_requested_elsewhere(self.policy, self.stop_reason):
            self.stop_reason = "stop requested on another rank"  # all ranks stop together
        if self.stop_reason is not None:  # a safe point: checkpoint, then let the caller decide
            self.save_checkpoint()
            raise StopRequested(self.stop_reason)

    def collect_rollout(self) -> TensorDictBase:
        """One batch of ``frames_per_batch`` env steps through the TorchRL collector."""
        t0 = time.perf_counter()
        with collection_threads(self.policy):  # one, but trainer.torch_threads for a CNN's step
            if self.algorithm.reset_each_rollout:  # GRPO: every env starts a new episode
                self.collector.reset()
                self.episodes.drop_running()
            if self._resume_rollout is not None:  # collected before the stop: learned from first
                batch, self._resume_rollout = overlap.unpack(self._resume_rollout), None
            else:
                batch = next(self._rollouts)
        self._timing["collect"] = time.perf_counter() - t0
        self.global_step += batch.numel() * self.dist.world_size  # every rank collected as much
        if self._event_transform is not None:
            self._event_transform.global_step = self.global_step
        if self.cfg.nan_guard:  # every rank checks, and all raise together
            device = next(self.policy.parameters()).device  # where the backend reduces
            check_rollout_finite(batch, self.dist, device, self.global_step)
        self.episodes.track(batch, all_gather_object if self.dist.enabled else None)
        return batch

    def update(self, batch: TensorDictBase) -> dict[str, float]:
        """The algorithm's update on the rollout, then fold its observations into the normaliser."""
        t0, batch = time.perf_counter(), batch.to(module_device(self.policy))  # (a no-op)
        try:
            losses = self.algorithm.update(batch)
        except NonFiniteError as exc:
            raise NonFiniteError(f"{exc} at step {self.global_step}") from None
        vector = vector_of(batch["observation"])  # images are never normalised (DESIGN47 §2)
        if vector is not None:
            self.policy.normalizer.update(vector, all_reduce_sum if self.dist.enabled else None)
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
        if self.overlap:  # the child's time on the rollout that was collected during this update
            metrics["perf/collect_busy_time"] = self.collector.busy_s
        self._timing["eval"] = 0.0
        metrics.update(self.episodes.means())
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

    # -- evaluation ----------------------------------------------------------------------------------
    def evaluate(self) -> None:
        """An eval round of the policy as it is now: run here, or (``eval_async``) handed to the eval
        worker with a snapshot of the whole state; ``_collect_eval`` takes its result in."""
        if self.eval_worker is None:
            self.eval_once()
            return
        self._collect_eval()  # at most one round in flight
        t_start = time.perf_counter()
        self.eval_worker.submit(EvalRound(self.global_step, self.state_dict(snapshot=True)))
        self._timing["eval"] += time.perf_counter() - t_start  # the round's cost on this process

    def eval_once(self) -> dict[str, float]:
        """Evaluate the current policy here and now: the sync rounds, a run's final round."""
        if self.eval_env is None or self.cfg.eval_episodes <= 0 or not self.dist.is_main:
            return {}
        metrics = self._run_round(self.policy)
        self._eval_done(self.global_step, metrics)
        return metrics

    def _run_round(self, policy: Policy) -> dict[str, float]:
        t_start = time.perf_counter()
        ctx = functools.partial(self._ctx, self.eval_env)
        with one_torch_thread():
            metrics = run_round(self.eval_env, policy, self.cfg.eval_episodes, self.eval_seed,
                                self.eval_event_manager, ctx)  # fmt: skip
        self._timing["eval"] += time.perf_counter() - t_start
        return metrics

    def _collect_eval(self) -> None:
        """Take the result of the round in flight in (waiting for it) as its snapshot step's round."""
        if getattr(self.eval_worker, "in_flight", None) is None:
            return
        t_start = time.perf_counter()
        done, metrics = self.eval_worker.result()
        self._timing["eval"] += time.perf_counter() - t_start  # waiting is on the critical path
        self._eval_done(done.step, metrics, done)

    def _eval_done(
        self, step: int, metrics: dict[str, float], done: EvalRound | None = None
    ) -> None:
        """What follows a round of the policy at ``step``: the metrics logged at that step, the
        console line, eval_end events and hooks, best.pt, and the step's checkpoint if it waited
        (``done``: a snapshot's round, whose state these files hold; None: the state now)."""
        self.last_eval = metrics
        self.logger.log(metrics, step)
        if self.console:
            log.info("%s", eval_line(step, metrics, self.cfg.eval_episodes))
        self.event_manager.fire("trigger", self._ctx(metrics=metrics, step=step), signal="eval_end")
        self._hook("eval_end", global_step=step)
        self.logger.log(self.hooks.take_logged(), step)
        value = metrics.get(self.cfg.best_metric)
        if value is not None and value > self.best_metric:
            self.best_metric = value
            self._save_best(self.state_dict() if done is None else done.state | self._eval_state())
        if done is not None and done.save:
            path = checkpoint_path(self.ckpt_dir, self.cfg.exp_name, done.step)
            self._write_checkpoint(path, done.state | self._eval_state())

    def _resume_eval_round(self) -> None:
        """A round that was in flight when the resumed run stopped is evaluated first (by the
        worker, or here on a copy of the policy with the snapshot's weights)."""
        done, self._resume_round = self._resume_round, None
        if done is not None and self.eval_worker is not None:
            self.eval_worker.submit(done)
        elif done is not None and self.eval_env is not None and self.dist.is_main:
            policy = copy.deepcopy(self.policy)
            policy.load_state_dict(done.state["policy"])
            self._eval_done(done.step, self._run_round(policy), done)

    def _eval_state(self) -> dict[str, Any]:
        return {"last_eval": dict(self.last_eval), "best_metric": self.best_metric}

    # -- checkpoints ---------------------------------------------------------------------------------
    def save_checkpoint(self) -> Path:
        """Write everything needed to evaluate or continue this run to ``checkpoints/`` (a round in
        flight is recorded, and a resume evaluates it first)."""
        path = checkpoint_path(self.ckpt_dir, self.cfg.exp_name, self.global_step)
        if self.last_checkpoint == path or not self.dist.is_main:
            return path
        return self._write_checkpoint(path, self.state_dict())

    def _save_step_checkpoint(self) -> None:
        """A due checkpoint holds the eval of its step, as in sync mode: with that round in flight it
        is written when the result comes in (or now, after waiting, see ``_defer_saves``)."""
        in_flight = getattr(self.eval_worker, "in_flight", None)
        if in_flight is not None and in_flight.step == self.global_step and self._defer_saves:
            in_flight.save = True
            return
        self._collect_eval()
        self.save_checkpoint()

    def _write_checkpoint(self, path: Path, state: dict[str, Any]) -> Path:
        save_checkpoint(path, state := ckpt_state.settled(self.algorithm, state))
        self.last_checkpoint = path
        prune_checkpoints(self.ckpt_dir, self.cfg.keep_last, newest=path)
        ckpt_state.written(self.algorithm, self.ckpt_dir, path, state)  # SAC: stale replay chunks
        log.info("[ckpt] saved %s", path)
        self.event_manager.fire("trigger", self._ctx(), signal="checkpoint")
        self._hook("checkpoint", checkpoint=path)
        return path

    def request_stop(self, reason: str) -> None:
        """Ask the loop to checkpoint and stop at the end of the current iteration (signal-safe)."""
        self.stop_reason = reason

    # -- state ---------------------------------------------------------------------------------------
    def state_dict(self, snapshot: bool = False) -> dict[str, Any]:
        """Everything a bit-exact continuation needs (docs/checkpoints.md); ``snapshot``: an eval's."""
        return {
            "global_step": self.global_step,
            "policy": self.policy.state_dict(),
            "algorithm": ckpt_state.algorithm_state(self.algorithm, snapshot),
            "windows": self.episodes.state_dict(),
            "events": {
                "train": self.event_manager.state_dict(),
                "eval": self.eval_event_manager.state_dict(),
            },
            **overlap.envs_state(self.collector, self.env),  # "envs", "observation_layout"
            "pending_rollout": overlap.pending_rollout(self.collector, self._resume_rollout),
            "rng": rng_state(),
            "last_eval": dict(self.last_eval),
            "best_metric": self.best_metric,
            "hooks": self.hooks.state_dict(),
            "pending_observation": to_plain(self._pending_observation()),  # (a dict: images)
            "recurrent_carry": loop.carried_state(self.collector, self._resume_carry),
            "eval_in_flight": record(
                getattr(self.eval_worker, "in_flight", None) or self._resume_round
            ),  # resume: first
            "config": self.config_dict,
            "versions": self.versions,
        }

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        """Continue from a checkpoint: call before ``train``."""
        self.env_resume = loop.restore_envs(self.env, sd, self.dist.is_main)  # docs/envs.md
        self.global_step = int(sd["global_step"])
        self.policy.load_state_dict(sd["policy"])
        self.algorithm.load_state_dict(sd["algorithm"])
        self.episodes.load_state_dict(sd["windows"])
        self.event_manager.load_state_dict(sd["events"]["train"], self.env)
        self.eval_event_manager.load_state_dict(sd["events"]["eval"], self.eval_env)
        self.last_eval = dict(sd.get("last_eval", {}))
        self.best_metric = float(sd.get("best_metric", -float("inf")))
        self.hooks.load_state_dict(sd.get("hooks", {}))
        if sd.get("eval_in_flight") is not None:
            self._resume_round = EvalRound.from_record(sd["eval_in_flight"])
        self._resume_rng = sd["rng"]
        self._resume_rollout = sd.get("pending_rollout")
        if self.dist.is_main:  # with the env state it belongs to (rank 0's)
            self._resume_obs = from_plain(sd.get("pending_observation"))
            self._resume_carry = sd.get("recurrent_carry")
        if self.env_resume is not None and self.env_resume.startswith("restarted"):
            self._resume_obs = self._resume_rollout = self._resume_carry = None  # new episodes
            self.episodes.drop_running()
            loop.restart_returns(self.algorithm)
        if not self.dist.is_main:  # rank 0's RNG would give every rank the same noise
            self._resume_rng = None
            torch.manual_seed(torch.initial_seed() + self.global_step)
        self.resumed_from = sd.get("path")
        log.info("[resume] continuing from %s at step %d", self.resumed_from, self.global_step)

    def close(self) -> None:
        """Shut the eval worker, collector, envs and loggers down."""
        if self.eval_worker is not None:
            self.eval_worker.close()
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
        return self._resume_obs if self.collector is None else self.collector.next_observation()

    def _start_collector(self) -> None:
        if self.collector is None:
            self.collector = RolloutCollector(
                self.env,
                loop.collection_policy(self.policy, self.algorithm, self.overlap),
                frames_per_batch=self.cfg.frames_per_batch,
                total_frames=-1,
                trust_policy=True,
                track_traj_ids=False,
                auto_register_policy_transforms=False,  # the policy needs no env transforms
            )
            # resumed: act first on what the interrupted run would have, from its recurrent state
            self.collector.resume_from(self._resume_obs, self._resume_carry)
            self._resume_obs = self._resume_carry = None
            if self.overlap:  # envs and collector move to a child (rlexp/training/overlap.py)
                timeout = self.cfg.stall_timeout_s
                self.collector = overlap.OverlapCollector(self.collector, self.policy, timeout)
            self._rollouts = iter(self.collector)

    def _hook(self, point: str, **kw: Any) -> None:
        """Fire the hooks of ``point`` with a read-only view of the run."""
        if not self.hooks:
            return
        state = HookState(
            point=point,
            global_step=kw.pop("global_step", self.global_step),  # eval_end: the evaluated step
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

    def _save_best(self, state: dict[str, Any]) -> None:
        path = save_checkpoint(self.ckpt_dir / "best.pt", ckpt_state.settled(self.algorithm, state))
        log.info("[ckpt] new best %s=%.3f -> %s", self.cfg.best_metric, self.best_metric, path)
        self.event_manager.fire("trigger", self._ctx(), signal="new_best")

    def _ctx(self, env: EnvBase | None = None, step: int | None = None, **kw: Any) -> EventContext:
        return EventContext(
            env=env if env is not None else self.env,
            global_step=self.global_step if step is None else step,
            run_dir=self.run_dir,
            **kw,
        )
