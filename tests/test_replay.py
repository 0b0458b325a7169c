"""The replay buffer (rlexp.algorithms.replay): shapes, uniform sampling over the valid rows, ring
order, both episode-end flags, and checkpoints: incremental chunks, a load in a fresh process giving
the same contents and the same next samples, deletion only after a later save commits, corrupt
chunks as one line."""

from __future__ import annotations

import io
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict

from rlexp.algorithms import replay as replay_mod
from rlexp.algorithms.replay import Replay
from rlexp.algorithms.replay_files import ReplayFileError

REPO = Path(__file__).resolve().parents[1]
OBS, ACT = 17, 6


def rollout(num_envs: int, steps: int, first: int, obs: int = OBS, act: int = ACT) -> TensorDict:
    """A rollout [num_envs, steps] whose rows are numbered from ``first`` (env-major, the order
    the buffer stores them in): observation[..., 0] is the row's number."""
    ids = torch.arange(first, first + num_envs * steps, dtype=torch.float32).reshape(
        num_envs, steps
    )
    return TensorDict(
        {
            "observation": ids[..., None] + torch.zeros(obs),
            "action": -ids[..., None] + torch.zeros(act),
            "next": {
                "observation": ids[..., None] + 0.5 + torch.zeros(obs),
                "reward": ids[..., None] * 0.25,
                "terminated": (ids % 7 == 3)[..., None],
                "truncated": (ids % 5 == 1)[..., None],
            },
            "action_log_prob": torch.zeros(num_envs, steps),  # not a transition entry
        },
        [num_envs, steps],
    )


def ids_at_positions(replay: Replay) -> list[int]:
    rows = replay._rb.storage.get(torch.arange(len(replay)))
    return [int(v) for v in rows["observation"][:, 0]]


def all_rows(replay: Replay) -> TensorDict:
    return replay._rb.storage.get(torch.arange(len(replay)))


def test_extend_and_sample_give_the_transition_entries_with_their_shapes_and_dtypes():
    replay = Replay(100, seed=5)
    replay.extend(rollout(3, 4, 0))
    batch = replay.sample(32)
    assert batch.batch_size == (32,) and len(replay) == 12 and replay.written == 12
    shapes = {k: (tuple(v.shape), v.dtype) for k, v in batch.items(True, True)}
    assert shapes == {
        "observation": ((32, OBS), torch.float32),
        "action": ((32, ACT), torch.float32),
        ("next", "observation"): ((32, OBS), torch.float32),
        ("next", "reward"): ((32, 1), torch.float32),
        ("next", "terminated"): ((32, 1), torch.bool),
        ("next", "truncated"): ((32, 1), torch.bool),
        ("next", "done"): ((32, 1), torch.bool),
    }
    # each sampled row is one whole transition
    ids = batch["observation"][:, 0]
    assert torch.equal(batch["action"][:, 0], -ids)
    assert torch.equal(batch["next", "observation"][:, 0], ids + 0.5)
    assert torch.equal(batch["next", "reward"][:, 0], ids * 0.25)


def test_truncation_and_termination_are_both_kept_per_row():
    replay = Replay(64)
    replay.extend(rollout(2, 20, 0))
    rows = all_rows(replay)
    ids = rows["observation"][:, 0].long()
    term, trunc = rows["next", "terminated"][:, 0], rows["next", "truncated"][:, 0]
    assert torch.equal(term, ids % 7 == 3) and torch.equal(trunc, ids % 5 == 1)
    assert torch.equal(rows["next", "done"][:, 0], term | trunc)
    assert bool((trunc & ~term).any()) and bool((term & ~trunc).any())  # both kinds present
    assert bool(rows["next", "terminated"][ids == 1]) is False  # truncated only: not terminal


def test_sampling_is_uniform_over_the_valid_rows_only():
    replay = Replay(1000, seed=11)  # 37 valid rows in a ring of 1000
    replay.extend(rollout(1, 37, 0))
    draws = torch.cat([replay.sample(500)["observation"][:, 0] for _ in range(30)]).long()
    assert int(draws.min()) == 0 and int(draws.max()) == 36  # never an unwritten row
    counts = torch.bincount(draws, minlength=37)
    from scipy.stats import chisquare

    assert chisquare(counts.numpy()).pvalue > 1e-3


def test_the_generator_is_the_buffers_own():
    a, b = Replay(100, seed=3), Replay(100, seed=3)
    a.extend(rollout(2, 10, 0))
    b.extend(rollout(2, 10, 0))
    first = a.sample(16)["observation"][:, 0]
    torch.manual_seed(123)  # the global RNG does not decide the draw
    torch.rand(7)
    assert torch.equal(b.sample(16)["observation"][:, 0], first)
    # the very draw TorchRL's own sampler makes from the same generator state, on the same rows
    a.extend(rollout(3, 30, 20))  # 110 rows through a ring of 100
    state = a.generator.get_state()
    ours = a.sample(64)
    a.generator.set_state(state)
    torchrls = a._rb.sample(64)
    assert len(a._rb) == len(a) == 100
    assert set(ours.keys(True, True)) == set(torchrls.keys(True, True))
    for key in ours.keys(True, True):
        assert torch.equal(ours.get(key), torchrls.get(key)), key
    c = Replay(100, seed=4)
    c.extend(rollout(2, 10, 0))
    assert not torch.equal(c.sample(16)["observation"][:, 0], first)


def test_the_ring_overwrites_the_oldest_rows_in_place():
    replay = Replay(10)
    for first in (0, 4, 8):  # 12 rows through a ring of 10
        replay.extend(rollout(1, 4, first))
    assert len(replay) == 10 and replay.written == 12
    assert ids_at_positions(replay) == [10, 11, 2, 3, 4, 5, 6, 7, 8, 9]
    replay.extend(rollout(1, 23, 12))  # one batch longer than the ring: its last 10, in place
    assert replay.written == 35
    assert ids_at_positions(replay) == [30, 31, 32, 33, 34, 25, 26, 27, 28, 29]
    replay.extend(rollout(1, 1, 35))
    assert ids_at_positions(replay)[5] == 35
    fresh = Replay(10)  # the first batch already longer than the ring
    fresh.extend(rollout(1, 23, 0))
    assert ids_at_positions(fresh) == [20, 21, 22, 13, 14, 15, 16, 17, 18, 19]


def test_bad_settings_are_one_line_naming_the_key(tmp_path):
    with pytest.raises(ValueError, match="algorithm.buffer_storage='disk'"):
        Replay(10, storage="disk")
    with pytest.raises(ValueError, match="algorithm.buffer_storage=memmap needs a directory"):
        Replay(10, storage="memmap")
    with pytest.raises(ValueError, match="algorithm.n_step=0"):
        Replay(10, n_step=0)
    with pytest.raises(ValueError, match="algorithm.buffer_size=0"):
        Replay(0)
    with pytest.raises(ValueError, match=r"n_step=2 needs the rollout as \[num_envs, T\]"):
        Replay(10, n_step=2).extend(rollout(2, 3, 0).reshape(-1))
    replay = Replay(10)
    replay.extend(rollout(1, 2, 0))
    with pytest.raises(ValueError, match="do not fit the replay buffer's"):
        replay.extend(rollout(1, 2, 2, obs=5))


def test_auto_storage_memory_maps_a_buffer_too_big_for_a_share_of_ram(tmp_path, monkeypatch):
    small = Replay(1000, storage="auto", directory=tmp_path / "a")
    small.extend(rollout(1, 3, 0))
    assert small.storage_kind == "memory"
    # 1000 rows of 167 bytes > a quarter of a 400 kB machine
    monkeypatch.setattr(replay_mod, "physical_memory", lambda: 400_000)
    big = Replay(1000, storage="auto", directory=tmp_path / "b")
    big.extend(rollout(1, 3, 0))
    assert big.storage_kind == "memmap" and any((tmp_path / "b" / "memmap").rglob("*.memmap"))
    assert ids_at_positions(big) == [0, 1, 2]


def test_a_memory_buffer_larger_than_the_ram_is_one_line_before_it_is_allocated(monkeypatch):
    monkeypatch.setattr(replay_mod, "physical_memory", lambda: 100_000)
    replay = Replay(1000, storage="memory")
    with pytest.raises(ValueError) as err:
        replay.extend(rollout(1, 3, 0))
    text = str(err.value)
    assert "algorithm.buffer_size=1000 x 167 bytes per transition = 0.0 GB" in text
    assert "algorithm.buffer_storage=memmap" in text and "\n" not in text


def image_rollout(num_envs: int, steps: int, first: int) -> TensorDict:
    """Observations that are TensorDicts (a vector and a uint8 image), as image tasks give."""
    td = rollout(num_envs, steps, first, obs=3)
    for key in ("observation", ("next", "observation")):
        vector = td.get(key)
        pixels = (
            (vector[..., :1, None, None] % 251).to(torch.uint8).expand(num_envs, steps, 2, 4, 4)
        )
        td.set(key, TensorDict({"vector": vector, "pixels": pixels.clone()}, [num_envs, steps]))
    return td


@pytest.mark.parametrize("n_step", [1, 2])
def test_dict_observations_are_stored_sampled_and_saved(tmp_path, n_step):
    replay = Replay(40, directory=tmp_path, seed=3, n_step=n_step, gamma=0.5)
    replay.extend(image_rollout(2, 15, 0))
    state = replay.save()
    batch = replay.sample(8)
    assert batch["observation", "pixels"].shape == (8, 2, 4, 4)
    assert batch["observation", "pixels"].dtype == torch.uint8
    ids = batch["observation", "vector"][:, 0]
    assert torch.equal(batch["observation", "pixels"][:, 0, 0, 0], (ids % 251).to(torch.uint8))
    loaded = Replay(40, directory=tmp_path, seed=0, n_step=n_step, gamma=0.5)
    loaded.load_state_dict(state)
    replay.generator.set_state(state["generator"])
    want, got = replay.sample(8), loaded.sample(8)
    for key in want.keys(True, True):
        assert torch.equal(got.get(key), want.get(key)), key


def chunk_files(directory: Path) -> list[str]:
    return sorted(p.name for p in directory.glob("chunk-*.pt"))


@pytest.mark.parametrize("storage", ["memory", "memmap"])
def test_saves_write_only_the_new_rows(tmp_path, storage):
    replay = Replay(5000, storage=storage, directory=tmp_path, seed=2)
    replay.extend(rollout(4, 500, 0))
    replay.save("ckpt1")
    replay.commit()
    full = sum(p.stat().st_size for p in tmp_path.glob("chunk-*.pt"))
    replay.extend(rollout(4, 25, 2000))  # 100 new rows
    state = replay.save("ckpt2")
    replay.commit()
    sizes = sorted(p.stat().st_size for p in tmp_path.glob("chunk-*.pt"))
    # the new chunk is 100 rows of 167 bytes (and torch's framing), not the buffer again
    assert len(sizes) == 2 and sizes[1] == full and 100 * 167 < sizes[0] < 100 * 167 + 8192
    manifest = io.BytesIO()
    torch.save(state, manifest)
    assert len(manifest.getvalue()) < 12_000  # what the checkpoint file holds of the buffer
    assert [(c["start"], c["stop"]) for c in state["chunks"]] == [(0, 2000), (2000, 2100)]
    again = replay.save("ckpt3")  # nothing new: no new file
    assert again["chunks"] == state["chunks"] and len(chunk_files(tmp_path)) == 2


CHILD = textwrap.dedent(
    """
    import os, signal, sys, torch
    sys.path.insert(0, sys.argv[1])
    from tests.test_replay import rollout
    from rlexp.algorithms.replay import Replay
    for storage in ("memory", "memmap"):
        out = sys.argv[2] + "/" + storage
        replay = Replay(50, storage=storage, directory=out + "/replay", seed=7)
        for i in range(6):
            replay.extend(rollout(3, 4, 12 * i))  # 72 rows: the ring has wrapped
            replay.sample(8)
            if i == 3:
                replay.save("early"); replay.commit()
        state = replay.save("late")
        torch.save(state, out + "/manifest.pt")
        torch.save({"rows": replay._rb.storage.get(torch.arange(50)).to_dict(),
                    "next": [replay.sample(8).to_dict() for _ in range(3)]}, out + "/expected.pt")
        replay.extend(rollout(3, 4, 1000))  # after the checkpoint: never seen by the load
    os.kill(os.getpid(), signal.SIGKILL)
    """
)


def test_save_then_sigkill_then_load_in_this_process_is_identical(tmp_path):
    env = {**os.environ, "PYTHONPATH": str(REPO / "src")}
    proc = subprocess.run(
        [sys.executable, "-c", CHILD, str(REPO), str(tmp_path)],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == -9, proc.stderr[-2000:]
    for storage in ("memory", "memmap"):
        out = tmp_path / storage
        state = torch.load(out / "manifest.pt", weights_only=True)
        expected = torch.load(out / "expected.pt", weights_only=True)
        replay = Replay(50, storage=storage, directory=out / "replay", seed=999)
        replay.load_state_dict(state)
        assert replay.written == 72 and len(replay) == 50 and replay.storage_kind == storage
        rows = replay._rb.storage.get(torch.arange(50))
        assert rows.to_dict().keys() == expected["rows"].keys()
        for key, value in TensorDict.from_dict(expected["rows"]).items(True, True):
            assert torch.equal(rows.get(key), value), key
        for want in expected["next"]:
            got = replay.sample(8)
            for key, value in TensorDict.from_dict(want).items(True, True):
                assert torch.equal(got.get(key), value), key


def test_chunks_are_deleted_only_once_a_later_save_commits(tmp_path):
    replay = Replay(20, directory=tmp_path, seed=1)
    replay.extend(rollout(1, 12, 0))
    replay.save("a")
    replay.commit()
    [c1] = chunk_files(tmp_path)
    replay.extend(rollout(1, 8, 12))
    state_b = replay.save("b")
    assert replay.commit(["b"]) == []  # rows 0-11 are still in the ring
    replay.extend(rollout(1, 15, 20))  # 35 rows: rows 0-14 overwritten, c1 [0, 12) no longer needed
    state_c = replay.save("c")
    assert [c["start"] for c in state_c["chunks"]] == [12, 20] and c1 in chunk_files(tmp_path)

    # a crash before the checkpoint holding state_c commits: state_b still loads, every row
    crashed = Replay(20, directory=tmp_path)
    crashed.load_state_dict(state_b)
    assert ids_at_positions(crashed) == list(range(20))

    assert replay.commit(["b", "c"]) == []  # the checkpoint of b is kept: so are its chunks
    assert replay.commit(["c"]) == [c1]  # b's checkpoint pruned: c1 goes, nothing else
    assert chunk_files(tmp_path) == sorted(c["file"] for c in state_c["chunks"])
    loaded = Replay(20, directory=tmp_path)
    loaded.load_state_dict(state_c)
    assert ids_at_positions(loaded) == list(range(20, 35)) + list(range(15, 20))
    assert loaded.commit([]) == []  # a loaded buffer never deletes the chunks it was loaded from
    assert chunk_files(tmp_path) == sorted(c["file"] for c in state_c["chunks"])


def test_commit_can_keep_the_last_n_saves(tmp_path):
    """``commit(n)``: the chunks of the last n saves stay (a trainer keeping n checkpoints)."""
    replay = Replay(10, directory=tmp_path)
    states = []
    for first in (0, 6, 12):
        replay.extend(rollout(1, 6, first))
        states.append(replay.save())  # tags save-6, save-12, save-18
        assert replay.commit(0) == []  # <= 0: every save is kept
    c1 = states[0]["chunks"][0]["file"]
    assert [c["start"] for c in states[2]["chunks"]] == [6, 12]  # [0, 6) all overwritten
    assert replay.commit(2) == []  # the save at 12 still needs [0, 6)
    assert replay.commit(1) == [c1]
    # a buffer loaded from the newest save goes on with the saves its manifest names
    loaded = Replay(10, directory=tmp_path)
    loaded.load_state_dict(states[2])
    loaded.extend(rollout(1, 6, 18))
    state = loaded.save()
    assert [c["start"] for c in state["chunks"]] == [12, 18]
    assert loaded.commit(2) == []  # save-18 (its own manifest) still needs [6, 12)
    assert loaded.commit(None) == [states[1]["chunks"][1]["file"]]


def test_a_chunk_no_save_names_is_removed_at_the_next_commit(tmp_path):
    """A crash between writing a chunk and committing its checkpoint leaves the chunk behind."""
    replay = Replay(100, directory=tmp_path)
    replay.extend(rollout(1, 10, 0))
    replay.save("a")
    orphan = tmp_path / "chunk-000000000010-000000000020-0badf00d.pt"
    orphan.write_bytes(b"left by a crash")
    replay.extend(rollout(1, 10, 10))
    replay.save("b")
    assert replay.commit(["b"]) == [orphan.name]


@pytest.fixture
def saved(tmp_path) -> tuple[Path, dict]:
    replay = Replay(30, directory=tmp_path, seed=1)
    replay.extend(rollout(2, 5, 0))
    replay.save("a")
    replay.extend(rollout(2, 5, 10))
    return tmp_path, replay.save("b")


def corrupt_truncated(path: Path) -> None:
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


def corrupt_text(path: Path) -> None:
    path.write_text("not a chunk")


def corrupt_missing(path: Path) -> None:
    path.unlink()


def corrupt_other_rows(path: Path) -> None:
    """A well-formed chunk of another layout under this chunk's name."""
    other = Replay(30, directory=path.parent / "other")
    other.extend(rollout(2, 5, 0, obs=3))
    [entry] = other.save()["chunks"]
    (path.parent / "other" / entry["file"]).replace(path)


def corrupt_empty(path: Path) -> None:
    path.write_bytes(b"")


@pytest.mark.parametrize(
    "corrupt, says",
    [
        (corrupt_truncated, "truncated or corrupt"),
        (corrupt_text, "not a checkpoint"),
        (corrupt_missing, "cannot be read (No such file or directory): the checkpoint needs it"),
        (corrupt_other_rows, "the manifest expects torch.float32 [10, 17]"),
        (corrupt_empty, "an empty file"),
    ],
)
def test_a_corrupt_chunk_is_one_line_naming_the_file(saved, corrupt, says):
    directory, state = saved
    victim = directory / state["chunks"][1]["file"]
    corrupt(victim)
    with pytest.raises(ReplayFileError) as err:
        Replay(30, directory=directory).load_state_dict(state)
    text = str(err.value)
    assert "\n" not in text and str(victim) in text and says in text, text


@pytest.mark.parametrize(
    "field, value, says",
    [
        ("chunks", [{"file": "../../x.pt", "start": 0, "stop": 20}], "not a chunk file"),
        ("written", -1, "replay.written=-1"),
        ("generator", torch.zeros(3, dtype=torch.uint8), "replay.generator"),
        ("capacity", 31, "algorithm.buffer_size=30"),
        ("layout", [["observation", "torch.float99", [17]]], "replay.layout entry"),
        ("written", 25, "the buffer holds [0, 25)"),
    ],
)
def test_a_bad_manifest_field_is_one_line(saved, field, value, says):
    directory, state = saved
    with pytest.raises(ReplayFileError) as err:
        Replay(30, directory=directory).load_state_dict({**state, field: value})
    assert "\n" not in str(err.value) and says in str(err.value), str(err.value)
