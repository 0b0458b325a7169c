"""The training episodes' statistics: each env's running return and length, the windows of the last
100 finished episodes (``train/episode_return``, ``train/episode_length``) and a rollout's per-term
means; checkpointed (``windows``) so that a resumed run logs what an uninterrupted one would."""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from typing import Any

import numpy as np
from tensordict import TensorDictBase


class EpisodeStats:
    """Finished episodes' returns and lengths, from [num_envs, T] rollouts."""

    def __init__(self, num_envs: int, window: int = 100) -> None:
        self.num_envs = num_envs
        self.returns: deque[float] = deque(maxlen=window)
        self.lengths: deque[int] = deque(maxlen=window)
        self.running_return = np.zeros(num_envs)
        self.running_length = np.zeros(num_envs, dtype=np.int64)
        self.term_means: dict[str, float] = {}  # rewards/<term>, metrics/<name>: the last rollout's

    def drop_running(self) -> None:
        """Every env starts a new episode (GRPO): the episodes in flight are not counted."""
        self.running_return[:] = 0.0
        self.running_length[:] = 0

    def track(
        self, batch: TensorDictBase, gather: Callable[[Any], list[Any]] | None = None
    ) -> None:
        """Fold a rollout in; ``gather`` (all_gather_object, distributed): every rank's finished
        episodes, in rank order."""
        nxt = batch["next"]
        rewards = nxt["reward"].reshape(self.num_envs, -1).cpu().numpy()
        dones = nxt["done"].reshape(self.num_envs, -1).cpu().numpy()
        returns: list[float] = []
        lengths: list[int] = []
        for t in range(rewards.shape[1]):
            self.running_return += rewards[:, t]
            self.running_length += 1
            finished = dones[:, t]
            if finished.any():
                returns += self.running_return[finished].tolist()
                lengths += self.running_length[finished].tolist()
                self.running_return[finished] = 0.0
                self.running_length[finished] = 0
        if gather is not None:
            gathered = gather((returns, lengths))
            returns = [r for rets, _ in gathered for r in rets]
            lengths = [n for _, lens in gathered for n in lens]
        self.returns.extend(returns)
        self.lengths.extend(lengths)
        self.term_means = {}
        for group in ("rewards", "metrics"):
            if group in nxt.keys():
                for key, value in nxt[group].items():
                    self.term_means[f"{group}/{key}"] = float(value.float().mean())

    def means(self) -> dict[str, float]:
        """The windows' mean return and length (once an episode has finished), the term means."""
        out = {}
        if self.returns:
            out["train/episode_return"] = float(np.mean(self.returns))
            out["train/episode_length"] = float(np.mean(self.lengths))
        return {**out, **self.term_means}

    def state_dict(self) -> dict[str, Any]:
        return {
            "returns": list(self.returns),
            "lengths": list(self.lengths),
            "running_return": self.running_return.copy(),
            "running_length": self.running_length.copy(),
        }

    def load_state_dict(self, w: dict[str, Any]) -> None:
        """The windows, and the running sums when the checkpoint had as many envs."""
        self.returns.extend(w["returns"])
        self.lengths.extend(w["lengths"])
        if len(w.get("running_return", ())) == self.num_envs:
            self.running_return[:] = np.asarray(w["running_return"])
            self.running_length[:] = np.asarray(w["running_length"])
