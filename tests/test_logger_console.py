"""``logger.console``: the [train] / [eval] summary lines can be turned off; the metrics stay."""

from __future__ import annotations

import json

from conftest import TINY, only_run_dir, run_train


def test_console_false_drops_the_summary_lines_only(tmp_path):
    proc = run_train([*TINY, "logger.console=false"], tmp_path)
    out = proc.stdout + proc.stderr
    assert "[train] step=" not in out and "[eval] step=" not in out, out
    assert "done: 512 env steps" in out  # rlexp's other lines stay
    lines = [
        json.loads(x) for x in (only_run_dir(tmp_path) / "metrics.jsonl").read_text().splitlines()
    ]
    assert any("train/episode_return" in m for m in lines)
    assert any("eval/episode_return" in m for m in lines)
