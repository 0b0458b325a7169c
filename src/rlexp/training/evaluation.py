"""Deterministic evaluation episodes: what the Trainer's ``eval_once`` and ``rlexp eval`` both run.

Two loops give the same numbers (tested). The lean one, for rlexp's envs with rlexp's sampling policy
(``rlexp.training.collector.supports_fast_rollout``; on a GPU env it reads rewards back in chunks of steps),
is the collector's: the deterministic sampler on
plain tensors, the env's own ``step_action`` / ``autoreset_observation``. TorchRL's
``step_and_maybe_reset`` loop serves everything else (transformed envs, other policies) and callers
that need each step's tensordict (``on_step``: the eval events of mode step / interval, e.g. the eval
video). Episodes are spread over the env's copies; more copies share the per-step Python and network
cost (docs/performance.md, "Evaluation"). ``eval/success_rate`` is reported for tasks that define
success only (a native task with a success rule, or any env whose steps carry ``metrics/success``
without a task spec saying otherwise); Gymnasium's MuJoCo tasks define none.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from tensordict import TensorDictBase
from torchrl.envs import EnvBase

from rlexp.training.collector import devices, supports_fast_rollout
from rlexp.training.loop import base_env

log = logging.getLogger(__name__)


#: The longest eval episode: one that has not ended after this many steps (an env without a time
#: limit whose episodes never end) is cut there and counted as a truncated episode, with one
#: warning; an eval round, and ``rlexp eval``, always ends. Far above any time limit in use
#: (MuJoCo 1,000, Atari 27,000 agent steps).
MAX_EPISODE_STEPS = 100_000


class RecurrentActor:
    """A recurrent policy's deterministic actions for a batch of env copies, its state carried.

    ``policy`` is a recurrent ``Policy`` (``policy.act``, ``initial_state``, ``reset_state``). The
    state is made at the first step (the batch of the observation: every copy at an episode's
    start); ``episodes_ended(done)`` resets the copies whose episode ended, so their next step reads
    the initial state. Callable on a TensorDict (TorchRL's loop) or, through ``act``, on the
    observation alone (the lean loop)."""

    def __init__(self, policy: Any, deterministic: bool = True) -> None:
        self.policy = policy
        self.deterministic = deterministic
        self.state: dict[str, torch.Tensor] | None = None
        # the parameters do not change during a round: the sampler (policy.act's) built once
        self._sample = policy.sampling_policy(deterministic).sampler()

    def act(self, obs: Any) -> torch.Tensor:
        """The action for ``obs`` (a Tensor or a TensorDict: a batch of copies); the state moves on
        (the actor's entries; the critic's, which acting does not need, stay as they were)."""
        if self.state is None:
            batch = int(obs.batch_size.numel() if isinstance(obs, TensorDictBase) else obs.shape[0])
            self.state = self.policy.initial_state(batch, device=obs.device)
        out, self.state = self._sample(obs, self.state, critic=False)
        return out[-2]  # (..., action, log-prob), as policy.act

    def episodes_ended(self, done: torch.Tensor) -> None:
        """Reset the state of the copies whose episode ended (``done``: bool [num_copies])."""
        if self.state is not None:
            device = next(iter(self.state.values())).device  # the env's may be another
            self.state = self.policy.reset_state(self.state, done.reshape(-1).bool().to(device))

    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        td.set("action", self.act(td.get("observation")))
        return td


def acting_policy(policy: Any) -> Any:
    """What an eval round acts with: the fast deterministic sampler, or for a recurrent policy a
    :class:`RecurrentActor` carrying its state."""
    if getattr(policy, "recurrent", False):
        return RecurrentActor(policy)
    return policy.sampling_policy(deterministic=True)


class EpisodeTally:
    """Per-copy running returns, lengths and success, kept for each copy's first ``quota`` episodes
    (the copies' quotas sum to ``episodes`` and differ by at most one), so copies whose episodes
    end early do not contribute more of them. An episode still running after ``max_steps`` steps
    is cut there (``cut`` counts them; the copy's next episode continues where it was)."""

    def __init__(self, num_copies: int, episodes: int, max_steps: int = MAX_EPISODE_STEPS) -> None:
        n = num_copies
        self.max_steps = max_steps
        self.cut = 0
        self.quota = np.full(n, episodes // n)
        self.quota[: episodes % n] += 1
        self.done_count = np.zeros(n, dtype=np.int64)
        self.ep_ret = np.zeros(n)
        self.ep_len = np.zeros(n, dtype=np.int64)
        self.ep_success = np.zeros(n)
        self.returns: list[float] = []
        self.lengths: list[int] = []
        self.successes: list[float] = []
        self.tracks_success = False  # the env reported success (the task defines it)

    @property
    def finished(self) -> bool:
        """Every copy has completed its quota."""
        return bool((self.done_count >= self.quota).all())

    def add(self, reward: np.ndarray, done: np.ndarray, success: np.ndarray | None) -> None:
        """One step of every copy: ``reward``, ``done`` (and ``success`` where the env reports it),
        each of shape [num_copies]."""
        self.ep_ret += reward
        self.ep_len += 1
        if success is not None:
            self.tracks_success = True
            np.maximum(self.ep_success, success, out=self.ep_success)
        if self.ep_len.max() >= self.max_steps:  # an episode that never ends: cut it here
            long = (self.ep_len >= self.max_steps) & ~done.astype(bool)
            self.cut += int((long & (self.done_count < self.quota)).sum())
            done = done.astype(bool) | long
        if not done.any():
            return
        for i in np.flatnonzero(done):
            if self.done_count[i] < self.quota[i]:
                self.returns.append(float(self.ep_ret[i]))
                self.lengths.append(int(self.ep_len[i]))
                self.successes.append(float(self.ep_success[i]))
                self.done_count[i] += 1
            self.ep_ret[i], self.ep_len[i], self.ep_success[i] = 0.0, 0, 0.0

    def metrics(self) -> dict[str, float]:
        """Mean/std return, mean length, the success rate (tasks that define success only) and the
        number of episodes counted."""
        out = {
            "eval/episode_return": float(np.mean(self.returns)),
            "eval/episode_return_std": float(np.std(self.returns)),
            "eval/episode_length": float(np.mean(self.lengths)),
            "eval/success_rate": float(np.mean(self.successes)),
            "eval/episodes": float(len(self.returns)),
        }
        if not self.tracks_success:
            del out["eval/success_rate"]
        return out


def defines_success(env: EnvBase) -> bool:
    """Whether the ``metrics/success`` an env reports means something: a native task without a
    success rule reports zeros (its spec says ``success=None``)."""
    spec = getattr(base_env(env), "task_spec", None)  # under TorchRL transforms
    return spec is None or getattr(spec, "success", None) is not None


def _success_key(env: EnvBase, nxt: TensorDictBase) -> tuple[str, str] | None:
    metrics = nxt.get("metrics", None)
    if metrics is None or "success" not in metrics.keys() or not defines_success(env):
        return None
    return ("metrics", "success")


def eval_line(step: int, metrics: dict[str, float], episodes: int) -> str:
    """The console's summary of a round (success only where the task defines it)."""
    success = metrics.get("eval/success_rate")
    return (
        f"[eval] step={step} return={metrics['eval/episode_return']:.2f} +- "
        f"{metrics['eval/episode_return_std']:.2f} length={metrics['eval/episode_length']:.1f}"
        + (f" success={success:.2f}" if success is not None else "")
        + f" ({episodes} episodes)"
    )


def event_callbacks(
    env: EnvBase, events: Any, ctx: Callable[..., Any]
) -> tuple[Callable[[TensorDictBase], None] | None, Callable[[TensorDictBase], TensorDictBase]]:
    """``run_episodes``' ``on_step`` and ``on_reset`` for an eval round with the eval events
    (an ``EventManager``; ``ctx(**kw)``: its EventContext). ``on_step`` is None without step or
    interval events: the round then takes the lean loop."""
    n = int(env.batch_size.numel())

    def on_reset(td: TensorDictBase) -> TensorDictBase:
        events.fire("reset", ctx(env_ids=np.arange(n)))
        base = base_env(env)  # reset events may have moved objects: observe again
        if events.has("reset") and hasattr(base, "current_tensordict"):
            td.set("observation", base.current_tensordict().get("observation"))
        return td

    def on_step(td: TensorDictBase) -> None:
        events.fire("step", ctx(tensordict=td, phase="action"))
        events.fire("interval", ctx(tensordict=td))

    # Step / interval events (the eval video, noise) see each step's tensordict: TorchRL's loop.
    return (on_step if events.has("step", "interval") else None), on_reset


@torch.no_grad()
def run_round(
    env: EnvBase,
    policy: Any,
    episodes: int,
    seed: int,
    events: Any = None,
    ctx: Callable[..., Any] | None = None,
) -> dict[str, float]:
    """An eval round of ``policy`` (a ``Policy``), in the training process or in the eval
    worker: the eval env reseeded, its deterministic episodes; with the eval events (``events``, an
    ``EventManager``; ``ctx(**kw)`` its EventContext), which are finalised and told ``eval_end``.
    The metrics without the count."""
    on_step, on_reset = None, None
    if events is not None:
        on_step, on_reset = event_callbacks(env, events, ctx)
    # Fresh episodes from the same seed every round: rounds compare like with like, and a resumed
    # run evaluates exactly as an uninterrupted one (no eval episode spans two rounds).
    env.set_seed(seed)
    metrics = run_episodes(env, acting_policy(policy), episodes, on_step, on_reset)
    metrics.pop("eval/episodes")
    if events is not None:
        events.finalize(ctx())
        events.fire("trigger", ctx(metrics=metrics), signal="eval_end")
    return metrics


@torch.no_grad()
def run_episodes(
    env: EnvBase,
    policy: Callable[[TensorDictBase], TensorDictBase],
    episodes: int,
    on_step: Callable[[TensorDictBase], None] | None = None,
    on_reset: Callable[[TensorDictBase], TensorDictBase] | None = None,
    lean: bool | None = None,
    max_steps: int = MAX_EPISODE_STEPS,
) -> dict[str, float]:
    """Run ``episodes`` episodes spread evenly over the env's copies (each copy's first ones, so
    short episodes are not favoured); returns mean/std return, mean length and success rate.

    ``on_reset`` sees (and may replace) the first tensordict after the env's reset; ``on_step``
    sees each step's tensordict after the policy acted, before the env steps (it needs TorchRL's
    loop). ``lean``: None picks the lean loop where it applies; False forces TorchRL's loop (the
    reference the lean one is tested against); True insists on the lean loop. ``max_steps``: an
    episode not ended after that many steps is cut there, with one warning (``EpisodeTally``).
    """
    usable = on_step is None and _lean_applies(env, policy)
    if lean and not usable:
        raise ValueError(
            "run_episodes(lean=True) needs an rlexp env without transforms, rlexp's sampling "
            "policy (or a RecurrentActor) and no on_step callback"
        )
    tally = EpisodeTally(int(env.batch_size.numel()), episodes, max_steps)
    td = env.reset()
    if on_reset is not None:
        td = on_reset(td)
    if usable if lean is None else lean:
        _lean_loop(env, policy, td.get("observation"), tally)
    else:
        _torchrl_loop(env, policy, td, tally, on_step)
    if tally.cut:
        name = getattr(base_env(env), "env_id", type(base_env(env)).__name__)
        log.warning(
            "[eval] %d of %d eval episodes of %s ran %d steps without ending and were cut there "
            "(counted as truncated): the env has no time limit; give it one with "
            "env.max_episode_steps=N",
            tally.cut, episodes, name, tally.max_steps,
        )  # fmt: skip
    return tally.metrics()


#: An eval round on a GPU env reads rewards and done flags back to the host every this many steps
#: (a round runs up to CHUNK - 1 steps past its last episode; the envs are reseeded every round).
DEVICE_CHUNK = 32


def _lean_applies(env: EnvBase, policy: Any) -> bool:
    """The lean loop's conditions (``supports_fast_rollout``), a RecurrentActor standing for
    rlexp's sampling policy."""
    if isinstance(policy, RecurrentActor):
        return supports_fast_rollout(env, policy.policy.sampling_policy(deterministic=True))
    return supports_fast_rollout(env, policy)


def _actor(policy: Any) -> tuple[Callable[[Any], torch.Tensor], Callable[[Any], None] | None]:
    """``obs -> action`` for the lean loops, and what to tell where episodes ended (None: nothing,
    a policy without state)."""
    if isinstance(policy, RecurrentActor):
        return policy.act, policy.episodes_ended
    sample = policy.sampler()  # the parameters do not change during a round: built once
    return (lambda obs: sample(obs)[-2]), None  # (..., action, log-prob)


def _lean_loop(env: EnvBase, policy, obs: torch.Tensor, tally: EpisodeTally) -> None:
    """The collector's fast path: deterministic actions from plain tensors, the env's own step."""
    act, ended = _actor(policy)
    to_policy, to_env = devices(env, getattr(policy, "policy", policy))
    if env.device.type != "cpu":
        _device_loop(env, act, ended, obs, tally, to_policy, to_env)
        return
    n = len(tally.quota)
    success_key = None
    first = True
    while not tally.finished:
        if to_env is not None:
            obs = obs.to(to_policy)
        action = act(obs)
        nxt = env.step_action(action if to_env is None else action.to(to_env))
        if first:  # an env's step output always has the same keys
            first = False
            success_key = _success_key(env, nxt)
        success = None if success_key is None else nxt.get(success_key).numpy().reshape(n)
        done = nxt.get("done")
        tally.add(nxt.get("reward").numpy().reshape(n), done.numpy().reshape(n), success)
        if ended is not None:  # a recurrent policy: the ended copies start from the initial state
            ended(done.reshape(n))
        obs = env.autoreset_observation(nxt)


def _device_loop(env, act, ended, obs, tally: EpisodeTally, to_policy, to_env) -> None:
    """The lean loop for an env on a GPU: rewards and done flags stay there, read back to the host
    once per ``DEVICE_CHUNK`` steps (no host round trip per step); the same tally, step by step."""
    n = len(tally.quota)
    success_key, first, keys = None, True, ("reward", "done")
    while not tally.finished:
        chunk: list[tuple[torch.Tensor, ...]] = []
        for _ in range(DEVICE_CHUNK):
            if to_env is not None:
                obs = obs.to(to_policy)
            action = act(obs)
            nxt = env.step_action(action if to_env is None else action.to(to_env))
            if first:  # an env's step output always has the same keys
                success_key, first = _success_key(env, nxt), False
                keys = (
                    ("reward", "done") if success_key is None else ("reward", "done", success_key)
                )
            chunk.append(tuple(nxt.get(k).reshape(n) for k in keys))
            if ended is not None:  # on the device: no read back
                ended(nxt.get("done").reshape(n))
            obs = env.autoreset_observation(nxt)
        host = [torch.stack(col).detach().float().cpu().numpy() for col in zip(*chunk, strict=True)]
        for t in range(DEVICE_CHUNK):
            tally.add(host[0][t], host[1][t] > 0, None if success_key is None else host[2][t])
            if tally.finished:
                return


def _torchrl_loop(
    env: EnvBase,
    policy: Callable[[TensorDictBase], TensorDictBase],
    td: TensorDictBase,
    tally: EpisodeTally,
    on_step: Callable[[TensorDictBase], None] | None,
) -> None:
    """TorchRL's ``step_and_maybe_reset`` loop: any env, any policy, each step's tensordict; a
    policy with state (``episodes_ended``) is told which copies' episodes ended."""
    n = len(tally.quota)
    key, first = None, True
    ended = getattr(policy, "episodes_ended", None)
    while not tally.finished:
        td = policy(td)
        if on_step is not None:
            on_step(td)
        out, td = env.step_and_maybe_reset(td)
        nxt = out["next"]
        if first:  # an env's step output always has the same keys
            key, first = _success_key(env, nxt), False
        success = None if key is None else nxt[key].reshape(n).cpu().numpy()
        tally.add(
            nxt["reward"].reshape(n).cpu().numpy(), nxt["done"].reshape(n).cpu().numpy(), success
        )
        if ended is not None:
            ended(nxt["done"].reshape(n))
