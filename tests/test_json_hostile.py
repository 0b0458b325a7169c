"""Hostile paths and contents given as a JSON experiment file: each gives one line and exit 2.

A symlink loop, a directory, a FIFO, a device, a huge file, bytes that are not UTF-8, JSON nested
100,000 deep, a task-file path with a NUL byte: none may hang, raise a traceback (RecursionError
included) or create a run dir.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
from pathlib import Path

import pytest

from conftest import REPO, run_train
from rlexp.config.json_format import MAX_DEPTH, MAX_FILE_BYTES
from rlexp.launch import json_entry

EXAMPLE = REPO / "examples" / "json" / "cart_pole"


def _pair(folder: Path, **trainer) -> Path:
    """The cart_pole example pair copied into ``folder``, with ``trainer`` keys changed."""
    folder.mkdir(parents=True, exist_ok=True)
    train = json.loads((EXAMPLE / "train_config.json").read_text())
    train["trainer"].update(trainer)
    shutil.copy(EXAMPLE / "gym_config.json", folder / "gym_config.json")
    path = folder / "train_config.json"
    path.write_text(json.dumps(train))
    return path


def _one_line(path: str, monkeypatch, capsys, cwd: Path) -> str:
    """Run ``train.py --config-json path`` in this process; the single stderr line (exit 2, no files)."""
    cwd.mkdir(exist_ok=True)
    monkeypatch.chdir(cwd)
    monkeypatch.setattr("sys.argv", ["train.py"])

    def too_slow(*_):
        raise TimeoutError(f"reading {path!r} blocked")

    old = signal.signal(signal.SIGALRM, too_slow)
    signal.alarm(60)  # a FIFO opened for reading without a writer would block forever
    try:
        with pytest.raises(SystemExit) as exit_info:
            json_entry.main(["--config-json", path, "trainer.iterations=1"])
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("config error: "), err
    assert "Traceback" not in err
    assert list(cwd.iterdir()) == [], "a run dir (or anything else) was created"
    return lines[0]


def test_symlink_loop(tmp_path, monkeypatch, capsys):
    (tmp_path / "a.json").symlink_to(tmp_path / "b.json")
    (tmp_path / "b.json").symlink_to(tmp_path / "a.json")
    line = _one_line(str(tmp_path / "a.json"), monkeypatch, capsys, tmp_path / "cwd")
    assert line.startswith(f"config error: {tmp_path / 'a.json'}: cannot be read")
    assert "symbolic links" in line


def test_symlink_to_itself_as_the_task_file(tmp_path, monkeypatch, capsys):
    path = _pair(tmp_path / "files", gym_config="loop.json")
    (tmp_path / "files" / "gym_config.json").unlink()
    (tmp_path / "files" / "loop.json").symlink_to(tmp_path / "files" / "loop.json")
    line = _one_line(str(path), monkeypatch, capsys, tmp_path / "cwd")
    assert "trainer.gym_config='loop.json': task file not found" in line
    assert "not a regular file" in line


def test_directory(tmp_path, monkeypatch, capsys):
    folder = tmp_path / "configs"
    folder.mkdir()
    line = _one_line(str(folder), monkeypatch, capsys, tmp_path / "cwd")
    assert line == (
        f"config error: {folder}: is a directory; give the train file in it "
        f"(e.g. {folder / 'train_config.json'})"
    )


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs on this OS")
def test_fifo(tmp_path, monkeypatch, capsys):
    os.mkfifo(tmp_path / "pipe.json")
    line = _one_line(str(tmp_path / "pipe.json"), monkeypatch, capsys, tmp_path / "cwd")
    assert "is not a regular file (a FIFO)" in line


def test_device(tmp_path, monkeypatch, capsys):
    line = _one_line("/dev/zero", monkeypatch, capsys, tmp_path / "cwd")
    assert line.startswith("config error: /dev/zero: is not a regular file (a character device)")


def test_huge_file(tmp_path, monkeypatch, capsys):
    path = tmp_path / "huge.json"
    with path.open("w") as f:  # valid JSON, just far too big for an experiment file
        f.write('{"trainer": {"exp_name": "')
        f.write("x" * MAX_FILE_BYTES)
        f.write('"}}')
    line = _one_line(str(path), monkeypatch, capsys, tmp_path / "cwd")
    assert f"is {path.stat().st_size} bytes" in line and "at most 4 MiB" in line


def test_not_utf8(tmp_path, monkeypatch, capsys):
    path = tmp_path / "latin1.json"
    path.write_bytes('{"trainer": {\n  "exp_name": "café"}}'.encode("latin-1"))
    line = _one_line(str(path), monkeypatch, capsys, tmp_path / "cwd")
    assert "is not UTF-8 text (byte 0xe9 at line 2); save it as UTF-8" in line


def test_utf8_byte_order_mark_is_accepted(tmp_path, monkeypatch):
    """Editors on Windows write a BOM: the file is still UTF-8 JSON."""
    path = _pair(tmp_path / "files")
    path.write_bytes(b"\xef\xbb\xbf" + path.read_bytes())
    monkeypatch.chdir(tmp_path)
    from rlexp.config.json_format import load_json_experiment

    assert load_json_experiment(path).root["trainer"]["exp_name"] == "cart_pole_ppo"


@pytest.mark.parametrize(
    "text",
    [
        "[" * 100_000 + "]" * 100_000,
        '{"a":' * 100_000 + "1" + "}" * 100_000,
        '{"trainer": ' + "[" * 100_000,  # deep and truncated
    ],
    ids=["lists", "objects", "truncated"],
)
def test_deeply_nested(text, tmp_path, monkeypatch, capsys):
    path = tmp_path / "deep.json"
    path.write_text(text)
    line = _one_line(str(path), monkeypatch, capsys, tmp_path / "cwd")
    assert f"nested more than {MAX_DEPTH} levels deep (line 1)" in line


def test_deep_inside_a_string_is_data(tmp_path, monkeypatch):
    """Brackets inside strings (escaped quotes included) do not count as nesting."""
    from rlexp.config.json_format import load_json_experiment

    path = _pair(tmp_path / "files", wandb_project_name='p\\"' + "[{" * 1000)
    monkeypatch.chdir(tmp_path)
    exp = load_json_experiment(path)
    assert exp.root["logger"]["wandb"]["project"] == 'p\\"' + "[{" * 1000


def test_nested_just_too_deep_in_the_task_file(tmp_path, monkeypatch, capsys):
    path = _pair(tmp_path / "files")
    gym = json.loads((tmp_path / "files" / "gym_config.json").read_text())
    deep: object = 1
    for _ in range(MAX_DEPTH):
        deep = {"a": deep}
    gym["env"]["extensions"]["deep"] = deep
    (tmp_path / "files" / "gym_config.json").write_text(json.dumps(gym, indent=1))
    line = _one_line(str(path), monkeypatch, capsys, tmp_path / "cwd")
    gym_path = (tmp_path / "files" / "gym_config.json").resolve()
    assert line.startswith(f"config error: {gym_path}: JSON nested more than {MAX_DEPTH} levels")


@pytest.mark.parametrize(
    ("ref", "expected"),
    [
        ("gym\u0000config.json", "trainer.gym_config='gym\\x00config.json': task file not found"),
        ("x" * 5000 + ".json", "task file not found"),
        ("~no_such_user_rlexp/gym_config.json", "task file not found"),
    ],
    ids=["nul-byte", "name-too-long", "unknown-user-home"],
)
def test_odd_task_file_paths(ref, expected, tmp_path, monkeypatch, capsys):
    path = _pair(tmp_path / "files", gym_config=ref)
    (tmp_path / "files" / "gym_config.json").unlink()
    line = _one_line(str(path), monkeypatch, capsys, tmp_path / "cwd")
    assert expected in line


def test_nul_byte_in_the_file_path(tmp_path, monkeypatch, capsys):
    line = _one_line("train\u0000config.json", monkeypatch, capsys, tmp_path / "cwd")
    assert "cannot be read" in line


@pytest.mark.parametrize("kind", ["symlink-loop", "deep"])
def test_hostile_files_on_the_command_line(kind, tmp_path):
    """The real command line: one line on stderr, exit 2, no traceback, nothing written."""
    if kind == "symlink-loop":
        (tmp_path / "train_config.json").symlink_to("train_config.json")
        expected = "cannot be read"
    else:
        (tmp_path / "train_config.json").write_text("[" * 100_000 + "]" * 100_000)
        expected = f"nested more than {MAX_DEPTH} levels deep"
    proc = run_train(["--config-json", "train_config.json"], cwd=tmp_path, check=False, timeout=120)
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("config error: train_config.json: "), proc.stderr
    assert expected in lines[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["train_config.json"]
