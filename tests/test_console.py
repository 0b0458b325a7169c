"""The console while the progress bar is live: log lines print above the bar, never into its line,
and the bar ends at the real step count (``1536/1300`` when the last batch overshoots the budget).
Checked on a rich console that believes it is a terminal, and end to end on a pseudo-terminal,
replayed through a small terminal model (what a person would see on the screen)."""

from __future__ import annotations

import io
import logging
import os
import pty
import re
import select
import struct
import sys

import pytest

from conftest import REPO, Children

#: Hydra's console format (hydra/job_logging/default.yaml).
HYDRA_FORMAT = "[%(asctime)s][%(name)s][%(levelname)s] - %(message)s"
_TOKEN = re.compile(r"\x1b\[([0-9;?]*)([A-Za-z])|\r|\n|[^\x1b\r\n]+")


def screen(raw: str) -> list[str]:
    """The lines a terminal shows after printing ``raw``: text, carriage return, newline, cursor
    up (``ESC[nA``) and erase in line (``ESC[nK``); colours and other escapes are dropped."""
    lines, row, col = [""], 0, 0
    for m in _TOKEN.finditer(raw):
        tok = m.group(0)
        if tok == "\r":
            col = 0
        elif tok == "\n":
            row, col = row + 1, 0
            if row == len(lines):
                lines.append("")
        elif tok.startswith("\x1b["):
            arg, cmd = m.group(1), m.group(2)
            if cmd == "A":
                row = max(0, row - int(arg or 1))
            elif cmd == "K":
                lines[row] = "" if arg == "2" else lines[row][:col]
        else:
            line = lines[row].ljust(col)
            lines[row] = line[:col] + tok + line[col + len(tok) :]
            col += len(tok)
    return [line.rstrip() for line in lines]


def is_bar(line: str) -> bool:
    return bool(re.search(r"\d+/\d+ steps .* sps", line))


def is_log(line: str) -> bool:
    return bool(re.search(r"\[\d{4}-\d\d-\d\d [\d:,]+\]\[[\w.]+\]\[[A-Z]+\] - ", line))


def check_screen(lines: list[str]) -> None:
    """Each log line on a line of its own, from its first column; never a bar on it."""
    logs = [x for x in lines if is_log(x)]
    assert logs, lines
    for line in logs:
        assert not is_bar(line), f"a log line drawn into the bar: {line!r}"
        assert line.startswith("["), f"a log line not at the start of its line: {line!r}"


class FakeTerminal(io.StringIO):
    """A handler stream that says it is a terminal (as Hydra's console handler's stdout is)."""

    def isatty(self) -> bool:
        return True


def test_log_records_print_above_the_bar_and_the_bar_ends_at_the_real_count(tmp_path):
    from rich.console import Console

    from rlexp.run.progress import Progress

    drawn = io.StringIO()
    console = Console(file=drawn, force_terminal=True, width=150, color_system="standard")
    terminal = FakeTerminal()
    console_handler = logging.StreamHandler(terminal)
    file_handler = logging.FileHandler(tmp_path / "train.log")
    log = logging.getLogger("rlexp.test_console")
    for h in (console_handler, file_handler):
        h.setFormatter(logging.Formatter(HYDRA_FORMAT))
        log.addHandler(h)
    log.setLevel(logging.INFO)
    try:
        with Progress(1300, console=console) as progress:
            for step in (256, 512, 768, 1024, 1280, 1536):  # the last batch overshoots 1300
                progress.update(step, 600.0, 7.5)
                log.info("[train] step=%d sps=600 return(100)=7.50", step)
            assert console_handler.stream is not terminal  # through the bar's console meanwhile
            assert file_handler.stream.name == str(tmp_path / "train.log")
        log.info("done: 1536 env steps")
    finally:
        for h in (console_handler, file_handler):
            log.removeHandler(h)
            h.close()
    # the terminal stream got only the line after the bar ended; the file got every line
    assert console_handler.stream is terminal
    assert terminal.getvalue().endswith("- done: 1536 env steps\n")
    assert terminal.getvalue().count("\n") == 1
    assert (tmp_path / "train.log").read_text().count("\n") == 7
    lines = screen(drawn.getvalue())
    check_screen(lines)
    assert [x.split(" - ")[1] for x in lines if is_log(x)] == [
        f"[train] step={s} sps=600 return(100)=7.50" for s in (256, 512, 768, 1024, 1280, 1536)
    ]
    bars = [x for x in lines if is_bar(x)]
    assert len(bars) == 1 and "1536/1300 steps" in bars[0], lines


def test_the_bar_is_off_without_a_terminal(monkeypatch):
    from rlexp.run.progress import Progress

    monkeypatch.setattr(sys.stderr, "isatty", lambda: False, raising=False)
    with Progress(100) as progress:
        progress.update(50, 1.0, None)
    assert progress._bar is None


def run_on_pty(args: list[str], cwd, timeout: float = 240) -> str:
    """``python train.py ARGS`` with stdin/stdout/stderr on a pseudo-terminal (160 x 40): all it
    drew, as a terminal received it."""
    import fcntl
    import termios

    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 40, 160, 0, 0))
    env = {**os.environ, "PYTHONPATH": str(REPO / "src"), "TERM": "xterm-256color"}
    for var in ("NO_COLOR", "FORCE_COLOR", "COLUMNS", "LINES", "CI", "TTY_COMPATIBLE"):
        env.pop(var, None)
    out = bytearray()
    with Children() as children:  # its process group is killed when this returns or fails
        proc = children.popen(
            [sys.executable, str(REPO / "train.py"), *args],
            stdin=slave,
            stdout=slave,
            stderr=slave,
            cwd=cwd,
            env=env,
        )
        os.close(slave)
        try:
            while True:
                ready, _, _ = select.select([master], [], [], 1.0)
                if ready:
                    try:
                        data = os.read(master, 65536)
                    except OSError:  # the child closed the terminal (EIO)
                        break
                    if not data:
                        break
                    out += data
                elif proc.poll() is not None:
                    break
            proc.wait(timeout=timeout)
        finally:
            os.close(master)
    assert proc.returncode == 0, out.decode(errors="replace")[-3000:]
    return out.decode(errors="replace")


def test_train_on_a_terminal_keeps_log_lines_out_of_the_bar(tmp_path):
    args = [
        "env=inverted_pendulum",
        "trainer.total_frames=1300",  # 6 batches of 256: 1536 steps
        "trainer.frames_per_batch=256",
        "algorithm.num_epochs=1",
        "trainer.eval_every=512",
        "trainer.eval_episodes=2",
        "logger=none",
    ]
    raw = run_on_pty(args, tmp_path)
    lines = screen(raw)
    check_screen(lines)
    trains = [x for x in lines if "[train] step=" in x]
    assert len(trains) >= 3, lines  # the run's [train] lines, each whole on its line
    bars = [x for x in lines if is_bar(x)]
    if not bars:
        pytest.fail(f"no progress bar on the terminal:\n{raw[-2000:]!r}")
    assert "1536/1300 steps" in bars[-1], bars
    done = next(i for i, x in enumerate(lines) if "done: 1,536 env steps" in x)
    assert lines.index(bars[-1]) < done  # the bar's last state stays above the lines after it
