"""Checkpoint writes are atomic (docs/checkpoints.md): a write that fails half-way, as on a full
disk, leaves the previous file under the final name whole and loadable, never a partial one, and
no temporary file behind; at every instant of the write the final name holds the old file or none.
Step checkpoints and ``best.pt``'s rewrite alike."""

from __future__ import annotations

import errno
import io
from pathlib import Path

import pytest
import torch

import rlexp.checkpoints.files as ckpt_mod
from conftest import SHORT, compose
from rlexp.checkpoints.files import load_checkpoint, save_checkpoint


def _state(step: int) -> dict:
    return {
        "global_step": step,
        "policy": {"w": torch.full((64, 64), float(step))},
        "algorithm": {"iteration": step // 256},
        "config": {"seed": 0},
    }


class FullDisk:
    """``torch.save`` that writes the first half of the real bytes, then fails as a full disk does,
    on the calls whose file name contains ``name`` and is in ``failing`` (1-based among those);
    at that instant, records what the final path ``watch`` holds (a kill would leave that)."""

    def __init__(self, name: str, failing: set[int], watch: Path) -> None:
        self.name, self.failing, self.watch = name, failing, watch
        self.real_save = torch.save
        self.calls = 0
        self.seen: list[int | str | None] = []  # watch's global_step mid-write, None: no file

    def __call__(self, obj, f, *args, **kw):
        if self.name not in str(getattr(f, "name", "")):
            return self.real_save(obj, f, *args, **kw)
        self.calls += 1
        if self.calls not in self.failing:
            return self.real_save(obj, f, *args, **kw)
        data = io.BytesIO()
        self.real_save(obj, data, *args, **kw)
        f.write(data.getvalue()[: len(data.getvalue()) // 2])
        f.flush()
        self.seen.append(self._watched())
        raise OSError(errno.ENOSPC, "No space left on device")

    def _watched(self) -> int | str | None:
        if not self.watch.exists():
            return None
        try:
            return load_checkpoint(self.watch)["global_step"]
        except ValueError as exc:
            return f"unloadable: {exc}"


def test_a_failed_rewrite_leaves_the_previous_file_whole(tmp_path, monkeypatch):
    path = tmp_path / "checkpoints" / "run_step_000000256.pt"
    save_checkpoint(path, _state(256))
    disk = FullDisk(path.name, {1}, watch=path)
    monkeypatch.setattr(ckpt_mod.torch, "save", disk)
    with pytest.raises(OSError, match="No space left"):
        save_checkpoint(path, _state(512))
    assert disk.seen == [256], "mid-write, the final name must still hold the previous file"
    assert load_checkpoint(path)["global_step"] == 256
    assert torch.equal(load_checkpoint(path)["policy"]["w"], torch.full((64, 64), 256.0))
    assert [p.name for p in path.parent.iterdir()] == [path.name], "a temporary file was left"


def test_a_failed_first_write_leaves_no_file_under_the_final_name(tmp_path, monkeypatch):
    path = tmp_path / "checkpoints" / "run_step_000000256.pt"
    disk = FullDisk(path.name, {1}, watch=path)
    monkeypatch.setattr(ckpt_mod.torch, "save", disk)
    with pytest.raises(OSError, match="No space left"):
        save_checkpoint(path, _state(256))
    assert disk.seen == [None], "mid-write, a partial file had the final name"
    assert list(path.parent.iterdir()) == []


def test_a_failed_rewrite_of_best_pt_keeps_the_previous_best(tmp_path, monkeypatch):
    """A real run: eval improves at every round (a stand-in eval), so best.pt is written at step
    256 and rewritten at step 512; that rewrite fails half-way. The best of step 256 stays."""
    from rlexp.app import RunEnded, train
    from rlexp.config.validate import to_root_config
    from rlexp.training.trainer import Trainer

    def improving_round(self, policy):
        return {
            "eval/episode_return": float(self.global_step),
            "eval/episode_return_std": 0.0,
            "eval/episode_length": 1.0,
        }

    run_dir = tmp_path / "run"
    best = run_dir / "checkpoints" / "best.pt"
    monkeypatch.setattr(Trainer, "_run_round", improving_round)
    disk = FullDisk("best.pt", {2}, watch=best)
    monkeypatch.setattr(ckpt_mod.torch, "save", disk)
    config = to_root_config(
        compose([*SHORT, "trainer.eval_every=256", "logger=none", "logger.jsonl=true"])
    )
    with pytest.raises(RunEnded) as ended:
        train(config, run_dir)
    assert ended.value.exit_code == 1 and "No space left on device" in str(ended.value)
    assert disk.calls == 2 and disk.seen == [256], "mid-rewrite, best.pt was not the old best"
    kept = load_checkpoint(best)
    assert kept["global_step"] == 256 and kept["best_metric"] == 256.0
    assert not list(run_dir.rglob("*.tmp-*")), "a temporary file was left"
