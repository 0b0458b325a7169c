"""The built-in hooks: ``stop_at``, ``stop_on_plateau``, ``schedule``, ``median_stop`` and ``piecewise``.

Each is a class registered by name; its parameters are checked before the run dir is written, and
its state (counters, the best value so far, a schedule's start value) is checkpointed.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

from rlexp.config.native_task import Flag, Number, ParamRule, Text
from rlexp.files import safe_read
from rlexp.hooks.base import HookControl, HookState, register_hook

_METRIC = Text()


def _value(state: HookState, metric: str) -> float | None:
    """The metric at this point: eval metrics at ``eval_end``, training metrics at ``log``."""
    source = state.eval_metrics if state.point == "eval_end" else state.metrics
    value = source.get(metric)
    if value is None or not math.isfinite(float(value)):
        return None
    return float(value)


def _points(metric: str) -> tuple[str, ...]:
    return ("eval_end",) if metric.startswith("eval/") else ("log",)


class _MetricHook:
    """A hook that watches one metric: at ``eval_end`` for ``eval/...`` metrics, else at ``log``."""

    def __init__(self, metric: str, higher_is_better: bool = True) -> None:
        self.metric = metric
        self.sign = 1.0 if higher_is_better else -1.0
        self.watch = _points(metric)

    def __call__(self, state: HookState, control: HookControl) -> None:
        if state.point not in self.watch:
            return
        value = _value(state, self.metric)
        if value is not None:
            self.observe(state, control, value)

    def observe(self, state: HookState, control: HookControl, value: float) -> None:
        raise NotImplementedError


@register_hook(
    "stop_at",
    points=("log", "eval_end"),
    params={
        "metric": _METRIC,
        "threshold": Number(),
        "times": Number(ge=1, integer=True),
        "higher_is_better": Flag(),
    },
    required=("threshold",),
)
class StopAt(_MetricHook):
    """Stop once ``metric`` is at or past ``threshold`` (``times`` evaluations / logs in a row)."""

    def __init__(
        self,
        threshold: float,
        metric: str = "eval/episode_return",
        times: int = 1,
        higher_is_better: bool = True,
    ) -> None:
        super().__init__(metric, higher_is_better)
        self.threshold = float(threshold)
        self.times = int(times)
        self.in_a_row = 0

    def observe(self, state: HookState, control: HookControl, value: float) -> None:
        reached = self.sign * (value - self.threshold) >= 0
        self.in_a_row = self.in_a_row + 1 if reached else 0
        if self.in_a_row >= self.times:
            rel = ">=" if self.sign > 0 else "<="
            row = f" ({self.times} in a row)" if self.times > 1 else ""
            control.request_stop(
                f"{self.metric}={value:.4g} {rel} {self.threshold:g}{row} at step {state.global_step}"
            )

    def state_dict(self) -> dict[str, Any]:
        return {"in_a_row": self.in_a_row}

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        self.in_a_row = int(sd["in_a_row"])


@register_hook(
    "stop_on_plateau",
    points=("log", "eval_end"),
    params={
        "metric": _METRIC,
        "patience": Number(ge=1, integer=True),
        "min_delta": Number(ge=0),
        "higher_is_better": Flag(),
    },
)
class StopOnPlateau(_MetricHook):
    """Stop when ``metric`` has not improved by more than ``min_delta`` for ``patience`` evaluations."""

    def __init__(
        self,
        metric: str = "eval/episode_return",
        patience: int = 5,
        min_delta: float = 0.0,
        higher_is_better: bool = True,
    ) -> None:
        super().__init__(metric, higher_is_better)
        self.patience = int(patience)
        self.min_delta = float(min_delta)
        self.best = -math.inf
        self.since_best = 0

    def observe(self, state: HookState, control: HookControl, value: float) -> None:
        if self.sign * value > self.best + self.min_delta:
            self.best, self.since_best = self.sign * value, 0
            return
        self.since_best += 1
        if self.since_best >= self.patience:
            control.request_stop(
                f"{self.metric} has not improved on {self.sign * self.best:.4g} for "
                f"{self.since_best} evaluations (patience {self.patience})"
            )

    def state_dict(self) -> dict[str, Any]:
        return {"best": self.best, "since_best": self.since_best}

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        self.best, self.since_best = float(sd["best"]), int(sd["since_best"])


SCHEDULE_KINDS = ("linear", "cosine", "step")


@register_hook(
    "schedule",
    points=("train_start", "rollout_end"),
    params={
        "name": Text(),
        "kind": Text(choices=SCHEDULE_KINDS),
        "start": Number(),
        "end": Number(),
        "start_step": Number(ge=0, integer=True),
        "end_step": Number(gt=0, integer=True),
        "every": Number(gt=0, integer=True),
        "factor": Number(gt=0),
    },
    required=("name",),
)
class Schedule:
    """A mutable hyperparameter as a function of env steps, set before every update.

    ``linear`` / ``cosine``: from ``start`` (default: its configured value) at ``start_step`` (0) to
    ``end`` (0) at ``end_step`` (default: the run's budget), constant outside. ``step``: ``start``
    multiplied by ``factor`` every ``every`` env steps."""

    def __init__(
        self,
        name: str,
        kind: str = "linear",
        start: float | None = None,
        end: float = 0.0,
        start_step: int = 0,
        end_step: int | None = None,
        every: int | None = None,
        factor: float = 0.5,
    ) -> None:
        self.name, self.kind = name, kind
        self.start, self.end = start, float(end)
        self.start_step, self.end_step = int(start_step), end_step
        self.every, self.factor = every, float(factor)

    @staticmethod
    def check_params(params: dict[str, Any], where: str) -> None:
        if params.get("kind") == "step" and "every" not in params:
            raise ValueError(f"{where}.params.every is needed with kind=step (env steps)")
        end_step = params.get("end_step")
        if end_step is not None and end_step <= params.get("start_step", 0):
            raise ValueError(
                f"{where}.params.end_step={end_step} must be above start_step="
                f"{params.get('start_step', 0)}"
            )

    def value(self, step: int, total: int) -> float:
        start = float(self.start)  # type: ignore[arg-type]
        if self.kind == "step":
            return start * self.factor ** (max(0, step - self.start_step) // int(self.every))  # type: ignore[arg-type]
        end_step = self.end_step if self.end_step is not None else total
        frac = min(1.0, max(0.0, (step - self.start_step) / max(1, end_step - self.start_step)))
        if self.kind == "cosine":
            frac = 0.5 * (1.0 - math.cos(math.pi * frac))
        return start + (self.end - start) * frac

    def __call__(self, state: HookState, control: HookControl) -> None:
        if self.start is None:  # the configured value, read once (and checkpointed)
            if self.name not in state.hyperparameters:
                control.set(self.name, 0.0)  # raises, listing the mutable names
            self.start = float(state.hyperparameters[self.name])
        # Before the update that follows: the value at the steps collected so far.
        control.set(self.name, self.value(state.global_step, state.total_steps))

    def state_dict(self) -> dict[str, Any]:
        return {"start": self.start}

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        self.start = sd["start"]


#: Bytes of a sibling's new ``metrics.jsonl`` lines read at one look at most.
SIBLING_READ = 16 << 20


@register_hook(
    "median_stop",
    points=("eval_end", "log"),
    params={
        "metric": _METRIC,
        "warmup": Number(ge=0, le=1),
        "min_siblings": Number(ge=1, integer=True),
        "higher_is_better": Flag(),
    },
)
class MedianStop(_MetricHook):
    """Sweep-level early stopping (the median stopping rule): after ``warmup`` of the budget, at each
    evaluation, stop this job when its ``metric`` is below the median of the sibling jobs' values at
    the same step — siblings being the other job dirs of the sweep dir (this run dir's parent) that
    have logged the metric at this step or later. Works for every launcher on a shared filesystem:
    it reads the siblings' ``metrics.jsonl``."""

    def __init__(
        self,
        metric: str = "eval/episode_return",
        warmup: float = 0.25,
        min_siblings: int = 2,
        higher_is_better: bool = True,
    ) -> None:
        super().__init__(metric, higher_is_better)
        self.warmup = float(warmup)
        self.min_siblings = int(min_siblings)
        self._offsets: dict[Path, tuple[int, list[tuple[int, float]]]] = {}

    def observe(self, state: HookState, control: HookControl, value: float) -> None:
        if state.global_step < self.warmup * state.total_steps or state.rank != 0:
            return
        values = []
        for sibling in sorted(state.run_dir.parent.iterdir()):
            if sibling == state.run_dir or not (sibling / "metrics.jsonl").is_file():
                continue
            at = self._value_at(sibling / "metrics.jsonl", state.global_step)
            if at is not None:
                values.append(at)
        if len(values) < self.min_siblings:
            return
        values.sort()
        mid = len(values) // 2
        median = values[mid] if len(values) % 2 else 0.5 * (values[mid - 1] + values[mid])
        if self.sign * (value - median) < 0:
            control.request_stop(
                f"median stopping rule: {self.metric}={value:.4g} at step {state.global_step} is "
                f"{'below' if self.sign > 0 else 'above'} the median {median:.4g} of "
                f"{len(values)} sibling jobs"
            )

    def _value_at(self, path: Path, step: int) -> float | None:
        """The sibling's metric at its last logged step <= ``step``, if it has logged the metric at
        ``step`` or later (it reached this step); reads each file's new lines only."""
        offset, points = self._offsets.get(path, (0, []))
        try:  # a sibling's dir is another job's: read bounded (rlexp.files.safe_read), never trusted
            with safe_read.open_regular(path) as opened:
                if opened is None:
                    return None
                f, size = opened
                f.seek(offset)
                chunk = f.read(max(0, min(size - offset, SIBLING_READ)))
        except (OSError, safe_read.Unreadable):
            return None
        end = chunk.rfind(b"\n") + 1
        if end == 0 and len(chunk) == SIBLING_READ:  # one line longer than a read: skip it
            end = len(chunk)
        complete = chunk[:end]
        for line in complete.splitlines():
            if self.metric.encode() not in line:
                continue
            try:
                row = json.loads(line)
                points.append((int(row["step"]), float(row[self.metric])))
            except (ValueError, KeyError, TypeError, OverflowError, RecursionError):
                continue  # not a row, or a value beyond float's range (10**400)
        self._offsets[path] = (offset + len(complete), points)
        if not points or max(s for s, _ in points) < step:
            return None
        before = [(s, v) for s, v in points if s <= step and math.isfinite(v)]
        return max(before)[1] if before else None


class _Points(ParamRule):
    """``[[step, value], ...]``: steps whole, >= 0 and increasing, values finite."""

    text = "a list of [env step, value] pairs, steps increasing from 0 or later"

    def check(self, value: Any, where: str, env: Any = None) -> None:
        if not isinstance(value, list) or not value:
            raise TypeError(f"{where}={value!r} must be {self.text}")
        last = -1
        for i, pair in enumerate(value):
            if not isinstance(pair, list) or len(pair) != 2:
                raise TypeError(f"{where}[{i}]={pair!r} must be [env step, value]")
            Number(ge=0, integer=True).check(pair[0], f"{where}[{i}][0]")
            Number().check(pair[1], f"{where}[{i}][1]")
            if int(pair[0]) <= last:
                raise ValueError(f"{where}[{i}][0]={pair[0]} must be above the step before it")
            last = int(pair[0])


@register_hook(
    "piecewise",
    points=("train_start", "rollout_end"),
    params={"name": Text(), "points": _Points()},
    required=("name", "points"),
)
class Piecewise:
    """A mutable hyperparameter held at ``value`` from each ``[step, value]`` of ``points`` on (before
    the first step: its configured value), set before every update: a PBT member's schedule,
    replayed (``rlexp pbt export``, docs/pbt.md)."""

    def __init__(self, name: str, points: list[list[float]]) -> None:
        self.name = name
        self.points = [(int(s), float(v)) for s, v in points]

    def __call__(self, state: HookState, control: HookControl) -> None:
        due = [v for s, v in self.points if s <= state.global_step]
        if due and state.hyperparameters.get(self.name) != due[-1]:
            control.set(self.name, due[-1])
