"""``rlexp runs`` over a PBT sweep lists each member's current hyperparameters (docs/pbt.md, #45
item 8): the values its ``pbt/lineage.jsonl`` last set (the start record, then each exploit's
``new``), one line per member below the table."""

from __future__ import annotations

import json
from pathlib import Path

from conftest import rlexp_cli


def _member(root: Path, name: str, lineage: list[dict]) -> None:
    run = root / name
    (run / "pbt").mkdir(parents=True)
    (run / "config.yaml").write_text("env:\n  name: Hopper-v5\nalgorithm:\n  name: ppo\n")
    (run / "status.json").write_text(json.dumps({"state": "running", "global_step": 4096}))
    (run / "pbt" / "lineage.jsonl").write_text("".join(json.dumps(r) + "\n" for r in lineage))


def test_runs_lists_each_member_s_current_hyperparameters(tmp_path):
    start = {"event": "start", "step": 0, "hyperparameters": {"lr": 0.0003, "clip_epsilon": 0.2}}
    _member(tmp_path, "0", [start])
    own, copied = {"lr": 0.0003, "clip_epsilon": 0.2}, {"lr": 0.0006, "clip_epsilon": 0.2}
    exploit = {  # a whole record, as hooks/pbt.py writes it (the readers check every field)
        "event": "exploit", "step": 2048, "generation": 1, "member": "1", "score": 10.5,
        "source": "0", "source_step": 2048, "source_score": 55.0, "old": own, "copied": copied,
        "new": {"lr": 0.00045, "clip_epsilon": 0.16},
        "explore": {"lr": "x0.75", "clip_epsilon": "x0.8"},
    }  # fmt: skip
    _member(tmp_path, "1", [start, exploit])
    code, out, err = rlexp_cli("runs", tmp_path)
    assert code == 0, err
    assert "PBT members' current hyperparameters:" in out, out
    lines = {
        Path(line.split(": ")[0].strip()).name: line for line in out.splitlines() if "lr=" in line
    }
    assert lines["0"].endswith(": lr=0.0003, clip_epsilon=0.2"), lines
    assert lines["1"].endswith(": lr=0.00045, clip_epsilon=0.16"), lines
