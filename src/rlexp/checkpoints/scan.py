"""What a checkpoint file declares, read before torch materialises any of it.

``torch.load`` allocates what the file *declares*: a storage record's element count, a tensor view's
shape over its storage, a compressed zip member's uncompressed size; and ``weights_only`` still lets
a pickle call ``torch.FloatTensor(n)`` or ``bytearray(n)``. A file of a few kB can so make eval,
export or a resume allocate gigabytes before anything refuses it (issue #29, item 7). ``scan`` reads
the zip's central directory (no member is decompressed) and ``data.pkl`` with an unpickler that
builds nothing: every global it meets is one of a short allowlist of stand-ins, each tensor becomes a
record of (storage, offset, shape, stride). It then checks what torch would allocate: every member
stored (torch writes them uncompressed), every storage exactly as long as its member, all storages
together no longer than the file, every view inside its storage and no larger than it. After that,
``torch.load`` of the same file materialises at most the file's own size.
"""

from __future__ import annotations

import codecs
import io
import math
import pickle
import zipfile
from collections import Counter, OrderedDict
from dataclasses import dataclass
from typing import IO, Any

import torch

#: Containers nested deeper than this are refused (rlexp's own checkpoints nest about 8 deep).
MAX_DEPTH = 64
#: Values in the checkpoint's tree, shared references counted each time (rlexp's: a few thousand).
MAX_NODES = 10_000_000


class ScanError(ValueError):
    """What makes the file unsafe or impossible to load; the caller names the file."""


@dataclass(frozen=True)
class StorageRef:
    """A storage record as ``data.pkl`` declares it: its zip member key, dtype, element count."""

    key: str
    dtype: torch.dtype
    numel: int

    @property
    def nbytes(self) -> int:
        return self.numel * _itemsize(self.dtype)


@dataclass
class TensorRef:
    """A tensor as ``data.pkl`` declares it: a view (offset, shape, stride) of a storage."""

    storage: StorageRef
    offset: int
    size: tuple[int, ...]
    stride: tuple[int, ...]
    where: str = "a tensor"

    @property
    def numel(self) -> int:
        return math.prod(self.size)


def _itemsize(dtype: torch.dtype) -> int:
    return torch.empty((), dtype=dtype).element_size()


#: ``torch.FloatStorage`` & co. (as ``data.pkl`` names them) -> their dtype.
_STORAGE_TYPES = {name: dtype for dtype, name in torch.storage._dtype_to_storage_type_map().items()}
_STORAGE_TYPES["UntypedStorage"] = torch.uint8
_DTYPES = {str(d).removeprefix("torch."): d for d in _STORAGE_TYPES.values()}


class _StorageType:
    """Stands for a storage class: only ever an argument of a storage record, never called."""

    def __init__(self, dtype: torch.dtype) -> None:
        self.dtype = dtype


class _Inert:
    """Stands for a class that is only ever an argument; called, it refuses."""

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        raise ScanError("not an rlexp checkpoint: it constructs a tensor by calling its class")


_INERT = _Inert()


def _tuple_of_ints(value: Any, what: str) -> tuple[int, ...]:
    if not isinstance(value, tuple | list) or not all(
        isinstance(v, int) and not isinstance(v, bool) and v >= 0 for v in value
    ):
        raise ScanError(f"a tensor's {what} {value!r} is not a tuple of ints >= 0")
    return tuple(value)


class _Scanner(pickle.Unpickler):
    """``data.pkl`` read into plain containers and ``TensorRef``s; nothing outside the allowlist
    is looked up, let alone imported or called."""

    def __init__(self, data: bytes) -> None:
        super().__init__(io.BytesIO(data))
        self.tensors: list[TensorRef] = []
        self.storages: dict[str, StorageRef] = {}
        self._allowed: dict[str, Any] = {
            "collections.OrderedDict": OrderedDict,
            "collections.Counter": Counter,
            "torch._utils._rebuild_tensor_v2": self._rebuild,
            "torch._utils._rebuild_tensor_v3": self._rebuild_v3,
            "torch._utils._rebuild_parameter": lambda data, *_: data,
            "torch._utils._rebuild_parameter_with_state": lambda data, *_: data,
            "torch._tensor._rebuild_from_type_v2": lambda func, _type, args, _state: func(*args),
            "_codecs.encode": _encode,
            "builtins.bytearray": _bytearray,
            "builtins.set": set,
            "builtins.complex": complex,
            "torch.Size": lambda dims=(): _tuple_of_ints(dims, "torch.Size"),
            "torch.device": lambda *args: ("device", *args),
            "torch.Tensor": _INERT,  # the type argument of _rebuild_from_type_v2
            "torch._tensor.Tensor": _INERT,
            "torch.nn.parameter.Parameter": _INERT,
        }

    def find_class(self, module: str, name: str) -> Any:
        full = f"{module}.{name}"
        if full in self._allowed:
            return self._allowed[full]
        if module == "torch" and name in _STORAGE_TYPES:
            return _StorageType(_STORAGE_TYPES[name])
        if module == "torch" and name in _DTYPES:
            return _DTYPES[name]
        raise ScanError(
            f"not an rlexp checkpoint: it holds {full}, which loading would construct or run; "
            "rlexp loads only tensors and plain values (weights_only)"
        )

    def persistent_load(self, pid: Any) -> StorageRef:
        if not (isinstance(pid, tuple) and len(pid) == 5 and pid[0] == "storage"):
            raise ScanError(f"a storage record {str(pid)[:80]} is not torch's")
        _, stype, key, _location, numel = pid
        if not isinstance(stype, _StorageType) or not isinstance(key, str):
            raise ScanError(f"storage record {str(key)[:40]!r} names no storage type")
        if not isinstance(numel, int) or isinstance(numel, bool) or numel < 0:
            raise ScanError(f"storage record {key!r} declares {numel!r} elements")
        ref = StorageRef(key, stype.dtype, numel)
        if self.storages.setdefault(key, ref) != ref:
            raise ScanError(f"storage record {key!r} is declared twice, differently")
        return ref

    def _rebuild(self, storage: Any, offset: Any, size: Any, stride: Any, *_: Any) -> TensorRef:
        if not isinstance(storage, StorageRef):
            raise ScanError("a tensor without a storage record")
        if not isinstance(offset, int) or isinstance(offset, bool) or offset < 0:
            raise ScanError(f"a tensor's storage offset {offset!r} is not an int >= 0")
        ref = TensorRef(
            storage, offset, _tuple_of_ints(size, "shape"), _tuple_of_ints(stride, "stride")
        )
        self.tensors.append(ref)
        return ref

    def _rebuild_v3(self, storage: Any, offset: Any, size: Any, stride: Any, *rest: Any) -> Any:
        return self._rebuild(storage, offset, size, stride)


def _encode(text: Any, encoding: Any = "utf-8") -> bytes:
    """``bytes`` as protocol 2 pickles them: from a string, as long as the string."""
    if not isinstance(text, str) or encoding not in ("latin1", "latin-1"):
        raise ScanError("a bytes value that is not pickled as torch pickles bytes")
    return codecs.encode(text, encoding)


def _bytearray(*args: Any) -> bytearray:
    """A bytearray from a string or bytes; ``bytearray(n)`` (n zero bytes from one number) is not."""
    if args and not isinstance(args[0], str | bytes):
        raise ScanError(f"a bytearray({str(args[0])[:40]}) declares its size instead of its bytes")
    return bytearray(*args)


def scan(f: IO[bytes], size: int) -> list[TensorRef]:
    """The tensors the torch zip checkpoint in ``f`` (``size`` bytes) declares, each with where it
    sits (``policy.actor_net.mlp.0.weight``); ``ScanError`` if loading it would materialise more
    than the file holds, or anything but tensors and plain values."""
    try:
        archive = zipfile.ZipFile(f)
    except (zipfile.BadZipFile, OSError, ValueError) as exc:
        raise ScanError(_not_a_zip(f, size, exc)) from None
    with archive:
        members = _members(archive, size)
        prefix = archive.infolist()[0].filename.split("/")[0]
        pkl = members.get(f"{prefix}/data.pkl")
        if pkl is None:
            raise ScanError("not a torch checkpoint: the archive has no data.pkl")
        scanner = _Scanner(archive.read(pkl))
        try:
            root = scanner.load()
        except ScanError:
            raise
        except Exception as exc:  # a malformed pickle: the stand-ins reject what they don't expect
            raise ScanError(f"corrupt: data.pkl does not unpickle ({str(exc)[:120]})") from None
    _walk(root)
    _check_storages(scanner, members, prefix, size)
    for ref in scanner.tensors:
        _check_view(ref)
    return scanner.tensors


def _not_a_zip(f: IO[bytes], size: int, exc: BaseException) -> str:
    if size == 0:
        return "an empty file"
    f.seek(0)
    if f.read(2) == b"PK":
        return "truncated or corrupt: the write that made it did not finish"
    return f"not a checkpoint: rlexp writes torch's zip format ({str(exc)[:80]})"


def _members(archive: zipfile.ZipFile, size: int) -> dict[str, zipfile.ZipInfo]:
    """Every member by name; refused: duplicates, compressed members (a zip bomb's way: torch's
    reader inflates to the declared size) and members longer than the file."""
    members: dict[str, zipfile.ZipInfo] = {}
    for info in archive.infolist():
        if info.filename in members:
            raise ScanError(f"corrupt: the archive holds {info.filename!r} twice")
        if info.compress_type != zipfile.ZIP_STORED:
            raise ScanError(
                f"its member {info.filename!r} is compressed, declaring {info.file_size} bytes; "
                "torch writes checkpoints uncompressed"
            )
        if info.file_size > size or info.compress_size > size:
            raise ScanError(
                f"corrupt: its member {info.filename!r} declares {info.file_size} bytes, more "
                f"than the file's {size}"
            )
        members[info.filename] = info
    if not members:
        raise ScanError("not a torch checkpoint: an empty archive")
    return members


def _walk(root: Any) -> None:
    """Give each tensor record the dotted path of its first place in the tree; refuse a cycle, a
    nesting deeper than ``MAX_DEPTH`` and a tree that shared references expand past ``MAX_NODES``
    (a few kB of pickle memo references can stand for 10^9 nodes, which any later walk of the
    config or state would expand). Iterative: a hostile file may nest deeply."""
    sizes: dict[int, int] = {}
    on_path: set[int] = set()
    stack: list[tuple[Any, str, int, bool]] = [(root, "", 0, False)]
    while stack:
        obj, where, depth, post = stack.pop()
        if isinstance(obj, TensorRef):
            obj.where = obj.where if obj.where != "a tensor" else where or "a tensor"
            continue
        kids = _children(obj, where)
        if kids is None:
            continue
        key = id(obj)
        if post:
            on_path.discard(key)
            sizes[key] = 1 + sum(sizes.get(id(v), 1) for _, v in kids)
            if sizes[key] > MAX_NODES:
                raise ScanError(
                    f"corrupt: {where or 'the checkpoint'} expands to over {MAX_NODES} values"
                )
            continue
        if key in on_path:
            raise ScanError(f"corrupt: {where or 'the checkpoint'} contains itself")
        if key in sizes:
            continue
        if depth > MAX_DEPTH:
            raise ScanError(
                f"corrupt: {where or 'the checkpoint'} nests more than {MAX_DEPTH} deep"
            )
        on_path.add(key)
        stack.append((obj, where, depth, True))
        stack.extend((v, w, depth + 1, False) for w, v in reversed(kids))


def _children(obj: Any, where: str) -> list[tuple[str, Any]] | None:
    """A container's children with their dotted paths; None for anything else."""
    if isinstance(obj, dict):
        return [(f"{where}.{k}" if where else str(k), v) for k, v in obj.items()]
    if isinstance(obj, list | tuple | set | frozenset):
        return [(f"{where}[{i}]", v) for i, v in enumerate(obj)]
    return None


def _check_storages(
    scanner: _Scanner, members: dict[str, zipfile.ZipInfo], prefix: str, size: int
) -> None:
    """Each storage's bytes are its member's, and together no more than the file holds (members of
    a hostile zip may overlap)."""
    users = {}
    for ref in scanner.tensors:
        users.setdefault(ref.storage.key, ref.where)
    total = 0
    for key, storage in scanner.storages.items():
        who = f"tensor {users.get(key, 'of storage ' + repr(key))}"
        info = members.get(f"{prefix}/data/{key}")
        if info is None:
            raise ScanError(f"corrupt: the data of {who} (data/{key}) is missing")
        if info.file_size != storage.nbytes:
            raise ScanError(
                f"{who}: its storage declares {storage.numel} x {storage.dtype} "
                f"({storage.nbytes} bytes), the file holds {info.file_size} bytes of it"
            )
        total += storage.nbytes
    if total > size:
        raise ScanError(f"corrupt: its tensors declare {total} bytes, more than the file's {size}")


def _check_view(ref: TensorRef) -> None:
    """A view must lie inside its storage and hold no more elements than it: a broadcast view
    (stride 0) of a few bytes declaring 10^8 elements costs 10^8 elements in every later use."""
    shape = tuple(ref.size)
    numel, stored = ref.numel, ref.storage.numel
    if len(ref.size) != len(ref.stride):
        raise ScanError(f"tensor {ref.where}: shape {shape} and stride {ref.stride} differ in rank")
    if numel == 0:
        if ref.offset > stored:
            raise ScanError(f"tensor {ref.where}: offset {ref.offset} past its {stored} elements")
        return
    extent = ref.offset + sum((n - 1) * s for n, s in zip(ref.size, ref.stride, strict=True)) + 1
    if numel > stored or extent > stored:
        raise ScanError(
            f"tensor {ref.where} declares shape {shape} ({numel} elements) over a storage of "
            f"{stored} elements: a crafted or corrupt file"
        )
