"""Which replay chunks a SAC / TD3 run keeps on disk (issue #49, item 3): every chunk a checkpoint
still on disk names, so that a resume falling back to an older checkpoint (the newer ones corrupt)
finds its rows after the ring has wrapped; a resume from another run's checkpoint links that run's
chunks and never deletes them; a checkpoint copied without its chunks is one line, exit 2.

The ring holds 50 transitions, a checkpoint comes every 40 env steps (2 envs x 1 step per
iteration: one chunk per checkpoint, [S-40, S)) and ``trainer.keep_last=3``. The checkpoint at step
S holds rows [S-50, S): the chunks [S-80, S-40) and [S-40, S). At the end (steps 520, 560, 600
kept) the chunks on disk must be exactly the ones these three name: [440, 480), [480, 520),
[520, 560), [560, 600). Keeping only the newest checkpoint's chunks, as before, left [520, 560) and
[560, 600): a resume that fell back to 520 found [440, 480) gone.
"""

from __future__ import annotations

import os
import re
import shutil
from itertools import pairwise
from pathlib import Path

import pytest
import torch
from test_resume import _kill_after_checkpoint, _same

from conftest import run_train
from rlexp.checkpoints.files import latest_checkpoint, load_checkpoint, step_checkpoints

TOTAL, EVERY, RING = 600, 40, 50
#: The chunks the kept checkpoints (520, 560, 600) name, worked out by hand (docstring).
KEPT = [(440, 480), (480, 520), (520, 560), (560, 600)]


def _args(run_dir: Path, *extra: str) -> list[str]:
    return [
        "algorithm=sac",
        "env=inverted_pendulum",
        "env.max_episode_steps=8",
        "env.num_envs=2",
        f"trainer.total_frames={TOTAL}",
        f"trainer.save_every={EVERY}",
        "trainer.keep_last=3",
        "trainer.eval_every=0",
        f"algorithm.buffer_size={RING}",
        "algorithm.learning_starts=100",
        "algorithm.batch_size=32",
        "algorithm.updates_per_step=0.5",
        "policy.actor.hidden_sizes=[32,32]",
        "policy.critic.hidden_sizes=[32,32]",
        "logger=none",
        f"hydra.run.dir={run_dir}",
        "seed=3",
        *extra,
    ]


def _chunks(run_dir: Path) -> list[tuple[int, int]]:
    """The row ranges of the chunk files in the run's replay folder."""
    names = [p.name for p in (run_dir / "replay").glob("chunk-*.pt")]
    return sorted(
        (int(m[1]), int(m[2])) for m in map(re.compile(r"chunk-(\d+)-(\d+)-").match, names)
    )


def _assert_same_end(a_dir: Path, b_dir: Path) -> None:
    """The two runs' final checkpoints hold the same networks, optimisers, buffer and RNGs."""
    a = load_checkpoint(latest_checkpoint(a_dir / "checkpoints"))
    b = load_checkpoint(latest_checkpoint(b_dir / "checkpoints"))
    assert a["global_step"] == b["global_step"] == TOTAL
    for key, value in a["policy"].items():
        assert torch.equal(value, b["policy"][key]), f"policy.{key} differs after resume"
    sa, sb = a["algorithm"], b["algorithm"]
    assert sa["gradient_steps"] == sb["gradient_steps"]
    for key, value in sa["loss"].items():
        assert torch.equal(value, sb["loss"][key]), f"loss.{key} differs after resume"
    assert _same(sa["optimizers"], sb["optimizers"]), "optimiser state differs after resume"
    assert sa["replay"]["written"] == sb["replay"]["written"] == TOTAL
    assert _same(sa["replay"]["generator"], sb["replay"]["generator"])
    assert _same(a["rng"], b["rng"])


@pytest.fixture(scope="module")
def whole(tmp_path_factory) -> Path:
    """The uninterrupted run."""
    root = tmp_path_factory.mktemp("keep")
    run_train(_args(root / "whole"), cwd=root, timeout=600)
    return root / "whole"


def test_the_chunks_on_disk_are_those_the_kept_checkpoints_name(whole):
    steps = [int(p.stem.rsplit("_", 1)[1]) for p in step_checkpoints(whole / "checkpoints")]
    assert steps == [520, 560, 600]
    assert _chunks(whole) == KEPT
    named = set()
    for path in step_checkpoints(whole / "checkpoints"):
        named |= {c["file"] for c in load_checkpoint(path)["algorithm"]["replay"]["chunks"]}
    assert named == {p.name for p in (whole / "replay").glob("chunk-*.pt")}


def test_the_keeper_reads_the_checkpoints_names_and_a_corrupt_one_names_none(tmp_path, whole):
    from rlexp.algorithms.replay_keep import ChunkKeeper

    ckpts = tmp_path / "checkpoints"
    shutil.copytree(whole / "checkpoints", ckpts)
    paths = step_checkpoints(ckpts)
    named = [
        {c["file"] for c in load_checkpoint(p)["algorithm"]["replay"]["chunks"]} for p in paths
    ]
    keeper = ChunkKeeper()
    assert keeper.named(ckpts) == set().union(*named)  # read from the files
    paths[-1].write_bytes(paths[-1].read_bytes()[:1000])  # truncated: no resume can use it
    assert keeper.named(ckpts) == named[0] | named[1]
    (ckpts / "best.pt").symlink_to(paths[-1].name)  # whatever the file, by its content
    assert keeper.named(ckpts) == named[0] | named[1]


def test_a_resume_past_a_corrupt_newest_checkpoint_finds_the_older_one_s_chunks(tmp_path, whole):
    broken = tmp_path / "broken"
    ckpts = broken / "checkpoints"
    _kill_after_checkpoint(_args(broken), tmp_path, ckpts, 400)
    kept = step_checkpoints(ckpts)  # 4 when the kill came between a write and the pruning
    assert len(kept) in (3, 4) and int(kept[-1].stem.rsplit("_", 1)[1]) >= 400
    with open(kept[-1], "r+b") as f:  # half a file: a write the kill cut short
        f.truncate(kept[-1].stat().st_size // 2)
    kept[-2].write_bytes(b"")  # and an empty one: the resume falls back two checkpoints, to one
    # whose oldest chunk only it names (the newest's commit may not have run before the kill)
    proc = run_train(_args(broken), cwd=tmp_path, timeout=600)
    out = proc.stdout + proc.stderr
    assert out.count("falling back to the previous checkpoint") == 2
    assert f"[resume] continuing from {kept[-3]}" in out
    assert {p.name for p in (ckpts / "corrupt").iterdir()} == {kept[-1].name, kept[-2].name}
    _assert_same_end(whole, broken)  # the same end as the run that was never stopped
    assert _chunks(broken) == KEPT  # the dead timeline's chunks went at the first commit


def test_a_resume_from_another_run_s_checkpoint_links_its_chunks_and_leaves_them(tmp_path, whole):
    before = {p.name: p.stat().st_mtime_ns for p in (whole / "replay").glob("chunk-*.pt")}
    source = whole / "checkpoints" / latest_checkpoint(whole / "checkpoints").name
    at_560 = source.with_name(source.name.replace("600", "560"))
    mine = tmp_path / "mine"
    run_train(_args(mine, f"trainer.resume={at_560}"), cwd=tmp_path, timeout=600)
    _assert_same_end(whole, mine)
    after = {p.name: p.stat().st_mtime_ns for p in (whole / "replay").glob("chunk-*.pt")}
    assert after == before  # the other run's chunks: none deleted, none rewritten
    assert _chunks(mine) == [(520, 560), (560, 600)]  # what its one checkpoint (600) names


def test_a_checkpoint_copied_without_its_chunks_is_one_line_exit_2(tmp_path, whole):
    alone = tmp_path / "elsewhere" / "ckpt_step_000000560.pt"
    alone.parent.mkdir()
    shutil.copy(next(p for p in step_checkpoints(whole / "checkpoints") if "560" in p.name), alone)
    proc = run_train(_args(tmp_path / "run", f"trainer.resume={alone}"), cwd=tmp_path, check=False)
    assert proc.returncode == 2, proc.stderr[-2000:]
    out = proc.stdout + proc.stderr
    assert "Traceback" not in out
    line = next(x for x in out.splitlines() if "replay buffer's chunk" in x)
    assert "trainer.resume=" in line and "chunk-000000000480-000000000520-" in line
    assert os.path.isdir(whole / "replay")


# -- item 2: an eval round's snapshot writes no chunk ---------------------------------------------

EVAL_RUN = [
    "algorithm=sac",
    "env=inverted_pendulum",
    "env.max_episode_steps=8",
    "env.num_envs=2",
    "trainer.total_frames=240",
    "trainer.eval_every=40",  # six rounds; those of 120 and 240 have a checkpoint waiting for them
    "trainer.eval_episodes=2",
    "trainer.save_every=120",
    "trainer.keep_last=0",
    "algorithm.buffer_size=50",
    "algorithm.learning_starts=60",
    "algorithm.batch_size=32",
    "algorithm.updates_per_step=0.5",
    "policy.actor.hidden_sizes=[32,32]",
    "policy.critic.hidden_sizes=[32,32]",
    "logger=none",
    "logger.jsonl=true",
    "trainer.progress=false",
    "seed=5",
]


def _train_in_process(run_dir: Path, *extra: str) -> None:
    from conftest import compose
    from rlexp.app import train
    from rlexp.config.validate import to_root_config

    threads = torch.get_num_threads()
    try:
        train(to_root_config(compose([*EVAL_RUN, *extra])), run_dir)
    finally:
        torch.set_num_threads(threads)


def _eval_rows(run_dir: Path) -> list[dict]:
    import json

    rows = [json.loads(x) for x in (run_dir / "metrics.jsonl").read_text().splitlines()]
    return [
        {k: v for k, v in r.items() if k == "step" or k.startswith("eval/")}
        for r in rows
        if "eval/episode_return" in r
    ]


def _assert_same_checkpoint(a_path: Path, b_path: Path) -> None:
    """The same state, the buffer's rows included (its chunk files may be cut differently)."""
    from rlexp.algorithms.replay import Replay

    a, b = load_checkpoint(a_path), load_checkpoint(b_path)
    assert a["global_step"] == b["global_step"]
    for key, value in a["policy"].items():
        assert torch.equal(value, b["policy"][key]), f"{a_path.name}: policy.{key} differs"
    sa, sb = a["algorithm"], b["algorithm"]
    for key, value in sa["loss"].items():
        assert torch.equal(value, sb["loss"][key]), f"{a_path.name}: loss.{key} differs"
    assert _same(sa["optimizers"], sb["optimizers"]) and _same(a["rng"], b["rng"])
    samples = []
    for path, state in ((a_path, sa), (b_path, sb)):
        replay = Replay(50, directory=path.parent.parent / "replay")
        replay.load_state_dict(state["replay"])  # every chunk it names is there and whole
        samples.append((len(replay), replay.written, replay.sample(2000)))
    (na, wa, xa), (nb, wb, xb) = samples
    assert (na, wa) == (nb, wb) and (xa == xb).all(), f"{a_path.name}: buffer rows differ"


@pytest.fixture(scope="module")
def sync_run(tmp_path_factory) -> Path:
    """The reference: every round evaluated in-process, state_dict saved for best.pt."""
    run_dir = tmp_path_factory.mktemp("sync") / "sync"
    _train_in_process(run_dir, "trainer.eval_async=false")
    return run_dir


def _assert_same_files(sync_dir: Path, async_dir: Path) -> None:
    assert _eval_rows(async_dir) == _eval_rows(sync_dir)
    names = [p.name for p in step_checkpoints(sync_dir / "checkpoints")]
    assert names == [p.name for p in step_checkpoints(async_dir / "checkpoints")]
    for name in ("best.pt", *names):
        _assert_same_checkpoint(sync_dir / "checkpoints" / name, async_dir / "checkpoints" / name)


def test_eval_snapshots_write_no_chunk_and_the_run_ends_the_same(sync_run, tmp_path, monkeypatch):
    from rlexp.algorithms import replay_files
    from rlexp.training.trainer import Trainer

    writes: list[tuple[int, int, bool]] = []  # rows, and whether an eval's snapshot wrote them
    in_snapshot = [False]
    real_write, real_evaluate = replay_files.write_chunk, Trainer.evaluate

    def write_chunk(directory, rows, start):
        entry = real_write(directory, rows, start)
        writes.append((entry["start"], entry["stop"], in_snapshot[0]))
        return entry

    def evaluate(self):
        self._collect_eval()  # evaluate's own first step: the last round's result (its best.pt)
        in_snapshot[0] = True
        try:
            real_evaluate(self)  # the snapshot, handed to the worker
        finally:
            in_snapshot[0] = False

    monkeypatch.setattr(replay_files, "write_chunk", write_chunk)
    monkeypatch.setattr(Trainer, "evaluate", evaluate)
    _train_in_process(tmp_path / "async", "trainer.eval_async=true")

    assert [w for w in writes if w[2]] == [], "an eval's snapshot wrote replay chunks"
    assert all(b[0] >= a[1] for a, b in pairwise(writes)), f"a row written twice: {writes}"
    rows = _eval_rows(sync_run)
    assert [r["step"] for r in rows] == [40, 80, 120, 160, 200, 240]
    _assert_same_files(sync_run, tmp_path / "async")
    # Chunks are written for what goes to disk only: best.pt (a round better than all before)
    # and the checkpoints of 120 and 240; an eval round that is neither writes nothing.
    best, bests = -float("inf"), set()
    for r in rows:
        if r["eval/episode_return"] > best:
            best = r["eval/episode_return"]
            bests.add(r["step"])
    assert len(bests) < len(rows), "every round a new best: vacuous"
    assert [w[1] for w in writes] == sorted(bests | {120, 240})


def test_a_round_in_flight_at_a_stop_holds_its_rows_and_resumes_the_same(
    sync_run, tmp_path, monkeypatch
):
    """A stop while the round of step 120 is out (its checkpoint waits for it): the stop's
    checkpoint holds that round's state, its replay rows written then; the resume evaluates it,
    writes its best.pt and checkpoint from it, and ends as the run that never stopped."""
    from rlexp.app import RunEnded
    from rlexp.training.trainer import Trainer

    real_evaluate = Trainer.evaluate

    def evaluate_then_stop(self):
        real_evaluate(self)
        if self.global_step == 120:
            self.request_stop("stop injected by the test")

    monkeypatch.setattr(Trainer, "evaluate", evaluate_then_stop)
    run_dir = tmp_path / "async"
    with pytest.raises(RunEnded):
        _train_in_process(run_dir, "trainer.eval_async=true")
    stopped = load_checkpoint(run_dir / "checkpoints" / "InvertedPendulum-v5_sac_step_000000120.pt")
    pending = stopped["eval_in_flight"]
    assert pending["step"] == 120 and pending["save"]
    assert "unsaved" not in pending["state"]["algorithm"]["replay"]
    monkeypatch.setattr(Trainer, "evaluate", real_evaluate)
    _train_in_process(run_dir, "trainer.eval_async=true")
    _assert_same_files(sync_run, run_dir)


def test_a_corrupt_chunk_found_at_resume_is_one_line_exit_2(tmp_path, whole):
    other = tmp_path / "other"
    shutil.copytree(whole, other)
    at_560 = next(p for p in step_checkpoints(other / "checkpoints") if "560" in p.name)
    chunk = next((other / "replay").glob("chunk-000000000520-000000000560-*.pt"))
    chunk.write_bytes(chunk.read_bytes()[:300])  # there, but cut short
    proc = run_train(_args(tmp_path / "run", f"trainer.resume={at_560}"), cwd=tmp_path, check=False)
    assert proc.returncode == 2, proc.stderr[-2000:]
    out = proc.stdout + proc.stderr
    assert "Traceback" not in out
    line = next(x for x in out.splitlines() if "config error" in x and chunk.name in x)
    assert "unreadable" in line and f"move {at_560} aside" in line
