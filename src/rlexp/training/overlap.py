"""Collection on a spare core while the update runs: ``algorithm.overlap=true`` (PPO; off by
default; docs/performance.md "Overlap").

The training envs and the collector move into a child process (forked once the collector exists,
so it starts from exactly the envs, observation and policy the synchronous loop would). Iteration
k takes rollout k from the child, starts rollout k+1 there with the policy's weights as they are
now (before update k), and runs update k here while the child steps the envs. Each rollout after
the first is therefore collected by the policy one update behind the one that learns from it; the
loss's ratio is taken to that behaviour policy's stored log-probabilities (``action_log_prob``),
as asynchronous PPO implementations (APPO, Sample Factory) do, and the clip bounds the step from
it. GAE's values are the current critic's, computed when the update starts, as in the synchronous
loop.

Determinism and exact resume: the child's torch generator is seeded per rollout from a number this
process draws when it starts the rollout (before the update's own draws), the envs' generators are
their own, and a checkpoint first waits for the rollout in flight: it holds that rollout
(``pending_rollout``, collected and not yet learned from), the envs as that rollout left them (read
from the child) and the observation the child acts on next. A resumed run learns from the pending
rollout first, then continues as the uninterrupted run does, bit for bit (tests/test_overlap.py).

Where it applies: PPO on one process, a CPU policy, envs stepped in the training process
(``env.backend`` gymnasium or native: ``rules.OVERLAP_BACKENDS``), no training events (they act on
the envs, which the child owns). Anything else is refused before the run starts, naming the setting
to change (``config.validate``, ``build``).
"""

from __future__ import annotations

import contextlib
import logging
import os
import pickle
import signal
import time
import traceback
from multiprocessing import Pipe
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase

from rlexp.runtime.signals import die_with_parent
from rlexp.runtime.user_code import describe
from rlexp.training import loop

log = logging.getLogger(__name__)


def pack(batch: TensorDictBase) -> dict[str, Any]:
    """A rollout as a checkpoint holds it (plain tensors: ``torch.load(weights_only=True)``)."""
    return {"data": batch.to_dict(), "batch_size": list(batch.batch_size)}


def unpack(record: dict[str, Any]) -> TensorDictBase:
    return TensorDict(record["data"], batch_size=record["batch_size"])


def envs_state(collector: Any, env: Any) -> dict[str, Any]:
    """The checkpoint's ``envs`` and ``observation_layout``: the envs here, or (overlap) the
    child's, after the rollout in flight."""
    if isinstance(collector, OverlapCollector):
        return collector.envs_state()
    return loop.envs_state(env)


def pending_rollout(collector: Any, resumed: dict[str, Any] | None) -> dict[str, Any] | None:
    """The checkpoint's ``pending_rollout``: collected ahead and not yet learned from (overlap,
    after waiting for it), or the one a resumed run has not taken yet, or None."""
    if not isinstance(collector, OverlapCollector):
        return resumed
    collector.wait()
    return None if collector.pending is None else pack(collector.pending)


class CollectionError(RuntimeError):
    """The collection process failed or died. The first line of the message says what was raised
    there (its type and message); the child's traceback follows (``error.log``)."""


class OverlapCollector:
    """The collector run in a forked child: ``start`` the next rollout there, take it with
    ``next``; ``envs_state`` / ``next_observation`` read the child's envs (after the rollout in
    flight, which is then held here: ``pending``)."""

    def __init__(self, collector: Any, policy: torch.nn.Module, timeout_s: float = 900.0) -> None:
        self.policy = policy
        self.timeout_s = timeout_s  # trainer.stall_timeout_s: a child silent this long failed
        self.pending: TensorDictBase | None = None  # collected, not yet taken by the loop
        self.busy_s = 0.0  # the child's time on the last rollout (hidden behind the update)
        self._in_flight = False
        self._base = collector
        self._conn, child = Pipe()
        parent = os.getpid()
        pid = os.fork()
        if pid == 0:  # the child: serve until told to stop or this process goes away
            code = 0
            try:
                self._conn.close()
                _serve(child, collector, policy, parent)
            except BaseException:
                code = 1
            finally:
                os._exit(code)  # no atexit handlers of the parent's loggers (W&B, TensorBoard)
        child.close()
        self.pid: int | None = pid
        log.info("[overlap] collecting in process %d while the update runs here", pid)

    def start(self) -> None:
        """Collect the next rollout in the child with the policy's weights as they are now."""
        if self._in_flight or self.pending is not None:
            return
        seed = int(torch.randint(0, 2**62, ()).item())  # the child's draws, from this generator
        self._send(("collect", self.policy.state_dict(), seed))  # pickled (copied) right here
        self._in_flight = True

    def wait(self) -> None:
        """Wait for the rollout in flight, if any (it becomes ``pending``)."""
        if self._in_flight:
            self._in_flight = False
            self.pending, self.busy_s = self._receive()

    def __iter__(self) -> OverlapCollector:
        return self

    def __next__(self) -> TensorDictBase:
        self.wait()
        if self.pending is None:  # nothing collected ahead (the first rollout): collect it now
            self.start()
            self.wait()
        batch, self.pending = self.pending, None
        return batch

    def envs_state(self) -> dict[str, Any]:
        """The checkpoint's ``envs`` / ``observation_layout``: the child's envs, after the
        rollout in flight."""
        self.wait()
        self._send(("envs_state",))
        return self._receive()

    def carried_state(self) -> dict[str, Any] | None:
        """A recurrent policy's state in the child, after the rollout in flight (None: none)."""
        if not getattr(self._base, "carries_state", False):
            return None
        self.wait()
        self._send(("carry",))
        return self._receive()

    def next_observation(self) -> torch.Tensor | None:
        self.wait()
        self._send(("observation",))
        return self._receive()

    def shutdown(self) -> None:
        """Stop the child (told to; killed if it does not end within 10 s), then the collector
        this process kept (its envs were never stepped here)."""
        if self.pid is None:
            return
        pid, self.pid = self.pid, None
        with contextlib.suppress(OSError):
            self._conn.send_bytes(pickle.dumps(("close",)))
        deadline = time.monotonic() + 10.0
        while not _ended(pid):
            if time.monotonic() > deadline:
                with contextlib.suppress(ProcessLookupError, ChildProcessError):
                    os.kill(pid, signal.SIGKILL)
                    os.waitpid(pid, 0)
                break
            time.sleep(0.01)
        self._conn.close()
        self._base.shutdown()

    # -- the pipe ----------------------------------------------------------------------------------
    def _send(self, message: tuple) -> None:
        if self.pid is None:
            raise CollectionError("the collection process was shut down")
        try:
            self._conn.send_bytes(pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL))
        except OSError as exc:
            raise CollectionError(f"the collection process {self.pid} is gone ({exc})") from None

    def _receive(self) -> Any:
        try:
            if not self._conn.poll(self.timeout_s):
                raise CollectionError(
                    f"the collection process {self.pid} answered nothing for {self.timeout_s:.0f} s "
                    "(trainer.stall_timeout_s; algorithm.overlap=true)"
                )
            status, value = pickle.loads(self._conn.recv_bytes())
        except (EOFError, OSError) as exc:
            raise CollectionError(
                f"the collection process {self.pid} died (algorithm.overlap=true; {exc!r})"
            ) from None
        if status == "error":
            what, trace = value
            raise CollectionError(
                f"in the collection process (algorithm.overlap=true): {what}\n{trace}"
            )
        return value


def _serve(conn: Any, collector: Any, policy: torch.nn.Module, parent: int) -> None:
    """The child's loop: a rollout per ``collect`` (the weights to act with, the seed of its
    draws), the envs' state or next observation on request, until ``close`` or end of pipe."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the training process's to handle
    die_with_parent(parent)  # also where an env step hangs and the closed pipe is never read
    torch.set_num_threads(1)
    after_fork = getattr(loop.base_env(collector.env), "after_fork", None)
    if after_fork is not None:  # thread pools do not survive a fork (native tasks' physics)
        after_fork()
    rollouts = iter(collector)
    while True:
        try:
            message = pickle.loads(conn.recv_bytes())
        except (EOFError, OSError):
            return  # the training process is gone
        kind = message[0]
        if kind == "close":
            return
        try:
            if kind == "collect":
                t0 = time.perf_counter()
                policy.load_state_dict(message[1])
                torch.manual_seed(message[2])
                reply: Any = (next(rollouts), time.perf_counter() - t0)
            elif kind == "envs_state":
                reply = loop.envs_state(collector.env)
            elif kind == "carry":  # a recurrent policy's state between steps
                reply = collector.carried_state()
            else:  # "observation"
                reply = collector.next_observation()
            out = pickle.dumps(("ok", reply), protocol=pickle.HIGHEST_PROTOCOL)
        except BaseException as exc:  # SIGINT is ignored here: user code's SystemExit too
            out = pickle.dumps(("error", (describe(exc), traceback.format_exc())))
        try:
            conn.send_bytes(out)
        except OSError:
            return


def _ended(pid: int) -> bool:
    """Whether child ``pid`` has exited (reaping it), or was reaped already."""
    try:
        return os.waitpid(pid, os.WNOHANG)[0] != 0
    except ChildProcessError:
        return True
