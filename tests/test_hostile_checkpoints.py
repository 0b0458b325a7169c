"""Hostile checkpoints (issue #29, items 7 and 8), made from a real checkpoint of a tiny run.

7. A file of a few hundred kB that declares far more than it holds (a broadcast view of 10^8
   elements over 256, a view past its storage, a storage record declaring 1.6 GB, a compressed
   member inflating to 1.2 GB) is refused naming the tensor, before memory grows: ``rlexp eval`` /
   ``export`` exit 2 with one line and a peak RSS far below what the file declares; a resume falls
   back past it.
8. Weights of another dtype are refused, not cast; a stored config without a section is one line;
   a directory, dangling symlink or FIFO with a checkpoint's name is skipped like a corrupt file;
   every scalar field (``global_step`` of 2**70, -1, "512", True, not the file name's step; the
   iteration, windows, RNG states, normaliser statistics, ...) is checked before use.
"""

from __future__ import annotations

import collections
import contextlib
import io
import json
import math
import os
import pickle
import shutil
import signal
import sys
import threading
import zipfile
from pathlib import Path

import pytest
import torch
from torch._utils import _rebuild_tensor_v2

from conftest import REPO, SHORT, Children, run_train
from conftest import rlexp_cli as _cli
from rlexp.checkpoints.files import latest_good_checkpoint, load_checkpoint, save_checkpoint

#: The tensor the item-7 files lie about, and its real shape (InvertedPendulum: 4 observations).
WEIGHT = "actor_net.mlp.0.weight"
#: Peak RSS an eval / export of a refused file must stay under (each file declares >= 1.2 GB).
RSS_LIMIT = 900 * 2**20


# -- a checkpoint zip written by hand: what torch.save would write, with chosen lies -------------
class _Storage:
    def __init__(self, key: str, dtype: torch.dtype, data: bytes | int, numel: int) -> None:
        self.key, self.dtype, self.data, self.numel = key, dtype, data, numel


class _Pickler(pickle.Pickler):
    """Pickles tensors as torch.save does (``_rebuild_tensor_v2`` over a storage record), each over
    a storage of its own; ``lies[id(tensor)]`` overrides its declared size, stride, storage numel
    or (``zeros``: a member of that many zero bytes, deflated) its data."""

    def __init__(self, f: io.BytesIO, lies: dict[int, dict]) -> None:
        super().__init__(f, protocol=2)
        self.lies, self.storages = lies, []

    def persistent_id(self, obj):
        if isinstance(obj, _Storage):
            name = torch.storage._dtype_to_storage_type_map()[obj.dtype]
            return ("storage", getattr(torch, name), obj.key, "cpu", obj.numel)
        return None

    def reducer_override(self, obj):
        if not torch.is_tensor(obj):
            return NotImplemented
        flat = obj.detach().reshape(-1).contiguous()
        data = flat.view(torch.uint8).numpy().tobytes()
        size, stride = tuple(obj.shape), torch.empty(obj.shape).stride()
        lie = self.lies.get(id(obj), {})
        numel = lie.get("numel", flat.numel())
        if "zeros" in lie:
            data, numel = lie["zeros"], lie["zeros"] // obj.element_size()
        storage = _Storage(str(len(self.storages)), obj.dtype, data, numel)
        self.storages.append(storage)
        args = (storage, 0, lie.get("size", size), lie.get("stride", stride))
        return (_rebuild_tensor_v2, (*args, False, collections.OrderedDict()))


def _write(path: Path, state: dict, lies: dict[int, dict] | None = None) -> Path:
    buf = io.BytesIO()
    pickler = _Pickler(buf, lies or {})
    pickler.dump({"format": "rlexp-checkpoint-v1", **state})
    with zipfile.ZipFile(path, "w", compresslevel=1) as archive:
        archive.writestr("archive/data.pkl", buf.getvalue())
        archive.writestr("archive/byteorder", "little")
        archive.writestr("archive/version", "3\n")
        for st in pickler.storages:
            name = f"archive/data/{st.key}"
            if isinstance(st.data, bytes):
                archive.writestr(name, st.data)
                continue
            info = zipfile.ZipInfo(name)
            info.compress_type = zipfile.ZIP_DEFLATED
            with archive.open(info, "w", force_zip64=True) as member:
                block = bytes(1 << 24)
                for _ in range(st.data // len(block)):
                    member.write(block)
    return path


# -- fixtures ------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    """A finished SHORT run: checkpoints at steps 256 and 512."""
    root = tmp_path_factory.mktemp("hostile")
    run_train([*SHORT, f"hydra.run.dir={root / 'run'}"], cwd=root)
    return root / "run"


def _ckpts(run_dir: Path) -> list[Path]:
    return sorted((run_dir / "checkpoints").glob("*_step_*.pt"))


def _state(run_dir: Path, which: int = -1) -> dict:
    ckpt = load_checkpoint(_ckpts(run_dir)[which])
    ckpt.pop("path")
    return ckpt


def _lying(run_dir: Path, path: Path, kind: str) -> Path:
    """A copy of the newest checkpoint in which one tensor declares far more than it holds (made
    once per module: deflating 1.2 GB of zeros takes seconds)."""
    made = run_dir.parent / f"{kind}.pt"
    if not made.exists():
        _make_lying(run_dir, made, kind)
    shutil.copyfile(made, path)
    return path


def _make_lying(run_dir: Path, path: Path, kind: str) -> Path:
    state = _state(run_dir)
    if kind == "returns broadcast":  # the reward normaliser's running returns: a resume uses them
        t = state["algorithm"]["reward_normalizer"]["returns"]
        return _write(path, state, {id(t): {"size": (300_000_000,), "stride": (0,)}})
    t = state["policy"][WEIGHT]
    lie = {
        "broadcast view": {"size": (20000, 20000), "stride": (0, 0)},
        "view past its storage": {"size": (20000, 20000), "stride": (20000, 1)},
        "huge storage record": {"numel": 400_000_000},
        "compressed member": {"zeros": 72 * 2**24, "size": (18 * 2**24,), "stride": (1,)},
    }[kind]
    return _write(path, state, {id(t): lie})


def _rlexp(children: Children, tmp_path: Path, *args) -> tuple[int, str, str, int]:
    """``python -m rlexp.cli ARGS`` in a child: (exit code, stdout, stderr, peak RSS in bytes)."""
    out, err = tmp_path / "stdout.txt", tmp_path / "stderr.txt"
    env = {**os.environ, "PYTHONPATH": str(REPO / "src"), "MUJOCO_GL": "egl"}
    with open(out, "w") as o, open(err, "w") as e:
        proc = children.popen(
            [sys.executable, "-m", "rlexp.cli", *map(str, args)], stdout=o, stderr=e, env=env
        )
    guard = threading.Timer(300, os.killpg, (proc.pid, signal.SIGKILL))
    guard.start()
    try:
        _, status, usage = os.wait4(proc.pid, 0)  # this child's own peak RSS
    finally:
        guard.cancel()
    proc.returncode = os.waitstatus_to_exitcode(status)
    return proc.returncode, out.read_text(), err.read_text(), usage.ru_maxrss * 1024


def _one_line(code: int, out: str, err: str, want: int = 2) -> str:
    lines = err.strip().splitlines()
    assert code == want and len(lines) == 1, (code, out, err)
    assert "Traceback" not in err and "mean return" not in out and "exported" not in out
    return lines[0]


# -- item 7: declared sizes are checked before anything is materialised ---------------------------
LIES = {  # kind -> what the one line must say (besides the file and the tensor)
    "broadcast view": "declares shape (20000, 20000) (400000000 elements) over a storage of 256",
    "view past its storage": "declares shape (20000, 20000) (400000000 elements) over a storage",
    "huge storage record": "declares 400000000 x torch.float32 (1600000000 bytes), the file holds",
    "compressed member": "is compressed, declaring 1207959552 bytes",
}


@pytest.mark.parametrize("kind", list(LIES))
def test_eval_refuses_a_file_declaring_more_than_it_holds_before_memory_grows(
    run_dir, tmp_path, children, kind
):
    path = _lying(run_dir, tmp_path / "InvertedPendulum-v5_ppo_step_000000512.pt", kind)
    assert path.stat().st_size < 10 * 2**20  # a small file (the deflated 1.2 GB: ~5 MB)
    code, out, err, rss = _rlexp(children, tmp_path, "eval", path, "--episodes", "1")
    assert rss < RSS_LIMIT, f"peak RSS {rss / 2**20:.0f} MiB for a refused file: {err}"
    line = _one_line(code, out, err)
    assert line.startswith(f"rlexp eval: checkpoint {str(path)!r} is unreadable ("), line
    assert LIES[kind] in line, line
    if kind != "compressed member":  # (its message names the zip member)
        assert f"tensor policy.{WEIGHT}" in line, line


@pytest.mark.parametrize("kind", ["broadcast view", "compressed member"])
def test_export_refuses_it_too(run_dir, tmp_path, children, kind):
    path = _lying(run_dir, tmp_path / "lying.pt", kind)
    code, out, err, rss = _rlexp(children, tmp_path, "export", path, "--out", tmp_path / "x.pt")
    assert rss < RSS_LIMIT, f"peak RSS {rss / 2**20:.0f} MiB for a refused file: {err}"
    line = _one_line(code, out, err)
    assert line.startswith(f"rlexp export: checkpoint {str(path)!r} is unreadable (") and (
        LIES[kind] in line
    ), line
    assert not (tmp_path / "x.pt").exists()


def test_a_stored_config_declaring_a_huge_policy_is_refused_before_it_is_built(
    run_dir, tmp_path, children
):
    """Not in the issue's text: the weights are honest, the stored config declares 16384-wide
    layers (1 GiB of float32 for one of them). The policy it declares is built on the meta device
    and compared first; the real one would be allocated (and initialised) before the refusal."""
    state = _state(run_dir)
    state["config"]["policy"].update(ortho_init=False)
    state["config"]["policy"]["actor"]["hidden_sizes"] = [16384, 16384]
    path = save_checkpoint(tmp_path / "wide.pt", state)
    code, out, err, rss = _rlexp(children, tmp_path, "eval", path, "--episodes", "1")
    assert rss < RSS_LIMIT, f"peak RSS {rss / 2**20:.0f} MiB for a refused file: {err}"
    line = _one_line(code, out, err)
    assert line == (
        "rlexp eval: the checkpoint's policy does not fit this config's policy (size mismatch for "
        f"policy.{WEIGHT}: shape (64, 4) in checkpoint {str(path)!r}, (16384, 4) in this config's "
        "policy)"
    )


def test_a_resume_falls_back_past_lying_and_non_file_checkpoints(run_dir, tmp_path, children):
    """One resume past four bad newest 'checkpoints' (newest first): a FIFO, a dangling symlink, a
    directory, and a file whose normaliser returns broadcast 3*10^8 float64 (2.4 GB) over one
    value. Each is named and moved to corrupt/; the run continues from step 256 to 768, with a
    small peak RSS."""
    run = shutil.copytree(run_dir, tmp_path / "run", symlinks=True)
    ckpts = run / "checkpoints"
    name = "InvertedPendulum-v5_ppo_step_{:09d}.pt"
    _lying(run_dir, ckpts / name.format(512), "returns broadcast")
    (ckpts / name.format(600)).mkdir()
    (ckpts / name.format(700)).symlink_to(tmp_path / "gone.pt")
    os.mkfifo(ckpts / name.format(800))
    (run / "status.json").write_text('{"state": "interrupted", "global_step": 512}')
    overrides = [a for a in SHORT if not a.startswith("trainer.total_frames")]
    args = [str(REPO / "train.py"), *overrides, "trainer.total_frames=768", f"hydra.run.dir={run}"]
    code, out, err, rss = _rlexp_train(children, tmp_path, args)
    assert code == 0, out + err
    text = out + err
    for step in (512, 600, 700, 800):
        assert f"{name.format(step)}" in text and "falling back" in text, text
        assert os.path.lexists(ckpts / "corrupt" / name.format(step)), step
    assert f"continuing from {ckpts / name.format(256)} at step 256" in text, text
    assert load_checkpoint(ckpts / name.format(768))["global_step"] == 768
    assert rss < RSS_LIMIT + 300 * 2**20, f"peak RSS {rss / 2**20:.0f} MiB"


def _rlexp_train(children: Children, tmp_path: Path, args: list[str]):
    out, err = tmp_path / "train_out.txt", tmp_path / "train_err.txt"
    env = {**os.environ, "PYTHONPATH": str(REPO / "src"), "MUJOCO_GL": "egl"}
    with open(out, "w") as o, open(err, "w") as e:
        proc = children.popen([sys.executable, *args], stdout=o, stderr=e, env=env, cwd=tmp_path)
    guard = threading.Timer(300, os.killpg, (proc.pid, signal.SIGKILL))
    guard.start()
    try:
        _, status, usage = os.wait4(proc.pid, 0)
    finally:
        guard.cancel()
    proc.returncode = os.waitstatus_to_exitcode(status)
    return proc.returncode, out.read_text(), err.read_text(), usage.ru_maxrss * 1024


# -- item 8 (a): weights of another dtype are refused, not cast -----------------------------------
@pytest.mark.parametrize("dtype", [torch.float16, torch.float64, torch.int32])
def test_policy_weights_of_another_dtype_are_refused_naming_tensor_and_dtypes(
    run_dir, tmp_path, dtype
):
    state = _state(run_dir)
    state["policy"][WEIGHT] = state["policy"][WEIGHT].to(dtype)
    path = save_checkpoint(tmp_path / "cast.pt", state)
    line = _one_line(*_cli("eval", path, "--episodes", "1", "--num-envs", "1"))
    assert line.startswith(f"rlexp eval: checkpoint {str(path)!r}: policy.{WEIGHT} is "), line
    assert f"is {dtype}, this config's policy has torch.float32" in line, line


def test_export_refuses_a_float64_normaliser_count_cast_to_float32(run_dir, tmp_path):
    """Not in the issue's text: a buffer (the normaliser's float64 count) stored as float32."""
    state = _state(run_dir)
    state["policy"]["normalizer.count"] = state["policy"]["normalizer.count"].float()
    path = save_checkpoint(tmp_path / "count.pt", state)
    line = _one_line(*_cli("export", path, "--out", tmp_path / "x.pt"))
    assert "policy.normalizer.count is torch.float32, this config's policy has torch.float64" in (
        line
    ), line


def test_optimiser_state_of_another_dtype_is_refused_on_resume(run_dir, tmp_path):
    from conftest import CONF_DIR
    from rlexp.config.validate import ConfigError
    from rlexp.launch.precheck import precheck

    state = _state(run_dir)
    state["algorithm"]["optimizer"]["state"][1]["exp_avg"] = state["algorithm"]["optimizer"][
        "state"
    ][1]["exp_avg"].double()
    path = save_checkpoint(tmp_path / "opt.pt", state)
    with pytest.raises(ConfigError, match=r"optimiser state exp_avg of .* is torch.float64, the "):
        precheck([*SHORT, f"trainer.resume={path}"], CONF_DIR)


# -- item 8 (b): a stored config without a section ------------------------------------------------
@pytest.mark.parametrize(
    ("command", "section"),
    [("eval", "policy"), ("eval", "env"), ("export", "env"), ("export", "trainer")],
)
def test_a_stored_config_without_a_section_is_one_line_naming_it(
    run_dir, tmp_path, command, section
):
    state = _state(run_dir)
    del state["config"][section]
    path = save_checkpoint(tmp_path / "partial.pt", state)
    extra = ["--episodes", "1"] if command == "eval" else ["--out", tmp_path / "x.pt"]
    line = _one_line(*_cli(command, path, *extra))
    assert line == (
        f"rlexp {command}: checkpoint {str(path)!r} is unusable: config.{section} is missing: the stored "
        f"config lacks its {section!r} section, which rebuilding the run needs"
    )


def test_a_config_section_of_the_wrong_type_is_one_line(run_dir, tmp_path):
    state = _state(run_dir)
    state["config"]["env"] = "InvertedPendulum-v5"
    path = save_checkpoint(tmp_path / "strenv.pt", state)
    line = _one_line(*_cli("eval", path))
    assert (
        f"{str(path)!r} is unusable: config.env is str: the stored config lacks its 'env'" in line
    )


@pytest.mark.parametrize("command", ["eval", "export"])
def test_a_stored_config_that_does_not_validate_is_one_line_naming_file_and_key(
    run_dir, tmp_path, command
):
    """Not in the issue's text: an unknown key in the stored config (OmegaConf's ConfigKeyError,
    a traceback before) and a value of the wrong type."""
    for key, value, says in [
        ("bogus", 1, "trainer.bogus: Key 'bogus' not in 'TrainerConfig'"),
        ("frames_per_batch", "many", "trainer.frames_per_batch: Value 'many' of type 'str'"),
    ]:
        state = _state(run_dir)
        state["config"]["trainer"][key] = value
        path = save_checkpoint(tmp_path / f"{key}.pt", state)
        extra = ["--episodes", "1"] if command == "eval" else ["--out", tmp_path / "x.pt"]
        line = _one_line(*_cli(command, path, *extra))
        assert line.startswith(
            f"rlexp {command}: checkpoint {str(path)!r} holds a config rlexp cannot use ({says}"
        ), line


# -- item 8 (c): a directory, dangling symlink or FIFO with a checkpoint's name -------------------
@pytest.mark.parametrize("kind", ["directory", "dangling symlink", "fifo"])
def test_a_non_file_with_a_checkpoint_s_name_is_skipped_like_a_corrupt_one(
    run_dir, tmp_path, caplog, kind
):
    run = shutil.copytree(run_dir, tmp_path / "run")
    bad = run / "checkpoints" / "InvertedPendulum-v5_ppo_step_000001024.pt"
    {"directory": bad.mkdir, "fifo": lambda: os.mkfifo(bad)}.get(
        kind, lambda: bad.symlink_to(tmp_path / "nowhere.pt")
    )()
    with caplog.at_level("WARNING"):
        code, out, err = _run_with_timeout(_cli, "eval", run, "--episodes", "1", "--num-envs", "1")
    assert code == 0, err
    assert "step_000000512.pt (step 512; the last checkpoint): mean return" in out, out
    assert f"skipped checkpoint {str(bad)!r} is " in caplog.text, caplog.text
    caplog.clear()
    with caplog.at_level("WARNING"):
        good = _run_with_timeout(latest_good_checkpoint, run / "checkpoints", move_aside=True)
    assert good is not None and good["global_step"] == 512
    assert f"{bad.name}" in caplog.text and "moved to" in caplog.text
    assert os.path.lexists(run / "checkpoints" / "corrupt" / bad.name) and not os.path.lexists(bad)


def _run_with_timeout(func, *args, timeout: float = 120, **kw):
    """``func(*args, **kw)`` in a thread: a call blocked on a FIFO fails the test instead of
    hanging it (the thread is a daemon: it dies with the session)."""
    result: list = []
    thread = threading.Thread(target=lambda: result.append(func(*args, **kw)), daemon=True)
    thread.start()
    thread.join(timeout)
    if thread.is_alive():
        # unblock it: a FIFO's open() returns once a writer opens the other end
        for fifo in Path(args[0]).rglob("*.pt") if isinstance(args[0], Path) else ():
            if fifo.is_fifo():
                with contextlib.suppress(OSError):
                    os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
        pytest.fail(f"{getattr(func, '__name__', func)} blocked for {timeout} s")
    return result[0]


# -- item 8 (d): every scalar field has a type and range -----------------------------------------
def _set(*keys):
    def change(state, value):
        target = state
        for key in keys[:-1]:
            target = target[key]
        target[keys[-1]] = value

    return change


_EVAL_ROUND = {"step": 10**9, "state": {}, "save": False}
FIELDS = [  # (id, change, value, what the message names)
    ("step 2**70", _set("global_step"), 2**70, "global_step=1180591620717411303424; expected an int in [0, "),
    ("step 10**12", _set("global_step"), 10**12, "global_step=1000000000000; expected an int in [0, "),
    ("step -1", _set("global_step"), -1, "global_step=-1; expected an int in"),
    ("step str", _set("global_step"), "512", "global_step='512'; expected an int"),
    ("step bool", _set("global_step"), True, "global_step=True; expected an int"),
    ("step float", _set("global_step"), 512.0, "global_step=512.0; expected an int"),
    ("step not the name's", _set("global_step"), 256, "global_step=256, but the file's name says step 512"),
    ("iteration 2**70", _set("algorithm", "iteration"), 2**70, "algorithm.iteration=1180591620717411303424; expected an int in [0, 512]"),
    ("iteration str", _set("algorithm", "iteration"), "2", "algorithm.iteration='2'; expected an int >= 0"),
    ("returns window", _set("windows", "returns"), "abc", "windows.returns is not a list of finite numbers"),
    ("lengths window", _set("windows", "lengths"), [3, -1], "windows.lengths is not a list of ints >= 0"),
    ("running length", _set("windows", "running_length"), torch.zeros(3, dtype=torch.int64), "windows.running_length does not match"),
    ("torch rng dtype", _set("rng", "torch"), torch.zeros(5056), "rng.torch is torch.float32, expected torch.uint8"),
    ("torch rng size", _set("rng", "torch"), torch.zeros(7, dtype=torch.uint8), "rng.torch is not a valid state"),
    ("numpy rng pos", _set("rng", "numpy", "pos"), 10**6, "rng.numpy.pos=1000000; expected an int in [0, 624]"),
    ("python rng", _set("rng", "python"), (3, (1, 2), None), "rng.python is not a valid state"),
    ("event rng", _set("events", "train", "rng"), {"bit_generator": "PCG64", "state": 5}, "events.train.rng is not a valid PCG64 state"),
    ("event counter", _set("events", "eval", "counters"), {"noise": -1}, "events.eval.counters.noise=-1; expected >= 0"),
    ("best metric", _set("best_metric"), math.nan, "best_metric=nan; expected a number"),
    ("last eval", _set("last_eval"), {"eval/episode_return": "high"}, "last_eval['eval/episode_return']='high'; expected a number"),
    ("eval round", _set("eval_in_flight"), _EVAL_ROUND, "eval_in_flight.step=1000000000; expected an int in [0, 512]"),
    ("reward count", _set("algorithm", "reward_normalizer", "count"), torch.tensor(-1.0, dtype=torch.float64), "count=-1.0; expected var >= 0 and count > 0"),
    ("reward var shape", _set("algorithm", "reward_normalizer", "var"), torch.ones(3, dtype=torch.float64), "algorithm.reward_normalizer.var is (3,); expected a float64 scalar tensor"),
    ("obs count", _set("policy", "normalizer.count"), torch.tensor(-1.0, dtype=torch.float64), "policy.normalizer.count holds negative values"),
    ("adam lr", lambda s, v: s["algorithm"]["optimizer"]["param_groups"][0].update(lr=v), math.inf, "param_groups[0].lr=inf; expected a finite number >= 0"),
    ("no rng", lambda s, v: s.pop("rng"), None, "rng is missing: a resume needs it"),
    ("rollout size", _set("pending_rollout"), {"data": {}, "batch_size": [1, -3]}, "pending_rollout.batch_size=[1, -3]; expected [envs, steps]"),
    ("rollout key", _set("pending_rollout"), {"data": {"observation": torch.zeros(1, 4, 3), "action": torch.zeros(1, 4, 2), "action_log_prob": torch.zeros(1, 4), "next": {"done": torch.zeros(1, 4, 1)}}, "batch_size": [1, 4]}, "pending_rollout.data.next.reward is missing: the update reads it"),
    ("rollout shape", _set("pending_rollout"), {"data": {"observation": torch.zeros(1, 4, 3), "action": torch.zeros(1, 5, 2), "action_log_prob": torch.zeros(1, 4)}, "batch_size": [1, 4]}, "pending_rollout.data.action is tensor("),
]  # fmt: skip


@pytest.mark.parametrize(
    ("change", "value", "names"), [f[1:] for f in FIELDS], ids=[f[0] for f in FIELDS]
)
def test_a_field_out_of_type_or_range_is_refused_like_a_corrupt_checkpoint(
    run_dir, tmp_path, caplog, change, value, names
):
    """The file is named like the run's step-512 checkpoint: a resume falls back to step 256,
    naming it; loading it alone is a ValueError naming the file and the field."""
    ckpts = shutil.copytree(run_dir / "checkpoints", tmp_path / "checkpoints")
    state = _state(run_dir)
    change(state, value)
    path = save_checkpoint(_ckpts(tmp_path)[-1], state)
    with caplog.at_level("WARNING"):
        good = latest_good_checkpoint(ckpts, move_aside=True)
    assert good is not None and good["global_step"] == 256, caplog.text
    assert f"checkpoint {str(path)!r} is unusable: " in caplog.text and names in caplog.text, (
        caplog.text
    )
    assert (ckpts / "corrupt" / path.name).is_file()


def test_eval_of_a_step_of_2_pow_70_is_one_line_exit_2(run_dir, tmp_path):
    state = _state(run_dir)
    state["global_step"] = 2**70
    path = save_checkpoint(tmp_path / "huge_step.pt", state)
    line = _one_line(*_cli("export", path, "--out", tmp_path / "x.pt"))
    assert line.startswith(
        f"rlexp export: checkpoint {str(path)!r} is unusable: global_step=1180591620717411303424; "
        "expected an int in [0, 768000]"
    ), line


def test_the_real_checkpoints_pass_every_check_and_the_files_torch_writes_too(run_dir, tmp_path):
    """The checks refuse nothing rlexp or torch.save writes: both checkpoints load, and a state
    rewritten by the hand-made writer above (no lie) loads equal to the original."""
    for path in _ckpts(run_dir):
        assert load_checkpoint(path, "resume")["global_step"] in (256, 512)
    state = _state(run_dir)
    again = load_checkpoint(_write(tmp_path / "same_step_000000512.pt", state), "resume")
    assert torch.equal(again["policy"][WEIGHT], state["policy"][WEIGHT])
    assert json.dumps(again["config"], sort_keys=True) == json.dumps(
        state["config"], sort_keys=True
    )


def test_pruning_counts_and_deletes_only_files(tmp_path):
    """Not in the issue's text: a directory with the newest checkpoint's name neither crashes the
    pruning after a save (``unlink`` of a directory) nor takes the place of a kept checkpoint."""
    from rlexp.checkpoints.files import prune_checkpoints

    files = [tmp_path / f"run_step_{s:09d}.pt" for s in (256, 512, 768)]
    for f in files:
        f.write_bytes(b"x")
    (tmp_path / "run_step_000001024.pt").mkdir()
    assert prune_checkpoints(tmp_path, keep_last=2, newest=files[-1]) == [files[0]]
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "run_step_000000512.pt", "run_step_000000768.pt", "run_step_000001024.pt"
    ]  # fmt: skip
