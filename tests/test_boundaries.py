"""Values at the boundary itself (issue #44 item 6), where an off-by-one shows.

- The checkpoint scan (``checkpoint_scan._check_view``): a view that ends exactly at its storage's
  last element is accepted, one element further is refused; torch's own loader is the reference
  for both (it builds the first and refuses the second).
- ``trainer.device=auto``: docs/batched_envs.md's "MLP of at most 256 units per layer" stays on the
  CPU at 255 and 256 and goes to CUDA at 257, in the actor or the critic, at any layer.
- The stop watchdog's ``status.json`` names the newest checkpoint as the resume point, not the one
  this attempt resumed from.
- Another library's name as the last part of a key with two or more dots still gets its rlexp key.
"""

from __future__ import annotations

import collections
import io
import pickle
import signal
import zipfile
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
from torch._utils import _rebuild_tensor_v2

from rlexp.checkpoints.scan import ScanError, scan


# -- the checkpoint scan's view bound --------------------------------------------------------------
class _Storage:
    """A storage record: 12 float32 elements 0, 1, ..., 11 (``numel`` as declared)."""

    numel = 12


class _View:
    """A tensor record over the storage: (offset, shape, stride) as declared, as torch pickles it."""

    def __init__(self, storage: _Storage, offset: int, size: tuple, stride: tuple) -> None:
        self.args = (storage, offset, size, stride)

    def __reduce__(self):
        return _rebuild_tensor_v2, (*self.args, False, collections.OrderedDict())


class _Pickler(pickle.Pickler):
    def persistent_id(self, obj):
        if isinstance(obj, _Storage):
            return ("storage", torch.FloatStorage, "0", "cpu", obj.numel)
        return None


def _checkpoint(offset: int, size: tuple, stride: tuple) -> bytes:
    """A torch zip checkpoint ``{"t": view}`` of one 12-element float32 storage, written by hand
    as ``torch.save`` writes it (stored members, data.pkl, data/0)."""
    pkl = io.BytesIO()
    _Pickler(pkl, protocol=2).dump({"t": _View(_Storage(), offset, size, stride)})
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w") as archive:
        archive.writestr("archive/data.pkl", pkl.getvalue())
        archive.writestr("archive/byteorder", "little")
        archive.writestr("archive/data/0", torch.arange(12, dtype=torch.float32).numpy().tobytes())
        archive.writestr("archive/version", "3\n")
    return out.getvalue()


def _scan(data: bytes):
    return scan(io.BytesIO(data), len(data))


#: (offset, shape, stride) ending exactly at element 11 (the last), and the same one element on.
AT_THE_END = [
    (4, (8,), (1,)),  # elements 4..11
    (0, (3, 4), (4, 1)),  # 0..11, contiguous
    (1, (2, 3), (6, 2)),  # 1 + 6*1 + 2*2 = 11: strided
    (11, (1,), (1,)),  # the last element alone
]


@pytest.mark.parametrize(("offset", "size", "stride"), AT_THE_END)
def test_a_view_ending_at_its_storages_last_element_is_accepted_and_one_further_refused(
    offset, size, stride
):
    at_end = _checkpoint(offset, size, stride)
    (ref,) = _scan(at_end)
    assert (ref.where, ref.offset, ref.size) == ("t", offset, size)
    loaded = torch.load(io.BytesIO(at_end), weights_only=True)["t"]  # torch agrees: it builds it
    want = torch.arange(12, dtype=torch.float32).as_strided(size, stride, offset)
    assert torch.equal(loaded, want) and loaded.flatten()[-1] == 11.0

    past = _checkpoint(offset + 1, size, stride)
    with pytest.raises(ScanError) as err:
        _scan(past)
    assert str(err.value) == (
        f"tensor t declares shape {size} ({want.numel()} elements) over a storage of 12 "
        "elements: a crafted or corrupt file"
    )
    with pytest.raises(RuntimeError, match="resize storage that is not resizable"):  # torch too
        torch.load(io.BytesIO(past), weights_only=True)


def test_a_broadcast_view_may_declare_as_many_elements_as_its_storage_holds_not_one_more():
    (ref,) = _scan(_checkpoint(0, (12,), (0,)))  # 12 elements read from element 0: as many
    assert ref.size == (12,)
    with pytest.raises(ScanError, match=r"declares shape \(13,\) \(13 elements\) over a storage"):
        _scan(_checkpoint(0, (13,), (0,)))
    with pytest.raises(ScanError, match=r"declares shape \(3, 5\) \(15 elements\)"):
        _scan(_checkpoint(0, (3, 5), (0, 0)))


def test_an_empty_view_may_sit_at_its_storages_end_not_past_it():
    assert _scan(_checkpoint(12, (0,), (1,)))[0].offset == 12
    with pytest.raises(ScanError, match="tensor t: offset 13 past its 12 elements"):
        _scan(_checkpoint(13, (0,), (1,)))


# -- trainer.device=auto's width threshold ---------------------------------------------------------
@pytest.mark.parametrize(
    ("actor", "critic", "device"),
    [
        ([255], [64, 64], "cpu"),
        ([256, 256], [64], "cpu"),  # docs: "at most 256 units per layer (64x64, 256x256)"
        ([64, 64], [32, 256], "cpu"),
        ([257, 16], [64, 64], "cuda"),  # one unit wider, in the first of two layers
        ([64, 64], [32, 257], "cuda"),  # ... or in the critic's last hidden layer
        ([16], [257], "cuda"),
    ],
)
def test_auto_device_keeps_at_most_256_units_on_the_cpu(monkeypatch, actor, critic, device):
    from rlexp.config.schema import MLPConfig, PolicyConfig
    from rlexp.runtime.devices import auto_device

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)  # as on a GPU machine
    cfg = PolicyConfig(actor=MLPConfig(hidden_sizes=actor), critic=MLPConfig(hidden_sizes=critic))
    got, why = auto_device(torch.device("cpu"), cfg, None)
    width = max(actor + critic)
    assert got == device, why
    relation = "<=" if device == "cpu" else ">"
    assert f"(widest layer {width} {relation} 256)" in why, why


# -- the stop watchdog's resume point --------------------------------------------------------------
def _watchdog(tmp_path: Path, newest: Path | None, resumed_from: Path | None):
    from rlexp.run.stalls import StopWatchdog

    trainer = SimpleNamespace(last_checkpoint=newest, global_step=1536, last_eval={})
    return StopWatchdog(trainer, tmp_path, resumed_from, grace_s=3.0)


def test_the_stop_watchdog_names_the_newest_checkpoint_not_the_one_resumed_from(
    tmp_path, monkeypatch
):
    """Resumed from step 512, saved 1024 and 1536 since, then stuck: a resume continues from 1536,
    and ``status.json`` says so (``expire``, with the exit stubbed)."""
    import json

    from rlexp.run import stalls

    ckpts = tmp_path / "checkpoints"
    resumed, newest = ckpts / "x_step_000000512.pt", ckpts / "x_step_000001536.pt"
    dog = _watchdog(tmp_path, newest, resumed)
    assert dog.reason(signal.SIGTERM) == (
        "SIGTERM received at step 1536: the loop did not reach its safe point within "
        "trainer.stop_grace_s=3 s (stuck in an env step or other user code?), so no checkpoint "
        f"was possible at the safe point; the resume point is {newest}"
    )
    exits = []
    monkeypatch.setattr(stalls.os, "_exit", exits.append)
    dog.expire(signal.SIGTERM)
    assert exits == [128 + signal.SIGTERM]
    status = json.loads((tmp_path / "status.json").read_text())
    assert status["state"] == "interrupted" and status["reason"].endswith(
        f"the resume point is {newest}"
    )
    # Nothing saved since the resume: the checkpoint it resumed from; nothing at all: said so.
    assert _watchdog(tmp_path, None, resumed).reason(2).endswith(f"the resume point is {resumed}")
    assert _watchdog(tmp_path, None, None).reason(2).endswith("no checkpoint was written yet")


# -- alias hints for keys of two or more dots ------------------------------------------------------
@pytest.mark.parametrize(
    ("key", "expected"),
    [
        ("policy.actor.net_arch", "`net_arch` (Stable-Baselines3, rl-zoo) is "
         "`policy.actor.hidden_sizes` here: and policy.critic.hidden_sizes"),
        ("policy.critic.activation_fn", "`activation_fn` (Stable-Baselines3, rl-zoo) is "
         "`policy.actor.activation` here"),
        ("policy.actor.learning_rate", "`learning_rate` (Stable-Baselines3, CleanRL, rl-zoo) is "
         "`algorithm.lr` here"),
    ],
)  # fmt: skip
def test_an_other_librarys_name_below_two_dots_gets_its_rlexp_key(key, expected):
    from rlexp.config.aliases import alias_hint
    from rlexp.config.validate import ConfigError
    from rlexp.launch.precheck import check_key

    assert alias_hint(key).startswith(expected)
    with pytest.raises(ConfigError) as err:
        check_key(key)
    msg = str(err.value)
    assert msg.startswith(f"{key} is not a config key") and expected in msg
    assert "did you mean" not in msg
