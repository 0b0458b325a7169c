"""Evaluation off the critical path (``trainer.eval_async``): a worker process evaluates snapshots of
the policy while the training process goes on, and the rule that decides ``auto``.

The worker is started once per run (``start``, at train start) with the ``spawn`` context: forking a
process that already runs torch's and MuJoCo's threads is unsafe. It builds its own eval env exactly
as the training process builds one (``env.num_eval_envs`` copies, the eval seed, reseeded every
round) and a policy of the run's shape, then for each snapshot it receives (the policy's state dict,
observation normaliser included) runs ``rlexp.training.evaluation.run_round``, as in-process rounds do:
the same deterministic episodes, the same numbers. It ignores SIGINT and SIGHUP (a terminal's
Ctrl-C reaches the whole process group; the training process decides), dies with the training
process (``PR_SET_PDEATHSIG`` on Linux, and a closed pipe ends it anywhere) and leaves through
``os._exit`` without the interpreter's teardown.

The Trainer keeps at most one :class:`EvalRound` in flight and takes its result in after the next
update (docs/performance.md, "Evaluation off the critical path").
"""

from __future__ import annotations

import copy
import dataclasses
import io
import logging
import os
import signal
import time
import traceback
from dataclasses import dataclass, field
from typing import Any

import torch

from rlexp.config.rules import torch_threads_for
from rlexp.config.schema import BasePolicyConfig, EnvConfig, RootConfig
from rlexp.runtime.signals import blocked, die_with_parent

log = logging.getLogger(__name__)

#: ``auto`` turns the worker on for runs with at least this many eval rounds: its start (~2-4 s of
#: the spare core; the first round waits for it if it comes sooner) is then paid back.
AUTO_MIN_ROUNDS = 10
#: The worker's start-up (spawn, imports, building its env) waits at least this long, whatever
#: ``trainer.stall_timeout_s``: tens of seconds on a machine busy with other runs.
STARTUP_TIMEOUT_MIN_S = 120.0
#: Group-wide terminal signals the worker must not act on (the training process stops it).
_TERMINAL_SIGNALS = {signal.SIGINT, signal.SIGHUP}


@dataclass
class EvalSetup:
    """What the worker builds its eval env and policy from (typed configs: picklable, no DictConfig)."""

    env: EnvConfig
    policy: BasePolicyConfig
    seed: int  # the eval seed (the run's seed + rlexp.training.build.EVAL_SEED_OFFSET)
    episodes: int  # trainer.eval_episodes
    device: str = "cpu"  # the policy's device in the training process
    precision: str = "fp32"  # trainer.precision: the policy's forward as in the training process

    def build(self) -> tuple[Any, Any]:
        """The eval env and a policy of the run's shape (its weights come with each snapshot)."""
        from rlexp.envs.factory import make_env
        from rlexp.policies.actor_critic import policy_for_env

        cfg = self.env
        if cfg.backend == "gymnasium_async":
            # This worker is a daemonic process, which may not start processes; the in-process
            # backend gives the same episodes, value for value (docs/envs.md).
            cfg = dataclasses.replace(cfg, backend="gymnasium")
        from rlexp.runtime.precision import set_precision

        env = make_env(cfg, cfg.num_eval_envs, self.seed)
        policy = policy_for_env(self.policy, cfg, env).to(self.device)
        set_precision(policy, self.precision, self.device)
        return env, policy


@dataclass
class EvalRound:
    """A snapshot being evaluated: its step, the Trainer's whole state at that step (what best.pt,
    and the step's checkpoint if ``save``, hold once the result is in), and whether the checkpoint of
    that step waits for this round."""

    step: int
    state: dict[str, Any]
    save: bool = False

    @classmethod
    def from_record(cls, rec: dict[str, Any]) -> EvalRound:
        return cls(int(rec["step"]), rec["state"], bool(rec.get("save", False)))


def record(round_: EvalRound | None) -> dict[str, Any] | None:
    """A round in flight as a checkpoint holds it (a resume evaluates it first); None: none."""
    return (
        None
        if round_ is None
        else {"step": round_.step, "state": round_.state, "save": round_.save}
    )


class EvalWorkerTimeout(RuntimeError):
    """The eval worker did not answer within ``trainer.stall_timeout_s``."""


@dataclass
class EvalWorker:
    """The training process's handle on the worker: ``start``, ``submit`` a round, ``result``."""

    setup: EvalSetup
    timeout_s: float | None = None  # trainer.stall_timeout_s: the longest wait for an answer
    in_flight: EvalRound | None = None
    _proc: Any = field(default=None, repr=False)
    _conn: Any = field(default=None, repr=False)
    _ready: bool = False

    def start(self) -> None:
        """Start the worker process (once); it imports and builds while training goes on."""
        if self._proc is not None:
            return
        ctx = torch.multiprocessing.get_context("spawn")
        self._conn, child = ctx.Pipe()
        self._proc = ctx.Process(
            target=_serve, args=(child, self.setup, os.getpid()), name="rlexp-eval", daemon=True
        )
        with blocked(_TERMINAL_SIGNALS):  # a Ctrl-C during its start-up reaches this process only
            self._proc.start()
        child.close()
        log.info("[eval] eval worker started (pid %d): evaluation runs beside training", self.pid)

    @property
    def pid(self) -> int | None:
        return None if self._proc is None else self._proc.pid

    def submit(self, round_: EvalRound) -> None:
        """Hand a snapshot to the worker (at most one round in flight). The state is copied:
        training goes on and changes the live tensors."""
        if self.in_flight is not None:
            raise RuntimeError(f"eval round of step {self.in_flight.step} is still in flight")
        self.start()
        round_.state = copy.deepcopy(round_.state)
        buffer = io.BytesIO()
        torch.save(round_.state["policy"], buffer)
        if not self._ready:  # the first round may come before the worker has built its env
            self._receive("ready", "start-up")
            self._ready = True
        self._conn.send((round_.step, buffer.getvalue()))
        self.in_flight = round_

    def result(self) -> tuple[EvalRound, dict[str, float]]:
        """The round in flight and its metrics (waits for them)."""
        round_ = self.in_flight
        if round_ is None:
            raise RuntimeError("no eval round in flight")
        step, metrics = self._receive("result", f"eval round of step {round_.step}")
        if step != round_.step:
            raise RuntimeError(f"the eval worker answered for step {step}, not {round_.step}")
        self.in_flight = None
        return round_, metrics

    def close(self) -> None:
        """Stop the worker: asked to leave when idle, killed when busy (a round in flight is in the
        stop checkpoint) or still starting; returns within ~0.2 s."""
        proc, self._proc = self._proc, None
        if proc is None:
            return
        if proc.is_alive() and self._ready and self.in_flight is None:
            try:
                self._conn.send(None)
                proc.join(0.2)
            except OSError:
                pass
        if proc.is_alive():
            proc.kill()
            proc.join(1.0)
        self._conn.close()

    def _receive(self, kind: str, what: str) -> Any:
        """The worker's next message of ``kind`` (for ``what``: its start-up, a round); its error,
        its death or its silence past ``timeout_s`` (stopped, or stuck in the env) as a
        RuntimeError."""
        start = time.monotonic()
        limit = self.timeout_s
        if limit is not None and kind == "ready":  # spawn + imports + env: slow on a busy machine
            limit = max(limit, STARTUP_TIMEOUT_MIN_S)
        while not self._conn.poll(0.1):
            if not self._proc.is_alive():
                raise RuntimeError(
                    f"the eval worker (pid {self._proc.pid}) died with exit code "
                    f"{self._proc.exitcode} (trainer.eval_async=false evaluates in this process)"
                )
            if limit is not None and time.monotonic() - start > limit:
                bound = f"trainer.stall_timeout_s={self.timeout_s:g} s"
                if limit != self.timeout_s:
                    bound = f"{limit:g} s ({bound}, at least {STARTUP_TIMEOUT_MIN_S:g} s to start)"
                raise EvalWorkerTimeout(
                    f"the eval worker (pid {self._proc.pid}) did not answer for its {what} within "
                    f"{bound} (stopped, or stuck in the eval env); trainer.eval_async=false "
                    "evaluates in this process"
                )
        try:
            got, payload = self._conn.recv()
        except EOFError:
            raise RuntimeError(f"the eval worker (pid {self._proc.pid}) closed its pipe") from None
        if got == "error":
            raise RuntimeError(
                f"the eval worker failed: {payload} (trainer.eval_async=false evaluates in this "
                "process)"
            )
        if got != kind:
            raise RuntimeError(f"the eval worker sent {got!r}, expected {kind!r}")
        return payload


def _serve(conn: Any, setup: EvalSetup, parent: int) -> None:
    """The worker: build once, then evaluate each (step, policy state) until told to stop."""
    die_with_parent(parent)  # even SIGKILLed mid-round; elsewhere the closed pipe ends it
    for sig in _TERMINAL_SIGNALS:
        signal.signal(sig, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, _TERMINAL_SIGNALS)
    from rlexp.common import speedups as _speedups
    from rlexp.training.evaluation import run_round

    torch.set_num_threads(1)  # as in-process rounds (one_torch_thread): the same kernels
    try:
        env, policy = setup.build()
        _speedups.training_gc()  # rounds walk only what they create (rlexp.common.speedups)
        conn.send(("ready", None))
        while (msg := _recv(conn)) is not None:
            step, payload = msg
            state = torch.load(io.BytesIO(payload), map_location="cpu", weights_only=True)
            policy.load_state_dict(state)
            metrics = run_round(env, policy, setup.episodes, setup.seed)  # as in-process rounds
            conn.send(("result", (step, metrics)))
    except Exception as exc:
        lines = traceback.format_exception_only(type(exc), exc)
        try:
            conn.send(("error", "".join(lines).strip()))
        except OSError:
            pass
        os._exit(1)
    os._exit(0)


def _recv(conn: Any) -> Any:
    try:
        return conn.recv()
    except EOFError:  # the training process is gone
        return None


# -- trainer.eval_async=auto ---------------------------------------------------------------------
def eval_consumers(config: RootConfig) -> list[str]:
    """The config's hooks and events that act on eval results, new bests or checkpoints (hooks at
    ``eval_end`` / ``checkpoint``, events of mode ``trigger``): an async round reaches them one
    iteration later than a sync one."""
    from rlexp.hooks.base import resolve_hook_func

    names = []
    for name, hook in config.hooks.items():
        points = getattr(resolve_hook_func(hook.func, f"hooks.{name}"), "POINTS", ("eval_end",))
        if {"eval_end", "checkpoint"} & set(points):
            names.append(f"hooks.{name}")
    names += [f"events.train.{n}" for n, ev in config.events.train.items() if ev.mode == "trigger"]
    return names


def launcher_jobs(n_jobs: Any, cpus: int) -> int:
    """Jobs a sweep runs side by side on this machine: the joblib launcher's ``n_jobs`` (-1: one
    per CPU, joblib's meaning); 1 for a single run and for launchers that run one job per
    allocation (SLURM) or one after another (Hydra's basic launcher)."""
    if not isinstance(n_jobs, int) or isinstance(n_jobs, bool):
        return 1
    return max(1, n_jobs if n_jobs > 0 else cpus + 1 + n_jobs)


def decide_eval_async(
    config: RootConfig, total: int, cpus: int, jobs: int = 1, ranks: int = 1
) -> tuple[bool, str]:
    """``trainer.eval_async`` as a bool for a run of ``total`` env steps, and why (logged once).

    ``auto`` is on when the worker measurably wins and changes nothing: evaluation runs in this
    process (rank 0), no eval events (they run in this process's eval env), no hooks or events
    acting on eval results, at least AUTO_MIN_ROUNDS rounds, and a spare core: ``cpus`` (this
    process's affinity) >= ``jobs`` x (``ranks`` x the threads a training process keeps busy + 1).
    """
    t, e = config.trainer, config.env
    choice = str(t.eval_async).strip().lower()
    evaluates = t.eval_every > 0 and t.eval_episodes > 0 and e.num_eval_envs > 0
    if not evaluates:
        return (
            False,
            "no evaluation (trainer.eval_every, trainer.eval_episodes or env.num_eval_envs is 0)",
        )
    if choice in ("true", "false"):
        return choice == "true", f"trainer.eval_async={choice}"
    if config.events.eval:
        return (
            False,
            f"events.eval ({', '.join(config.events.eval)}) run in this process's eval env",
        )
    if e.backend in ("vecenv", "torchrl"):  # a simulator (and its GPU memory) in a second process
        return False, f"env.backend={e.backend}: the worker would build a second simulator"
    consumers = eval_consumers(config)
    if consumers:
        return (
            False,
            f"{', '.join(consumers)} act on eval results (set true to accept a 1-iteration lag)",
        )
    rounds = total // t.eval_every
    if rounds < AUTO_MIN_ROUNDS:
        return (
            False,
            f"{rounds} eval rounds in the budget (< {AUTO_MIN_ROUNDS}: the worker's start-up would not pay off)",
        )
    threads = torch_threads_for(t.torch_threads, cpus, jobs * ranks)
    if e.backend == "native":  # the physics thread pool steps the training envs
        from rlexp.envs.native.env import default_num_threads

        threads = max(threads, default_num_threads(e.num_envs))
    need = jobs * (ranks * threads + 1)
    detail = f"{cpus} CPUs, {jobs} job(s) x ({ranks} rank(s) x {threads} thread(s) + 1 eval worker)"
    if cpus < need:
        return False, f"no spare core: {detail} = {need}"
    return True, f"a spare core: {detail} = {need} <= {cpus}"
