"""Seconds for ``rlexp runs`` to list many run dirs: the timing tests/test_runs.py does not do.

The test (``test_two_thousand_runs_list_reading_four_small_files_each``) counts the work instead
(files opened, parsed, dirs listed), so that a loaded machine cannot fail it; this script times the
same listing: ``--runs`` synthetic run dirs (config.yaml as rlexp writes it, the default config;
status, heartbeat, provenance and overrides as a finished run leaves them), read, filtered on task
and algorithm, sorted and formatted; then a ``--where`` filter on another config key, which reads
every config.yaml. The medians of ``--repeats`` rounds, in a temporary dir.

    PYTHONPATH=src .venv/bin/python benchmarks/runs_list.py --runs 2000 --repeats 5
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))


def make_runs(root: Path, count: int) -> None:
    """``count`` finished run dirs under ``root/multirun/s<k>/<i>``."""
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from rlexp.config.schema import register_configs

    register_configs()
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        config_yaml = OmegaConf.to_yaml(compose(config_name="config", overrides=["env=hopper"]))
    now = time.time()
    for i in range(count):
        run = root / "multirun" / f"s{i // 100}" / str(i % 100)
        (run / ".hydra").mkdir(parents=True)
        (run / "config.yaml").write_text(config_yaml.replace("seed: 0", f"seed: {i}", 1))
        (run / ".hydra" / "overrides.yaml").write_text(f"- env=hopper\n- seed={i}\n")
        prov = {
            "git_commit": "0123456789abcdef",
            "host": "node-7",
            "start_time": "2026-11-20T10:00:00+0000",
        }
        (run / "provenance.json").write_text(json.dumps(prov))
        status = {"state": "finished", "global_step": 1000, "time": "2026-11-20T10:05:00+0000"}
        status["final_eval"] = {"eval/episode_return": float(i % 50)}
        (run / "status.json").write_text(json.dumps(status))
        beat = {"time": now, "global_step": 1000, "total": 1000, "best": float(i), "pid": 4242,
                "best_metric": "eval/episode_return", "task": "Hopper-v5", "algorithm": "ppo"}  # fmt: skip
        (run / "heartbeat.json").write_text(json.dumps(beat))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--runs", type=int, default=2000)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    from rlexp.analysis import runs

    with tempfile.TemporaryDirectory() as tmp:
        make_runs(Path(tmp), args.runs)
        os.chdir(tmp)
        listing, where = [], []
        for _ in range(args.repeats):
            start = time.perf_counter()
            rows = runs.read_runs([Path("multirun")])
            rows = runs.select(rows, ["env.name=Hopper-v5", "algorithm.name=ppo"])
            [runs.cells(r) for r in runs.sort_runs(rows, "-best")]
            listing.append(time.perf_counter() - start)
            start = time.perf_counter()
            runs.select(rows, ["seed=1?"])
            where.append(time.perf_counter() - start)
    print(f"{args.runs} runs, {args.repeats} rounds (median, min-max):")
    print(f"  list, filter on task/algorithm, sort: {statistics.median(listing):.2f} s "
          f"({min(listing):.2f}-{max(listing):.2f})")  # fmt: skip
    print(f"  --where on another config key: +{statistics.median(where):.2f} s "
          f"({min(where):.2f}-{max(where):.2f})")  # fmt: skip


if __name__ == "__main__":
    main()
