"""``Replay.snapshot`` / ``settle`` (issue #49, item 3): an eval round's copy of the buffer's state
writes nothing; if that copy goes into a checkpoint, ``settle`` writes the rows it lacks, and the
result loads as the buffer was at the snapshot. Rows the next update would overwrite are written
first; later than that a snapshot cannot be settled (loudly). ``ChunkKeeper``: what the
checkpoint files in a folder name."""

from __future__ import annotations

import pytest
from test_replay import all_rows, ids_at_positions, rollout

from rlexp.algorithms.replay import Replay
from rlexp.algorithms.replay_files import ReplayFileError


def _chunk_files(replay: Replay) -> list[str]:
    return sorted(p.name[:31] for p in replay.directory.glob("chunk-*.pt"))


def test_a_snapshot_writes_nothing_and_settles_to_the_buffer_at_its_step(tmp_path):
    replay = Replay(13, directory=tmp_path, seed=4)
    replay.extend(rollout(2, 3, 0))  # rows 0-5
    replay.save()  # chunk [0, 6)
    replay.extend(rollout(2, 4, 6))  # rows 6-13: the ring (13) has dropped row 0
    snap = replay.snapshot()
    assert _chunk_files(replay) == ["chunk-000000000000-000000000006"]
    expected_ids, expected_next = ids_at_positions(replay), replay.sample(40)
    replay.extend(rollout(2, 1, 14))  # the next update: rows 14-15 overwrite rows 1 and 2 only
    settled = replay.settle(snap)
    assert _chunk_files(replay) == [
        "chunk-000000000000-000000000006",
        "chunk-000000000006-000000000014",  # exactly the rows the snapshot lacked
    ]
    assert "unsaved" not in settled and settled["written"] == 14
    loaded = Replay(13, directory=tmp_path)
    loaded.load_state_dict(settled)
    assert ids_at_positions(loaded) == expected_ids
    assert (loaded.sample(40) == expected_next).all()
    # the next save goes on after the settled rows: [14, 16), nothing written twice
    replay.save()
    assert _chunk_files(replay)[-1] == "chunk-000000000014-000000000016"


def test_rows_a_snapshot_needs_are_written_before_the_next_update_overwrites_them(tmp_path):
    replay = Replay(10, directory=tmp_path, seed=4)
    replay.extend(rollout(2, 4, 0))  # rows 0-7, none saved
    snap = replay.snapshot()
    kept = all_rows(replay).clone()
    replay.extend(rollout(2, 3, 8))  # rows 8-13 overwrite rows 0-3, which the snapshot holds
    assert _chunk_files(replay) == ["chunk-000000000000-000000000008"]
    loaded = Replay(10, directory=tmp_path)
    loaded.load_state_dict(replay.settle(snap))
    assert (all_rows(loaded) == kept).all()
    assert _chunk_files(replay) == ["chunk-000000000000-000000000008"]  # settled: no second write


def test_a_snapshot_is_not_settled_after_a_second_update_nor_loaded_unsettled(tmp_path):
    replay = Replay(10, directory=tmp_path)
    replay.extend(rollout(1, 3, 0))
    snap = replay.snapshot()
    with pytest.raises(ReplayFileError, match="never settled"):
        Replay(10, directory=tmp_path).load_state_dict(snap)
    replay.extend(rollout(1, 1, 3))
    replay.extend(rollout(1, 1, 4))  # the trainer takes a round in after one update: dropped
    with pytest.raises(RuntimeError, match="can no longer be written"):
        replay.settle(snap)
    assert _chunk_files(replay) == []
