"""The replay buffer's checkpoint cost (issue #49, item 3): time and bytes of a save, at buffer sizes
that matter, for HalfCheetah's transitions (observation 17, action 6, float32; reward, three flags).

For each size: fill the buffer with ``size`` transitions, then

- ``first save``: the first checkpoint of a full buffer (every row is new: one chunk of all rows);
- ``incremental``: ``--new`` more transitions, then the next save (one chunk of those rows only)
  and its ``commit`` (with the ring full, the chunk whose rows were overwritten is deleted);
- ``load``: a fresh buffer rebuilt from the manifest and its chunks;
- ``full rewrite``: what a design that rewrites the whole buffer per checkpoint costs every time
  (``torch.save`` of all rows, atomically), for comparison.

Time is the median of ``--repeats``; bytes are what each save adds to the disk. The chunk files go
to ``--dir`` (a temporary folder by default; use a folder on the disk your runs write to).

    python benchmarks/replay_checkpoint.py --sizes 100000 1000000 --new 1000
"""

from __future__ import annotations

import argparse
import io
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch
from tensordict import TensorDict

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

from rlexp.algorithms.replay import Replay  # noqa: E402
from rlexp.files.fsutil import atomic_write  # noqa: E402

OBS, ACT = 17, 6


def transitions(count: int, gen: torch.Generator) -> TensorDict:
    """``count`` HalfCheetah-shaped transitions, flat."""
    return TensorDict(
        {
            "observation": torch.randn(count, OBS, generator=gen),
            "action": torch.rand(count, ACT, generator=gen) * 2 - 1,
            "next": {
                "observation": torch.randn(count, OBS, generator=gen),
                "reward": torch.randn(count, 1, generator=gen),
                "terminated": torch.zeros(count, 1, dtype=torch.bool),
                "truncated": torch.rand(count, 1, generator=gen) < 1e-3,
            },
        },
        [count],
    )


def chunk_bytes(directory: Path) -> int:
    return sum(p.stat().st_size for p in directory.glob("chunk-*.pt"))


def timed(fn, repeats: int) -> tuple[float, object]:
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def measure(size: int, new: int, repeats: int, storage: str, root: Path) -> dict[str, float]:
    gen = torch.Generator().manual_seed(0)
    directory = root / f"{storage}-{size}"
    replay = Replay(size, storage=storage, directory=directory, seed=0)
    for start in range(0, size, 100_000):
        replay.extend(transitions(min(100_000, size - start), gen))

    t0 = time.perf_counter()
    replay.save("first")
    replay.commit()
    first_s = time.perf_counter() - t0
    first_bytes = chunk_bytes(directory)

    inc, inc_bytes = [], []
    state = None
    for i in range(repeats):
        replay.extend(transitions(new, gen))
        before = chunk_bytes(directory)
        t0 = time.perf_counter()
        state = replay.save(f"inc{i}")
        inc.append(time.perf_counter() - t0)
        inc_bytes.append(chunk_bytes(directory) - before)
        replay.commit()

    def load() -> Replay:
        fresh = Replay(size, storage=storage, directory=directory, seed=1)
        fresh.load_state_dict(state)
        return fresh

    load_s, _ = timed(load, 1)
    buf = io.BytesIO()
    torch.save(state, buf)  # what the manifest adds to the checkpoint file
    manifest = len(buf.getvalue())

    rows = replay._rb.storage.get(torch.arange(size)).to_dict()
    target = directory / "full_rewrite.pt"

    def rewrite() -> None:
        atomic_write(target, lambda tmp: torch.save(rows, tmp))

    rewrite_s, _ = timed(rewrite, 1)
    rewrite_bytes = target.stat().st_size
    target.unlink()
    return {
        "first_s": first_s,
        "first_mb": first_bytes / 1e6,
        "inc_s": statistics.median(inc),
        "inc_kb": statistics.median(inc_bytes) / 1e3,
        "commit_files": len(list(directory.glob("chunk-*.pt"))),
        "load_s": load_s,
        "rewrite_s": rewrite_s,
        "rewrite_mb": rewrite_bytes / 1e6,
        "manifest_kb": manifest / 1e3,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[100_000, 1_000_000])
    parser.add_argument(
        "--new", type=int, default=1000, help="rows added before each incremental save"
    )
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--storage", nargs="+", default=["memory", "memmap"])
    parser.add_argument("--dir", type=Path, default=None)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory(dir=args.dir) as tmp:
        print(
            f"| storage | transitions | first save | incremental save (+{args.new} rows) "
            "| chunk files | load | full rewrite (for comparison) |"
        )
        print("|---|---:|---:|---:|---:|---:|---:|")
        for storage in args.storage:
            for size in args.sizes:
                r = measure(size, args.new, args.repeats, storage, Path(tmp))
                print(
                    f"| {storage} | {size:,} | {r['first_s']:.2f} s, {r['first_mb']:.1f} MB "
                    f"| {r['inc_s'] * 1e3:.1f} ms, {r['inc_kb']:.0f} kB "
                    f"(manifest {r['manifest_kb']:.1f} kB) | {r['commit_files']} "
                    f"| {r['load_s']:.2f} s | {r['rewrite_s']:.2f} s, {r['rewrite_mb']:.1f} MB |",
                    flush=True,
                )
    return 0


if __name__ == "__main__":
    sys.exit(main())
