"""A stop signal is honoured at the safe point, never in the middle of an update (docs/faults.md).

The signal is raised in this process at a chosen instant of the update: right after the first
optimiser step of the second PPO update, when the parameters are neither the old nor the new ones.
The run must finish that update and checkpoint at the end of the iteration; the checkpoint must
equal an uninterrupted run's at the same step, and a resume from it must be bit-identical.
"""

from __future__ import annotations

import signal
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
import torch
from torch.optim.optimizer import register_optimizer_step_post_hook

from conftest import SHORT, compose
from rlexp.checkpoints.files import load_checkpoint, step_checkpoints

#: Four updates of 256 env steps, four optimiser steps each (256 / mini_batch_size 64, one epoch).
RUN = [
    *SHORT,
    "trainer.total_frames=1024",
    "trainer.keep_last=0",
    "logger=none",
    "logger.jsonl=true",
]
#: The update the signal lands in (1-based), and the env steps collected when it starts.
NTH_UPDATE, STEP = 2, 512
#: What belongs to the run's state; ``config``, ``versions`` and ``path`` name the run instead.
NOT_STATE = {"config", "versions", "path"}


def _train(run_dir: Path, *extra: str) -> None:
    from rlexp.app import train
    from rlexp.config.validate import to_root_config

    train(to_root_config(compose([*RUN, *extra])), run_dir)


def _differences(a: Any, b: Any, where: str = "") -> list[str]:
    """Where two checkpoint values differ, bit for bit (tensors: dtype, shape and values)."""
    if isinstance(a, torch.Tensor) or isinstance(b, torch.Tensor):
        same = isinstance(a, torch.Tensor) and isinstance(b, torch.Tensor)
        return [] if same and a.dtype == b.dtype and torch.equal(a, b) else [where]
    if isinstance(a, dict) and isinstance(b, dict):
        if a.keys() != b.keys():
            return [f"{where} keys {sorted(map(str, a.keys() ^ b.keys()))}"]
        return [d for k in a for d in _differences(a[k], b[k], f"{where}.{k}")]
    if isinstance(a, list | tuple) and isinstance(b, list | tuple):
        if len(a) != len(b):
            return [f"{where} length {len(a)} != {len(b)}"]
        return [
            d
            for i, (x, y) in enumerate(zip(a, b, strict=True))
            for d in _differences(x, y, f"{where}[{i}]")
        ]
    return [] if a == b or (a != a and b != b) else [f"{where}: {a!r} != {b!r}"]  # NaN == NaN


def _state_differences(a: dict[str, Any], b: dict[str, Any]) -> list[str]:
    return _differences(
        {k: v for k, v in a.items() if k not in NOT_STATE},
        {k: v for k, v in b.items() if k not in NOT_STATE},
    )


@contextmanager
def _signal_mid_update(sig: int, nth_update: int) -> Iterator[list[int]]:
    """Raise ``sig`` in this process right after the first optimiser step of PPO update number
    ``nth_update``; yields the optimiser steps taken in that update (to show the signal landed
    inside it). The disposition is the terminal's, whatever the test runner inherited (a shell's
    ``&`` or ``nohup`` ignore SIGINT / SIGHUP, and rlexp keeps an ignored signal ignored)."""
    from rlexp.algorithms.ppo import PPO

    real_update = PPO.update
    state = {"armed": False, "in_update": False}
    steps_in_update: list[int] = []

    def update(self, batch):
        state["armed"] = state["in_update"] = self.iteration + 1 == nth_update
        try:
            return real_update(self, batch)
        finally:
            state["in_update"] = False

    def after_step(optimizer, args, kwargs) -> None:
        if state["in_update"]:
            steps_in_update.append(1)
        if state["armed"]:
            state["armed"] = False
            signal.raise_signal(sig)  # its Python handler has run when this returns

    default = signal.default_int_handler if sig == signal.SIGINT else signal.SIG_DFL
    previous = signal.signal(sig, default)
    handle = register_optimizer_step_post_hook(after_step)
    PPO.update = update
    try:
        yield steps_in_update
    finally:
        PPO.update = real_update
        handle.remove()
        signal.signal(sig, previous)


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_a_stop_signal_mid_update_checkpoints_the_complete_update_and_resumes_exactly(
    tmp_path, sig
):
    from rlexp.app import RunEnded

    whole = tmp_path / "whole"
    _train(whole, "trainer.save_every=256")  # a checkpoint at every step, STEP's included
    reference = {load_checkpoint(p)["global_step"]: p for p in step_checkpoints(whole)}

    broken = tmp_path / "broken"  # no step checkpoints: the only one is the stop's
    with _signal_mid_update(sig, NTH_UPDATE) as steps, pytest.raises(RunEnded) as ended:
        _train(broken, "trainer.save_every=0")
    assert ended.value.exit_code == 128 + sig, str(ended.value)
    assert len(steps) == 4, "the signal did not land inside the update, or the update was cut"
    saved = step_checkpoints(broken)
    assert [p.name[-12:] for p in saved] == [f"{STEP:09d}.pt"], (
        "the stop must checkpoint once, at the end of the iteration the signal came in"
    )
    stopped = load_checkpoint(saved[0])
    assert stopped["algorithm"]["iteration"] == NTH_UPDATE
    differ = _state_differences(load_checkpoint(reference[STEP]), stopped)
    assert not differ, f"not the state after the whole update: {differ[:4]}, {len(differ)} in all"

    _train(broken, "trainer.save_every=0")  # resume=auto: continues from the stop's checkpoint
    final = load_checkpoint(step_checkpoints(broken)[-1])
    assert final["global_step"] == 1024
    differ = _state_differences(load_checkpoint(reference[1024]), final)
    assert not differ, f"not the uninterrupted run's state: {differ[:4]}, {len(differ)} in all"
