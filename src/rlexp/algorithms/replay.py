"""The replay buffer of the off-policy learners (SAC, TD3): TorchRL's ``ReplayBuffer`` on a
``LazyTensorStorage`` (memory) or ``LazyMemmapStorage`` (memory-mapped files in the run dir),
sampled uniformly from the buffer's own ``torch.Generator``, checkpointed incrementally.

Transitions are ``observation``, ``action``, ``("next", "observation" | "reward" | "terminated" |
"truncated" | "done")`` (+ ``steps_to_next_obs`` with ``n_step > 1``, see ``nstep.py``); both flags
are kept: targets bootstrap through a truncation, never through a termination.

Checkpoints (docs/replay.md): ``save(tag)`` writes only the rows added since the previous save, as
one new chunk file (``replay_files.py``), and returns a small manifest (counters, generator state,
the chunk list) that goes into the checkpoint. Once that checkpoint is on disk, ``commit(named=...)``
deletes the chunks that no checkpoint still on disk names (``replay_keep.py`` reads which); a crash
before the commit leaves every chunk an existing checkpoint names. ``snapshot`` is a save without
the write, for an eval round's copy of the state: ``settle`` writes its rows if that copy ever goes
into a checkpoint (best.pt). ``load_state_dict`` rebuilds the storage from the chunks: the same rows
at the same ring positions, the same generator, so the next samples are the uninterrupted run's.
"""

from __future__ import annotations

import logging
import os
import secrets
import shutil
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import LazyMemmapStorage, LazyTensorStorage, RandomSampler, ReplayBuffer

from rlexp.algorithms import nstep, replay_files
from rlexp.algorithms.replay_files import CHUNK_NAME, MANIFEST_FORMAT, ReplayFileError

log = logging.getLogger(__name__)

#: ``algorithm.buffer_storage`` choices.
STORAGES = ("memory", "memmap", "auto")
#: ``auto`` memory-maps a buffer whose full size would take more than this share of the RAM.
AUTO_MEMMAP_SHARE = 0.25
#: What a stored transition holds (``("next", "done")`` is added when the batch has none).
TRANSITION_KEYS = (
    "observation",
    "action",
    ("next", "observation"),
    ("next", "reward"),
    ("next", "terminated"),
    ("next", "truncated"),
    ("next", "done"),
)


def _nested(columns: dict[tuple[str, ...], Any], shape: torch.Size) -> TensorDict:
    """A TensorDict of ``columns`` (keys as tuples), built without per-entry checks."""
    top: dict[str, Any] = {}
    for key, value in columns.items():
        node = top
        for part in key[:-1]:
            node = node.setdefault(part, {})
        node[key[-1]] = value

    def build(tree: dict[str, Any]) -> TensorDict:
        items = {k: build(v) if isinstance(v, dict) else v for k, v in tree.items()}
        return TensorDict._new_unsafe(items, batch_size=shape)

    return build(top)


def physical_memory() -> int:
    """This machine's RAM in bytes (0 where the OS does not say)."""
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return 0


class Replay:
    """A ring of ``capacity`` transitions; ``directory`` holds its chunk files (and, memory-mapped,
    its storage); ``seed`` seeds the sampling generator; ``n_step``/``gamma``: n-step returns."""

    def __init__(
        self,
        capacity: int,
        storage: str = "memory",
        directory: str | Path | None = None,
        device: str | torch.device = "cpu",
        seed: int = 0,
        *,
        n_step: int = 1,
        gamma: float = 0.99,
    ) -> None:
        if not isinstance(capacity, int) or isinstance(capacity, bool) or capacity < 1:
            raise ValueError(f"algorithm.buffer_size={capacity!r}; expected an int >= 1")
        if storage not in STORAGES:
            raise ValueError(f"algorithm.buffer_storage={storage!r}; choose from {list(STORAGES)}")
        if storage == "memmap" and directory is None:
            raise ValueError(
                "algorithm.buffer_storage=memmap needs a directory for its files (the run dir's)"
            )
        if not isinstance(n_step, int) or isinstance(n_step, bool) or n_step < 1:
            raise ValueError(f"algorithm.n_step={n_step!r}; expected an int >= 1")
        if not 0.0 <= gamma <= 1.0:
            raise ValueError(f"algorithm.gamma={gamma!r}; expected a number in [0, 1]")
        self.capacity = capacity
        self.storage = storage
        self.directory = Path(directory) if directory is not None else None
        self.device = torch.device(device)
        self.n_step, self.gamma = n_step, float(gamma)
        self.generator = torch.Generator()
        self.generator.manual_seed(seed)
        #: transitions ever added; the n-th sits at ring position ``n % capacity``
        self.written = 0
        self.layout: replay_files.Layout | None = None
        self.storage_kind: str | None = None  # memory or memmap, once decided
        self._rb: ReplayBuffer | None = None
        self._leaves: list[tuple[tuple[str, ...], torch.Tensor]] = []  # the storage's tensors
        self._pending: nstep.NStepState | None = None
        self._chunks: list[dict[str, Any]] = []  # the chunks the rows up to _saved_upto are in
        self._saved_upto = 0
        self._saved: dict[str, list[str]] = {}  # tag -> chunk names, for saves not yet released
        self._last_tag: str | None = None
        #: the newest ``snapshot`` not yet settled or given up: its id, rows, chunks (``_Snap``)
        self._snap: dict[str, Any] | None = None

    # ----- filling and sampling ------------------------------------------------------------------

    def __len__(self) -> int:
        return min(self.written, self.capacity)

    def extend(self, batch: TensorDictBase) -> None:
        """Add a rollout: ``[num_envs, T]`` (each env's steps in time order) or, with
        ``n_step=1``, any batch shape (flattened)."""
        rows = self._transitions(batch)
        count = rows.batch_size[0]
        if count == 0:
            return
        if count > self.capacity:  # only the last capacity rows survive: write them where they go
            rows = rows[count - self.capacity :]
        start = self.written + count - rows.batch_size[0]
        snap, end = self._snap, start + rows.batch_size[0]
        if snap is not None and snap["extends"] > 0:
            self._snap = None  # its round was taken in after the last update: kept or dropped
        elif snap is not None:
            snap["extends"] = 1
            if snap["done"] is None and end > snap["start"] + self.capacity:
                self._settle_snap(snap)  # the ring would overwrite rows it may still need
        if self._rb is None:  # TorchRL allocates the storage from the first rows
            self._build(rows)
            self._set_cursor(start)
            self._rb.extend(rows)
            self._leaves = self._storage_leaves()
        else:
            self._write(rows, start)
        self.written += count

    def _write(self, rows: TensorDictBase, start: int) -> None:
        """Write ``rows`` at ring positions ``start % capacity, ...`` straight into the TorchRL
        storage's tensors (where its RoundRobinWriter puts them, without its per-call overhead:
        SAC adds a few rows per gradient step)."""
        count, at = rows.batch_size[0], start % self.capacity
        first = min(count, self.capacity - at)
        for key, dst in self._leaves:
            src = rows.get(key)
            if src.dtype != dst.dtype or src.shape[1:] != dst.shape[1:]:
                self._check_layout(rows)  # raises, naming both layouts
            dst[at : at + first] = src[:first]
            if first < count:  # wraps round
                dst[: count - first] = src[first:]
        store = self._rb.storage
        store._len = min(start + count, self.capacity)
        self._set_cursor(start + count)

    def _storage_leaves(self) -> list[tuple[tuple[str, ...], torch.Tensor]]:
        """The storage's tensors by key (memory-mapped ones as plain tensor views of the map)."""
        stored = self._rb.storage._storage
        leaves = []
        for key in stored.keys(include_nested=True, leaves_only=True):
            value = stored.get(key)
            leaves.append(
                ((key,) if isinstance(key, str) else tuple(key), value.as_subclass(torch.Tensor))
            )
        return sorted(leaves, key=lambda kv: kv[0])

    def sample(self, batch_size: int) -> TensorDictBase:
        """``batch_size`` transitions drawn uniformly (with replacement) from the valid rows, by
        the buffer's own generator, as TorchRL's ``RandomSampler`` draws them."""
        size = len(self)
        if size == 0:
            raise ValueError("the replay buffer is empty: nothing to sample (learning_starts=0?)")
        index = torch.randint(0, size, (batch_size,), generator=self.generator)
        if self._leaves[0][1].device != index.device:
            index = index.to(self._leaves[0][1].device)
        out: dict[str, Any] = {}
        nxt: dict[str, torch.Tensor] = {}
        for key, leaf in self._leaves:
            value = leaf[index]
            if value.device != self.device:  # memory-mapped storage feeding an accelerator
                value = value.to(self.device, non_blocking=True)
            if len(key) == 1:
                out[key[0]] = value
            elif len(key) == 2 and key[0] == "next":
                nxt[key[1]] = value
            else:  # an observation that is itself a TensorDict: the general path
                return self._gather(index).to(self.device)
        shape = torch.Size([batch_size])
        out["next"] = TensorDict._new_unsafe(nxt, batch_size=shape, device=self.device)
        return TensorDict._new_unsafe(out, batch_size=shape, device=self.device)

    def _gather(self, index: torch.Tensor) -> TensorDict:
        """The rows at ring positions ``index``, on the CPU (the storage may be on an accelerator)."""
        index = index.to(self._device())
        rows = {key: leaf[index].cpu() for key, leaf in self._leaves}
        return _nested(rows, torch.Size([index.numel()]))

    def _device(self) -> torch.device:
        """Where the storage's tensors are: ``device``, or the CPU for memory-mapped ones."""
        return torch.device("cpu") if self.storage_kind == "memmap" else self.device

    def _transitions(self, batch: TensorDictBase) -> TensorDictBase:
        """The rollout's transition entries; n-step windows applied; flat ``[N]``."""
        dims = batch.batch_dims
        columns: dict[tuple[str, ...], torch.Tensor] = {}
        for key in TRANSITION_KEYS:
            value = batch.get(key, None)
            if value is None and key == ("next", "done"):
                value = columns[("next", "terminated")] | columns[("next", "truncated")]
            if value is None:
                missing = [k for k in TRANSITION_KEYS[:-1] if batch.get(k, None) is None]
                raise KeyError(f"a replay transition needs {missing}; the batch has none")
            columns[(key,) if isinstance(key, str) else key] = value
        if self.n_step == 1:
            flat = torch.Size([batch.batch_size.numel()])
            return _nested({k: v.reshape(*flat, *v.shape[dims:]) for k, v in columns.items()}, flat)
        if dims != 2:
            raise ValueError(
                f"algorithm.n_step={self.n_step} needs the rollout as [num_envs, T]; got "
                f"{tuple(batch.batch_size)}"
            )
        rows = _nested(columns, batch.batch_size)
        out, self._pending = nstep.nstep_transitions(rows, self._pending, self.n_step, self.gamma)
        return out

    def _build(self, rows: TensorDictBase) -> None:
        """The TorchRL buffer, its storage chosen now that a row's size is known."""
        self.layout = replay_files.layout_of(rows)
        need = self.capacity * replay_files.row_bytes(self.layout)
        kind = self.storage
        if kind == "auto":
            big = need > AUTO_MEMMAP_SHARE * physical_memory()
            kind = "memmap" if big and self.directory is not None else "memory"
        if kind == "memmap":
            scratch = self.directory / "memmap"
            shutil.rmtree(scratch, ignore_errors=True)  # a dead run's storage: never a checkpoint
            scratch.mkdir(parents=True, exist_ok=True)
            free = shutil.disk_usage(scratch).free
            if need > free:
                raise ValueError(
                    f"algorithm.buffer_size={self.capacity} x {need // self.capacity} bytes per "
                    f"transition = {need / 1e9:.1f} GB; {scratch} has {free / 1e9:.1f} GB free: "
                    "a smaller buffer_size, or a run dir on a larger disk"
                )
            store = LazyMemmapStorage(self.capacity, scratch_dir=scratch, existsok=True)
        else:
            ram = physical_memory()
            if self.device.type == "cpu" and ram and need > ram:
                raise ValueError(
                    f"algorithm.buffer_size={self.capacity} x {need // self.capacity} bytes per "
                    f"transition = {need / 1e9:.1f} GB, more than this machine's {ram / 1e9:.1f} GB "
                    "of RAM: algorithm.buffer_storage=memmap (or auto), or a smaller buffer_size"
                )
            store = LazyTensorStorage(self.capacity, device=self.device)
        self.storage_kind = kind
        self._rb = ReplayBuffer(
            storage=store, sampler=RandomSampler(), batch_size=None, generator=self.generator
        )
        log.info(
            "replay buffer: %d transitions in %s (%s; %.1f MB when full)",
            self.capacity,
            kind,
            replay_files.layout_text(self.layout),
            self.capacity * replay_files.row_bytes(self.layout) / 1e6,
        )

    def _check_layout(self, rows: TensorDictBase) -> None:
        layout = replay_files.layout_of(rows)
        if layout != self.layout:
            raise ValueError(
                f"these transitions ({replay_files.layout_text(layout)}) do not fit the replay "
                f"buffer's ({replay_files.layout_text(self.layout)})"
            )

    def _set_cursor(self, written: int) -> None:
        self._rb._writer.load_state_dict(
            {"_cursor": written % self.capacity, "_write_count": written}
        )

    # ----- checkpoints ---------------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        """``save()``: a manifest is only ever one whose rows are on disk."""
        return self.save()

    def save(self, tag: str | None = None) -> dict[str, Any]:
        """Write the rows added since the last save as one new chunk file; the small manifest for
        the checkpoint ``tag`` names (its file name, say; default ``save-<written>``). Deletes
        nothing: see ``commit``."""
        tag = f"save-{self.written}" if tag is None else tag
        snap = self._snap
        if snap is not None and snap["done"] is None and snap["written"] != self.written:
            self._snap = snap = None  # rows were added since: that round's copy was not kept
        first = self.written - len(self)
        start = max(self._saved_upto, first)
        if start < self.written:
            entry = self._write_rows(start, self.written)
            if snap is not None and snap["done"] is None:  # its rows are exactly this chunk's
                snap["done"] = [*snap["chunks"], entry]
        self._chunks = [c for c in self._chunks if c["stop"] > first]
        self._saved.pop(tag, None)  # in save order: a tag saved again is the newest
        self._saved[tag] = [c["file"] for c in self._chunks]
        self._last_tag = tag
        return self._manifest(self._chunks)

    def snapshot(self) -> dict[str, Any]:
        """The manifest ``save`` would return, without writing anything: an eval round's copy of
        the state, which becomes a checkpoint only if its round is the best (best.pt) or a due
        checkpoint waits for it. ``settle`` makes it a real manifest until the second ``extend``
        after it, the next ``save`` of later rows or the next ``snapshot`` (the trainer takes a
        round in after one update; rows that update overwrites are written first)."""
        first = self.written - len(self)
        start = max(self._saved_upto, first)
        chunks = [dict(c) for c in self._chunks if c["stop"] > first]
        done = chunks if start >= self.written else None
        snap = {"id": secrets.token_hex(8), "written": self.written, "start": start}
        self._snap = {**snap, "chunks": chunks, "done": done, "extends": 0}
        return {**self._manifest(chunks), "unsaved": snap}

    def settle(self, manifest: dict[str, Any]) -> dict[str, Any]:
        """``manifest`` ready for a checkpoint file: a ``snapshot``'s with the rows it still lacks
        written as a chunk (nothing else changes); any other as it is, chunks another run's
        directory holds linked into this one (``replay_files.adopt_chunks``)."""
        unsaved = manifest.get("unsaved")
        if unsaved is None:
            return self._adopted(manifest)
        snap = self._snap
        if snap is None or snap["id"] != unsaved.get("id"):
            raise RuntimeError(
                f"the replay buffer's snapshot at {unsaved.get('written')} transitions can no "
                "longer be written: the buffer was saved or snapshot again since"
            )
        if snap["done"] is None:
            self._settle_snap(snap)
        out = {k: v for k, v in manifest.items() if k != "unsaved"}
        out["chunks"] = [dict(c) for c in snap["done"]]
        return out

    def _settle_snap(self, snap: dict[str, Any]) -> None:
        """Write the rows ``snap`` lacks, ``[start, written)``, still in the ring, as the next chunk."""
        if self._saved_upto > snap["start"]:  # cannot happen: save() settles or drops it
            raise RuntimeError("the replay buffer was saved past a snapshot it did not settle")
        snap["done"] = [*snap["chunks"], self._write_rows(snap["start"], snap["written"])]

    def _write_rows(self, start: int, stop: int) -> dict[str, Any]:
        """Rows ``[start, stop)`` (in the ring) as the next chunk of the buffer's own sequence."""
        if self.directory is None:
            raise ValueError("saving a replay buffer needs its directory (Replay(directory=...))")
        rows = self._gather(torch.arange(start, stop) % self.capacity)
        entry = replay_files.write_chunk(self.directory, rows, start)
        self._chunks.append(entry)
        self._saved_upto = stop
        return entry

    def _manifest(self, chunks: list[dict[str, Any]]) -> dict[str, Any]:
        return {
            "format": MANIFEST_FORMAT,
            "capacity": self.capacity,
            "written": self.written,
            "n_step": self.n_step,
            "gamma": self.gamma,
            "storage": self.storage_kind,
            "generator": self.generator.get_state(),
            "layout": [[list(k), d, list(s)] for k, d, s in self._layout_to_save()],
            "chunks": [dict(c) for c in chunks],
            "saved": {t: list(names) for t, names in self._saved.items()},
            "pending": nstep.nstep_state_dict(self._pending),
        }

    def _adopted(self, manifest: dict[str, Any]) -> dict[str, Any]:
        """``manifest`` whose chunks are in this buffer's directory: those of another run's
        (``directory``, set by the resume's loader) hard-linked or copied here first."""
        source = manifest.get("directory")
        if source is None:
            return manifest
        out = {k: v for k, v in manifest.items() if k != "directory"}
        names = replay_files.chunk_names(out)
        if names and self.directory is not None:
            replay_files.adopt_chunks(Path(source), self.directory, names)
        return out

    def _layout_to_save(self) -> replay_files.Layout:
        """The storage's layout; before its first row, the one the waiting n-step steps give."""
        if self.layout is not None or self._pending is None:
            return self.layout or []
        steps = replay_files.layout_of(self._pending.steps)
        return sorted([*steps, ((nstep.STEPS_KEY,), str(torch.int64), (1,))])

    def commit(
        self, keep: Iterable[str] | int | None = None, *, named: Iterable[str] = ()
    ) -> list[str]:
        """Call once the checkpoint holding the last save's manifest is on disk (and old ones
        pruned): forget the saves not kept and delete the chunk files nothing needs: no kept save,
        not ``named`` (the chunks the checkpoints still on disk name: ``replay_keep.py``), not
        the buffer's own rows, not a snapshot that may still be settled. ``keep``: the tags of
        the saves to keep (the last save is always kept); an int ``n``: the last ``n`` saves
        (``<= 0``: all); ``None``: the last save only. The deleted names."""
        tags = list(self._saved)
        if keep is None:
            kept = set(tags[-1:])
        elif isinstance(keep, int):
            kept = set(tags if keep <= 0 else tags[-keep:])
        else:
            kept = set(keep) | ({self._last_tag} if self._last_tag is not None else set())
        self._saved = {t: names for t, names in self._saved.items() if t in kept}
        needed = {n for names in self._saved.values() for n in names} | set(named)
        needed.update(c["file"] for c in self._chunks)  # the buffer's own, saved or loaded
        if self._snap is not None:
            needed.update(c["file"] for c in self._snap["done"] or self._snap["chunks"])
        deleted = []
        if self.directory is not None and self.directory.is_dir():
            for path in sorted(self.directory.iterdir()):
                if CHUNK_NAME.fullmatch(path.name) and path.name not in needed:
                    path.unlink(missing_ok=True)
                    deleted.append(path.name)
        return deleted

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Rebuild the buffer from a manifest ``save`` returned and its chunk files in
        ``directory``; ``ReplayFileError`` (one line, naming the file) when they are not usable."""
        if not isinstance(state, dict) or state.get("format") != MANIFEST_FORMAT:
            raise ReplayFileError(f"not a replay buffer manifest (format {MANIFEST_FORMAT!r})")
        if "unsaved" in state:
            raise ReplayFileError("replay: an eval snapshot's manifest, never settled (no rows)")
        state = self._adopted(state)
        capacity = replay_files._int(state.get("capacity"), "capacity", 1, replay_files.MAX_ROWS)
        if capacity != self.capacity:
            raise ReplayFileError(
                f"the checkpoint's buffer holds {capacity} transitions, algorithm.buffer_size="
                f"{self.capacity}: resume with the run's buffer_size"
            )
        n_step = replay_files._int(state.get("n_step"), "n_step", 1, 1 << 20)
        if n_step != self.n_step or (n_step > 1 and state.get("gamma") != self.gamma):
            raise ReplayFileError(
                f"the checkpoint's buffer has n_step={n_step}, gamma={state.get('gamma')!r}; this "
                f"run has {self.n_step}, {self.gamma}: resume with the run's settings"
            )
        written = replay_files._int(state.get("written"), "written", 0, replay_files.MAX_ROWS)
        generator = replay_files.check_generator(state.get("generator"))
        layout = (
            replay_files.check_layout(state.get("layout"))
            if written or state.get("pending")
            else None
        )
        chunks = replay_files.check_chunks(state.get("chunks"), written, capacity)
        saved = replay_files.check_saved(state.get("saved"))
        pending = replay_files.check_pending(state.get("pending"), layout or [], n_step)
        if written and self.directory is None:
            raise ValueError("loading a replay buffer needs its directory (Replay(directory=...))")
        parts = [(c, replay_files.read_chunk(self.directory, c, layout)) for c in chunks]

        self.layout, self._rb, self._leaves, self.written = layout, None, [], 0
        first = written - min(written, capacity)
        for entry, rows in parts:
            lo = max(entry["start"], first)
            rows = rows[lo - entry["start"] :]
            if self._rb is None:
                self._build(rows)
            self._rb.storage.set(
                torch.arange(lo, entry["stop"]) % capacity, rows.to(self._device())
            )
        self.written = written
        if self._rb is not None:
            self._set_cursor(written)
            self._leaves = self._storage_leaves()
            if len(self._rb.storage) != len(self):
                raise ReplayFileError(
                    f"the chunks filled {len(self._rb.storage)} rows, expected {len(self)}"
                )
        try:
            self.generator.set_state(generator.clone())
        except RuntimeError as exc:
            raise ReplayFileError(f"replay.generator is not a generator state ({exc})") from None
        self._chunks, self._saved_upto, self._saved = chunks, written, saved
        self._last_tag = self._snap = None
        self._pending = nstep.nstep_from_state_dict(pending)
