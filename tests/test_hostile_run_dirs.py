"""One damaged or hostile run dir never breaks ``rlexp runs`` / ``report`` / ``compare`` (#29 items
5 and 6): a good run next to it lists with its values, the bad one is named in one warning line;
memory stays bounded (a 2 GB line, the curve bootstrap of a 500-job sweep); symlinked run dirs and
date dirs are listed, once each, and a symlink loop ends.

The run dirs are written by hand in the format a real run writes (a run of ``train.py
env=inverted_pendulum trainer.total_frames=512 trainer.frames_per_batch=256 ...``), so no test
trains. Cases that hang or eat memory on a reader without bounds (a FIFO, ``/dev/zero``, a YAML
alias bomb) run the CLI in a child with a memory limit and a timeout."""

from __future__ import annotations

import json
import logging
import os
import socket
import subprocess
import sys
import tracemalloc
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from conftest import REPO
from rlexp.analysis import compare, runs, stats

HOST = socket.gethostname()
T0 = "2026-11-20T10:00:00+0000"
T0_EPOCH = 1795168800.0  # T0 as epoch seconds
ENV = "InvertedPendulum-v5"
COMMIT = "36d0b26e0749fa83a89cb98e7bc74cce3235ce4b"
#: Seconds a child CLI may take (a FIFO read without O_NONBLOCK blocks forever).
TIMEOUT = 60
#: Address space a child CLI may take (an unbounded read of /dev/zero takes it all).
CHILD_MEMORY = 4 << 30

CONFIG = """seed: {seed}
trainer:
  exp_name: {env}_ppo
  total_frames: 512
  iterations: null
  frames_per_batch: 256
  device: cpu
  eval_every: 256
  eval_episodes: 2
  resume: auto
  best_metric: eval/episode_return
policy:
  name: actor_critic
  actor:
    hidden_sizes:
    - 64
    - 64
    activation: tanh
algorithm:
  name: ppo
  gamma: 0.99
  lr: 0.0003
  adam_eps: 1.0e-05
  num_epochs: 1
env:
  name: {env}
  backend: gymnasium
  num_envs: 1
  kwargs: {{}}
logger:
  jsonl: true
hooks: {{}}
"""


def write_run(
    path: Path,
    final: float = 24.0,
    seed: int = 0,
    state: str = "finished",
    step: int = 512,
    host: str = "node-7",
    pid: int = 4242,
) -> Path:
    """A run dir as ``train.py`` leaves it (the files ``rlexp runs``/``report``/``compare`` read)."""
    (path / ".hydra").mkdir(parents=True)
    overrides = ["env=inverted_pendulum", f"seed={seed}", "trainer.total_frames=512"]
    (path / ".hydra" / "overrides.yaml").write_text("".join(f"- {o}\n" for o in overrides))
    (path / "config.yaml").write_text(CONFIG.format(seed=seed, env=ENV))
    (path / ".hydra" / "config.yaml").write_text(CONFIG.format(seed=seed, env=ENV))
    prov = {
        "versions": {"python": "3.11.7", "rlexp": "0.1.0"},
        "git_commit": COMMIT,
        "git_dirty": False,
        "project": None,
        "host": host,
        "device": "cpu",
        "argv": ["train.py", *overrides, f"hydra.run.dir={path}"],
        "start_time": T0,
    }
    (path / "provenance.json").write_text(json.dumps(prov, indent=2))
    evals = {"eval/episode_return": final, "eval/episode_return_std": 5.0}
    status = {
        "state": state,
        "global_step": step,
        "final_eval": evals if state != "running" else {},
    }
    status |= {"time": "2026-11-20T10:05:00+0000", "pid": pid, "host": host, "env_resume": None}
    (path / "status.json").write_text(json.dumps(status, indent=2))
    beat = {"host": host, "pid": pid, "pid_start_ticks": 883621, "boot_id": "b-1"}
    beat |= {"interval_s": 10.0, "time": T0_EPOCH + 300, "task": ENV, "algorithm": "ppo"}
    beat |= {"global_step": step, "total": 512, "best_metric": "eval/episode_return"}
    beat |= {"best": final, "last_eval": evals}
    (path / "heartbeat.json").write_text(json.dumps(beat))
    rows = []
    for k, at in enumerate((256, 512), 1):
        rows.append({"step": at, "time": T0_EPOCH + k, "loss/policy": -0.001, "perf/sps": 4000.0})
        rows.append({"step": at, "time": T0_EPOCH + k, "eval/episode_return": final - 2 + k})
    (path / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    return path


def dead_pid() -> int:
    proc = subprocess.Popen(["true"])
    proc.wait()
    return proc.pid


# -- the damage, one function per case --------------------------------------------------------------
def _status(**fields) -> Callable[[Path], None]:
    """Rewrite ``status.json`` with ``fields`` changed (written as Python's json writes them)."""

    def damage(d: Path) -> None:
        status = json.loads((d / "status.json").read_text()) | fields
        (d / "status.json").write_text(json.dumps(status))

    return damage


def _text(name: str, content: str | bytes) -> Callable[[Path], None]:
    def damage(d: Path) -> None:
        path = d / name
        path.unlink(missing_ok=True)
        path.write_bytes(content if isinstance(content, bytes) else content.encode())

    return damage


def _running_here(d: Path) -> None:
    """status.json says running on this host, by a process that is gone."""
    _status(state="running", host=HOST, pid=dead_pid(), final_eval={})(d)


def _beat(**fields) -> Callable[[Path], None]:
    """A running run on this host whose process is gone, with a heartbeat of ``fields``."""

    def damage(d: Path) -> None:
        _running_here(d)
        beat = json.loads((d / "heartbeat.json").read_text()) | {"host": HOST, "time": 1e9}
        (d / "heartbeat.json").write_text(json.dumps(beat | fields))

    return damage


def _running_elsewhere_with_metrics(content: str | bytes | None, kind: str = "") -> Callable:
    """A run whose status says running on another host, without a heartbeat: ``rlexp runs`` reads
    the end of its metrics.jsonl (``content``, or a FIFO / a dir with that name)."""

    def damage(d: Path) -> None:
        _status(state="running", final_eval={})(d)
        (d / "heartbeat.json").unlink()
        (d / "metrics.jsonl").unlink()
        if kind == "fifo":
            os.mkfifo(d / "metrics.jsonl")
        elif kind == "dir":
            (d / "metrics.jsonl").mkdir()
        else:
            _text("metrics.jsonl", content)(d)

    return damage


def _sparse(name: str, size: int) -> Callable[[Path], None]:
    def damage(d: Path) -> None:
        (d / name).unlink(missing_ok=True)
        with open(d / name, "wb") as f:
            f.truncate(size)

    return damage


def _fifo(name: str) -> Callable[[Path], None]:
    def damage(d: Path) -> None:
        (d / name).unlink()
        os.mkfifo(d / name)

    return damage


def _symlink(name: str, target: str) -> Callable[[Path], None]:
    def damage(d: Path) -> None:
        (d / name).unlink()
        (d / name).symlink_to(target)

    return damage


def _no_heartbeat(damage: Callable[[Path], None]) -> Callable[[Path], None]:
    """``damage``, and no heartbeat.json: task and algorithm come from the config."""

    def both(d: Path) -> None:
        (d / "heartbeat.json").unlink()
        damage(d)

    return both


def _a_dir(name: str) -> Callable[[Path], None]:
    def damage(d: Path) -> None:
        (d / name).unlink()
        (d / name).mkdir()

    return damage


def _beat_file(content: str) -> Callable[[Path], None]:
    """A running run on this host whose process is gone, with ``content`` as its heartbeat."""

    def damage(d: Path) -> None:
        _running_here(d)
        (d / "heartbeat.json").write_text(content)

    return damage


def _prov(**fields) -> Callable[[Path], None]:
    def damage(d: Path) -> None:
        prov = json.loads((d / "provenance.json").read_text()) | fields
        (d / "provenance.json").write_text(json.dumps(prov))

    return damage


def _billion_laughs_mapping() -> str:
    """A 1 kB YAML whose mappings, walked, hold 9**9 leaves (rlexp never writes an alias)."""
    lines = ["l0: &l0 {" + ", ".join(f"k{i}: lol" for i in range(9)) + "}"]
    for level in range(1, 10):
        keys = ", ".join(f"k{i}: *l{level - 1}" for i in range(9))
        lines.append(f"l{level}: &l{level} {{{keys}}}")
    return "\n".join(lines) + "\n"


def _billion_laughs_list() -> str:
    lines = ["- &l0 [lol, lol, lol, lol, lol, lol, lol, lol, lol]"]
    lines += [f"- &l{n} [{', '.join([f'*l{n - 1}'] * 9)}]" for n in range(1, 10)]
    return "\n".join(lines) + "\n"


def _deep_json(depth: int = 100_000) -> str:
    return "[" * depth + "]" * depth


#: name -> (damage, status the bad run shows, words its warning holds). In-process: these never
#: hang, and at most take a little memory, on a reader without bounds.
RUNS_CASES = {
    "status_nested_100k_deep": (_text("status.json", _deep_json()), "unknown", "nested"),
    "status_a_json_list": (_text("status.json", '[{"state": "finished"}]'), "unknown", "array"),
    "status_step_minus_5": (_status(global_step=-5), "unknown", "global_step -5"),
    "status_step_10_400": (_status(global_step=10**400), "unknown", "global_step"),
    "status_step_1e308": (_status(global_step=1e308), "unknown", "global_step 1e+308"),
    "status_step_abc": (_status(global_step="abc"), "unknown", "global_step 'abc'"),
    "status_step_nan": (_status(global_step=float("nan")), "unknown", "global_step nan"),
    "status_state_an_object": (_status(state={"a": 1}), "unknown", "state"),
    "status_final_eval_a_list": (_status(final_eval=[1, 2]), "unknown", "final_eval"),
    "status_final_eval_10_400": (_status(final_eval={"x": 10**400}), "unknown", "final_eval"),
    "status_a_directory": (_a_dir("status.json"), "unknown", "directory"),
    "status_50_MB": (_sparse("status.json", 50 << 20), "unknown", "too large"),
    "status_not_utf8": (_text("status.json", b"\xff\xfe{\x00"), "unknown", "not JSON"),
    "heartbeat_pid_a_string": (_beat(pid="4242"), "died", "heartbeat.json: pid '4242'"),
    "heartbeat_pid_10_30": (_beat(pid=10**30), "died", "heartbeat.json: pid"),
    "heartbeat_interval_minus_1": (_beat(interval_s=-1), "died", "interval_s -1"),
    "heartbeat_time_a_list": (_beat(time=[1]), "died", "heartbeat.json: time"),
    "heartbeat_a_number": (_beat_file("7"), "died", "heartbeat.json"),
    "config_python_object_tag": (
        _no_heartbeat(_text("config.yaml", "seed: !!python/object/apply:os.getpid []\n")),
        "finished",
        "config.yaml",
    ),
    "config_a_list": (_no_heartbeat(_text("config.yaml", "- a\n- b\n")), "finished", "config"),
    "config_a_float_tag_abc": (
        _no_heartbeat(_text("config.yaml", "seed: !!float abc\n")),
        "finished",
        "config.yaml",
    ),
    "status_a_symlink_loop": (_symlink("status.json", "status.json"), "unknown", "symbolic"),
    "overrides_a_mapping": (
        _text(".hydra/overrides.yaml", "seed: 1\nenv: x\n"),
        "finished",
        "overrides.yaml",
    ),
    "provenance_host_a_list": (
        _prov(host=["a"]),
        "finished",
        "provenance.json: host",
    ),
    "metrics_step_10_400": (
        _running_elsewhere_with_metrics('{"step": 1' + "0" * 400 + ', "eval/episode_return": 1}\n'),
        "running?",
        "metrics.jsonl",
    ),
    "metrics_step_5000_digits": (
        _running_elsewhere_with_metrics('{"step": ' + "9" * 5000 + "}\n"),
        "running?",
        "metrics.jsonl",
    ),
    "metrics_a_directory": (_running_elsewhere_with_metrics(None, "dir"), "running?", "directory"),
}


#: Cases that hang or exhaust memory on a reader without bounds: run in a child, with limits.
CHILD_CASES = {
    "status_a_fifo": (_fifo("status.json"), "unknown", "FIFO"),
    "status_a_symlink_to_dev_zero": (
        _symlink("status.json", "/dev/zero"),
        "unknown",
        "character device",
    ),
    "metrics_a_fifo": (_running_elsewhere_with_metrics(None, "fifo"), "running?", "FIFO"),
    "config_alias_bomb": (
        _no_heartbeat(_text("config.yaml", _billion_laughs_mapping())),
        "finished",
        "alias",
    ),
    "overrides_alias_bomb": (
        _text(".hydra/overrides.yaml", _billion_laughs_list()),
        "finished",
        "alias",
    ),
}


def good_and_bad(root: Path, damage: Callable[[Path], None]) -> None:
    """Two good runs (finals 24 and 30) and a bad one between them."""
    write_run(root / "good_a", 24.0, seed=0)
    damage(write_run(root / "bad", 27.0, seed=1))
    write_run(root / "good_b", 30.0, seed=2)


def assert_good_runs(rows: dict[str, dict]) -> None:
    for name, final in (("good_a", 24.0), ("good_b", 30.0)):
        row = rows[name]
        assert (row["status"], row["task"], row["algorithm"]) == ("finished", ENV, "ppo"), row
        assert (row["step"], row["total"], row["last"], row["best"]) == (512, 512, final, final)
        assert (row["host"], row["git"], row["start"]) == ("node-7", COMMIT[:8], T0)


def one_warning_naming(warnings: list[str], bad: Path, words: str) -> None:
    assert len(warnings) == 1, warnings
    assert str(bad) in warnings[0] and words in warnings[0], warnings[0]
    assert "\n" not in warnings[0]


def _warnings(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]


def list_runs(root: Path, capsys, caplog) -> tuple[dict[str, dict], list[str], str]:
    """``rlexp runs ROOT`` in-process: the table, then the JSON rows and the warnings."""
    runs.main([str(root)])
    table = capsys.readouterr().out
    caplog.clear()
    runs.main([str(root)], as_json=True)
    rows = {Path(r["path"]).name: r for r in json.loads(capsys.readouterr().out)}
    return rows, _warnings(caplog), table


# -- item 5: rlexp runs -----------------------------------------------------------------------------
@pytest.mark.parametrize("case", sorted(RUNS_CASES))
def test_runs_lists_every_good_run_next_to_a_bad_one_and_names_it_once(
    tmp_path, capsys, caplog, case
):
    damage, shown, words = RUNS_CASES[case]
    good_and_bad(tmp_path, damage)
    rows, warnings, table = list_runs(tmp_path, capsys, caplog)
    assert_good_runs(rows)
    assert "good_a" in table and "good_b" in table and "bad" in table
    assert rows["bad"]["status"] == shown, rows["bad"]
    one_warning_naming(warnings, tmp_path / "bad", words)


def rlexp_child(children, *args: str, cwd: Path) -> subprocess.CompletedProcess:
    """``rlexp ARGS`` in a child limited to CHILD_MEMORY of address space; fails the test if it is
    still running after TIMEOUT seconds (teardown kills it)."""
    code = (
        "import resource, sys; "
        f"resource.setrlimit(resource.RLIMIT_AS, ({CHILD_MEMORY}, {CHILD_MEMORY})); "
        "from rlexp.cli import main; main(sys.argv[1:])"
    )
    env = {**os.environ, "PYTHONPATH": str(REPO / "src")}
    proc = children.popen(
        [sys.executable, "-c", code, *args],
        cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        out, err = proc.communicate(timeout=TIMEOUT)
    except subprocess.TimeoutExpired:
        pytest.fail(f"rlexp {' '.join(args)} still running after {TIMEOUT} s: it hangs")
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)


@pytest.mark.parametrize("case", sorted(CHILD_CASES))
def test_runs_never_hangs_nor_exhausts_memory_on_a_bad_run(tmp_path, children, case):
    damage, shown, words = CHILD_CASES[case]
    good_and_bad(tmp_path, damage)
    table = rlexp_child(children, "runs", str(tmp_path), cwd=tmp_path)
    assert table.returncode == 0 and "Traceback" not in table.stderr, table.stderr[-2000:]
    assert "good_a" in table.stdout and "good_b" in table.stdout and "bad" in table.stdout
    proc = rlexp_child(children, "runs", "--json", str(tmp_path), cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    rows = {Path(r["path"]).name: r for r in json.loads(proc.stdout)}
    assert_good_runs(rows)
    assert rows["bad"]["status"] == shown
    one_warning_naming(proc.stderr.splitlines(), tmp_path / "bad", words)


# -- item 5: rlexp report ---------------------------------------------------------------------------
def sweep_with_a_bad_job(sweep: Path, damage: Callable[[Path], None]) -> None:
    """A 3-job grid (seed=0,1,2): jobs 0 and 2 good (finals 24, 30), job 1 damaged."""
    from omegaconf import OmegaConf

    for num, final in ((0, 24.0), (1, 27.0), (2, 30.0)):
        d = write_run(sweep / str(num), final, seed=num)
        if num == 1:
            damage(d)
    hydra = {
        "sweep": {"dir": str(sweep), "subdir": "${hydra.job.num}"},
        "sweeper": {
            "_target_": "hydra._internal.core_plugins.basic_sweeper.BasicSweeper",
            "max_batch_size": None,
            "params": None,
        },
        "overrides": {"task": ["env=inverted_pendulum", "seed=0,1,2", "trainer.total_frames=512"]},
    }
    (sweep / "multirun.yaml").write_text(OmegaConf.to_yaml(OmegaConf.create({"hydra": hydra})))


def assert_good_jobs_scored(sweep: Path) -> None:
    """Jobs 0 and 2 (finals 24 and 30) are scores of the sweep's one configuration."""
    import csv

    table = list(csv.DictReader((sweep / "report.csv").read_text().splitlines()))
    row = next(r for r in table if "0" in r["seeds"].split())  # job 1 may be a config of its own
    assert {"0", "2"} <= set(row["seeds"].split()), table
    assert float(row["iqm_ci_low"]) <= 24.0 and float(row["iqm_ci_high"]) >= 30.0, row


REPORT_CASES = {
    "status_nested_100k_deep": (_text("status.json", _deep_json()), "nested"),
    "status_step_10_400": (_status(global_step=10**400), "global_step"),
    "status_a_directory": (_a_dir("status.json"), "directory"),
    "status_50_MB": (_sparse("status.json", 50 << 20), "too large"),
    "metrics_step_10_400": (
        _text("metrics.jsonl", '{"step": 1' + "0" * 400 + ', "eval/episode_return": 1}\n'),
        "metrics.jsonl",
    ),
    "metrics_value_10_400": (
        _text("metrics.jsonl", '{"step": 512, "eval/episode_return": 1' + "0" * 400 + "}\n"),
        "metrics.jsonl",
    ),
    "metrics_line_nested_100k_deep": (
        _text("metrics.jsonl", '{"step": 512, "x": ' + _deep_json() + "}\n"),
        "metrics.jsonl",
    ),
    "heartbeat_pid_10_30": (_beat(pid=10**30), "heartbeat.json"),
    "config_python_object_tag": (
        _text("config.yaml", "seed: !!python/object/apply:os.getpid []\n"),
        "config.yaml",
    ),
    "config_alias_bomb": (_text("config.yaml", _billion_laughs_mapping()), "alias"),
    "overrides_a_mapping": (_text(".hydra/overrides.yaml", "seed: 1\nenv: x\n"), "overrides"),
    "provenance_nested_100k_deep": (_text("provenance.json", _deep_json()), "provenance.json"),
}


@pytest.mark.parametrize("case", sorted(REPORT_CASES))
def test_report_counts_the_good_jobs_and_names_the_bad_one_once(tmp_path, caplog, case):
    from rlexp.analysis.report import report

    damage, words = REPORT_CASES[case]
    sweep_with_a_bad_job(tmp_path, damage)
    caplog.clear()
    md = report(tmp_path, plot=False)
    assert "3 jobs expected" in md, md
    assert_good_jobs_scored(tmp_path)
    one_warning_naming(_warnings(caplog), tmp_path / "1", words)


REPORT_CHILD_CASES = {
    "status_a_fifo": (_fifo("status.json"), "FIFO"),
    "metrics_a_fifo": (_fifo("metrics.jsonl"), "FIFO"),
    "metrics_a_symlink_to_dev_zero": (_symlink("metrics.jsonl", "/dev/zero"), "character device"),
    "overrides_alias_bomb": (_text(".hydra/overrides.yaml", _billion_laughs_list()), "alias"),
}


@pytest.mark.parametrize("case", sorted(REPORT_CHILD_CASES))
def test_report_never_hangs_nor_exhausts_memory_on_a_bad_job(tmp_path, children, case):
    damage, words = REPORT_CHILD_CASES[case]
    sweep_with_a_bad_job(tmp_path, damage)
    proc = rlexp_child(children, "report", "--no-plot", str(tmp_path), cwd=tmp_path)
    assert proc.returncode == 0 and "Traceback" not in proc.stderr, proc.stderr[-2000:]
    assert "3 jobs expected" in proc.stdout
    assert_good_jobs_scored(tmp_path)
    warnings = [ln for ln in proc.stderr.splitlines() if not ln.startswith("wrote ")]
    one_warning_naming(warnings, tmp_path / "1", words)


def test_a_multirun_yaml_alias_bomb_leaves_the_plan_unknown(tmp_path, children):
    sweep_with_a_bad_job(tmp_path, lambda d: None)
    (tmp_path / "multirun.yaml").write_text("hydra:\n  x:\n" + "".join(
        "    " + ln + "\n" for ln in _billion_laughs_list().splitlines()
    ))  # fmt: skip
    proc = rlexp_child(children, "report", "--no-plot", str(tmp_path), cwd=tmp_path)
    assert proc.returncode == 0 and "Traceback" not in proc.stderr, proc.stderr[-2000:]
    assert "multirun.yaml is not readable (uses a YAML alias" in proc.stdout


def test_a_2_gb_metrics_line_is_skipped_without_reading_it_into_memory(tmp_path, caplog):
    from rlexp.analysis.reporting.jobs import read_job

    d = write_run(tmp_path / "0")
    with open(d / "metrics.jsonl", "ab") as f:  # 64 MB of one line, no newline (a sparse file)
        f.truncate(f.tell() + (64 << 20))
    with open(d / "metrics.jsonl", "ab") as f:
        f.write(b'\n{"step": 768, "eval/episode_return": 31.5}\n')
    tracemalloc.start()
    try:
        job = read_job(d, "eval/episode_return")
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 8 << 20, f"{peak / 2**20:.0f} MiB to read a 64 MiB line"
    assert job.curve == [(256, 23.0), (512, 24.0), (768, 31.5)]
    assert job.problems == ["metrics.jsonl: 1 line(s) skipped (first: line 5, longer than 1 MiB)"]


# -- item 5: rlexp compare --------------------------------------------------------------------------
COMPARE_CASES = {
    k: RUNS_CASES[k]
    for k in ("status_nested_100k_deep", "status_step_10_400", "heartbeat_pid_10_30")
} | {
    "metrics_line_nested_100k_deep": (
        REPORT_CASES["metrics_line_nested_100k_deep"][0],
        "finished",
        "metrics.jsonl",
    ),
}


@pytest.mark.parametrize("case", sorted(COMPARE_CASES))
def test_compare_scores_the_good_runs_and_names_the_bad_one_once(tmp_path, capsys, caplog, case):
    damage, shown, words = COMPARE_CASES[case]
    good_and_bad(tmp_path, damage)
    caplog.clear()
    compare.main([str(tmp_path)], "eval/episode_return", as_json=True)
    out = json.loads(capsys.readouterr().out)
    by_name = {Path(r["path"]).name: r for r in out["runs"]}
    assert (by_name["good_a"]["final"], by_name["good_b"]["final"]) == (24.0, 30.0)
    assert by_name["bad"]["status"] == shown
    one_warning_naming(_warnings(caplog), tmp_path / "bad", words)


def test_compare_never_hangs_on_a_metrics_fifo(tmp_path, children):
    good_and_bad(tmp_path, _fifo("metrics.jsonl"))
    proc = rlexp_child(children, "compare", "--json", str(tmp_path), cwd=tmp_path)
    assert proc.returncode == 0 and "Traceback" not in proc.stderr, proc.stderr[-2000:]
    by_name = {Path(r["path"]).name: r for r in json.loads(proc.stdout)["runs"]}
    assert (by_name["good_a"]["final"], by_name["good_b"]["final"]) == (24.0, 30.0)
    assert by_name["bad"]["final"] == 27.0  # status.json's final eval: the history is unread
    one_warning_naming(proc.stderr.splitlines(), tmp_path / "bad", "FIFO")


# -- item 5: the curve bootstrap in bounded memory --------------------------------------------------
def _curves() -> list[list[tuple[int, float]]]:
    """Nine runs of 6-8 evals (one logged at other steps) and a flat one."""
    out = []
    for i in range(9):
        off = 50 if i == 8 else 0
        out.append(
            [
                (off + 100 * k, float((i * 7) % 5 + k * (1 + i % 4) + (0.25 if i % 2 else 0.0)))
                for k in range(6 + i % 3)
            ]
        )
    return [*out, [(0, 3.0), (100, 3.0), (200, 3.0)]]


#: iqm_band(_curves(), seed=4) as rlexp computed it before the bootstrap was chunked.
BAND = {
    "steps": [0, 50, 100, 150, 200, 250, 300, 350, 400, 450, 500, 550, 600, 650, 700, 750],
    "center": [2.3, 2.9583333333333335, 3.9583333333333335, 4.958333333333333, 5.958333333333333,
               7.75, 8.9, 10.0, 11.1, 12.2, 13.3, 13.375, 14.375, 14.583333333333334,
               15.583333333333334, 8.0],
    "low": [0.95, 1.75, 2.4166666666666665, 3.0, 3.5416666666666665, 4.35, 5.05, 5.65, 6.3, 7.0,
            7.6, 7.9375, 8.5625, 7.0, 7.5, 8.0],
    "high": [3.4, 4.375, 5.7093749999999845, 7.208333333333333, 8.708333333333334, 11.0, 12.7,
             14.35, 15.95, 17.65249999999996, 19.352499999999967, 21.5625, 23.1875, 23.5, 25.0,
             8.0],
}  # fmt: skip
X = np.array([3.0, 9.5, 1.0, 4.0, 4.0, 7.25, 2.0, 8.0, 6.5, 5.0, 0.5])
A = np.array([5.0, 7.0, 6.5, 9.0, 4.0, 8.0, 7.5, 6.0])
B = np.array([4.0, 6.0, 5.5, 3.0, 6.5, 5.0])


@pytest.mark.parametrize("budget", [None, 150, 2000])
def test_the_bootstraps_in_chunks_equal_the_results_before(monkeypatch, budget):
    if budget is not None:  # small chunks: steps in two slices, one step per call, resamples
        # in batches of 16 (150) or 222 (2000), stratified resamples in chunks of 10 or 142
        monkeypatch.setattr(stats, "BOOT_ELEMENTS", budget)
    steps, center, low, high = stats.iqm_band(_curves(), seed=4)
    assert steps.tolist() == BAND["steps"]
    assert (center.tolist(), low.tolist(), high.tolist()) == (
        BAND["center"],
        BAND["low"],
        BAND["high"],
    )
    assert stats.bootstrap_ci(X, stats.iqm, seed=2) == (2.5, 6.571428571428571)
    diff = stats.stratified_bootstrap(
        A, B, lambda p, q: stats.iqm(p, axis=1) - stats.iqm(q, axis=1)
    )
    assert diff == (-0.125, 3.375)
    assert stats.stratified_bootstrap(A, B, stats._poi_rows, seed=3) == (
        0.5208333333333334,
        0.9895833333333334,
    )


def _address_space_limit(extra: int):
    """Cap this process's address space at its size now + ``extra`` (a regression then fails
    with MemoryError instead of taking the machine); returns the restore function."""
    import resource

    size = next(
        int(ln.split()[1]) * 1024
        for ln in Path("/proc/self/status").read_text().splitlines()
        if ln.startswith("VmSize:")
    )
    old = resource.getrlimit(resource.RLIMIT_AS)
    resource.setrlimit(resource.RLIMIT_AS, (size + extra, old[1]))
    return lambda: resource.setrlimit(resource.RLIMIT_AS, old)


def test_the_bootstraps_of_a_500_job_sweep_stay_under_200_mb():
    """500 seeds of one configuration, 100 evals each: holding steps x resamples x seeds at once
    took 100 x 5000 x 500 x 8 bytes = 2 GB an array; chunked, the peak does not grow with steps."""
    rng = np.random.default_rng(0)
    steps = np.arange(1, 101) * 1000
    walks = rng.normal(size=(500, 100)).cumsum(axis=1)
    curves = [list(zip(steps.tolist(), w.tolist(), strict=True)) for w in walks]
    finals = np.array([c[-1][1] for c in curves])
    stats.iqm_band(curves[:2])  # scipy's imports: not part of the peak measured
    restore = _address_space_limit(3 << 30)
    tracemalloc.start()
    try:
        got_steps, center, low, high = stats.iqm_band(curves)
        ci = stats.bootstrap_ci(finals, stats.iqm)
        pair = stats.stratified_bootstrap(finals[:250], finals[250:], stats._poi_rows)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
        restore()
    assert peak < 200 << 20, f"peak {peak / 2**20:.0f} MiB"
    assert got_steps.tolist() == steps.tolist()
    assert np.all((low <= center) & (center <= high))
    last = np.array([c[-1][1] for c in curves])
    assert (low[-1], high[-1]) == stats.bootstrap_ci(last, stats.iqm) == ci
    assert 0 <= pair[0] <= pair[1] <= 1


# -- item 6: symlinked run dirs and date dirs -------------------------------------------------------
def linked_tree(root: Path) -> Path:
    """outputs/ with a real run, a symlinked run dir, a symlinked date dir, the real run again
    through a link, a loop back to outputs/ and a dangling link."""
    out = root / "outputs"
    write_run(out / "2026-11-20" / "10-00-00", 24.0, seed=0)
    write_run(root / "elsewhere" / "run_b", 30.0, seed=1)
    write_run(root / "elsewhere" / "2026-11-21" / "09-00-00", 27.0, seed=2)
    (out / "2026-11-20" / "linked").symlink_to(root / "elsewhere" / "run_b")
    (out / "2026-11-21").symlink_to(root / "elsewhere" / "2026-11-21")
    (out / "2026-11-20" / "again").symlink_to(out / "2026-11-20" / "10-00-00")
    (out / "loop").symlink_to(out)
    (out / "dangling").symlink_to(root / "nowhere")
    return out


LINKED = ["outputs/2026-11-20/10-00-00", "outputs/2026-11-20/linked", "outputs/2026-11-21/09-00-00"]


def test_runs_follows_symlinked_run_and_date_dirs_once_each(tmp_path, capsys, monkeypatch):
    linked_tree(tmp_path)
    monkeypatch.chdir(tmp_path)
    runs.main([], as_json=True)
    rows = json.loads(capsys.readouterr().out)
    assert sorted(r["path"] for r in rows) == LINKED
    assert sorted(r["last"] for r in rows) == [24.0, 27.0, 30.0]
    runs.main([])
    table = capsys.readouterr().out
    assert all(p in table for p in LINKED) and "3 run(s): 3 finished" in table


def test_compare_follows_symlinked_run_dirs_once_each(tmp_path, capsys, monkeypatch):
    linked_tree(tmp_path)
    monkeypatch.chdir(tmp_path)
    compare.main(["outputs"], "eval/episode_return", as_json=True)
    out = json.loads(capsys.readouterr().out)
    assert sorted(r["label"] for r in out["runs"]) == [p[len("outputs/") :] for p in LINKED]
    assert sorted(r["final"] for r in out["runs"]) == [24.0, 27.0, 30.0]


def test_report_follows_symlinked_job_dirs_once_each(tmp_path):
    from rlexp.analysis.report import report

    sweep = tmp_path / "sweep"
    sweep_with_a_bad_job(sweep, lambda d: None)
    (sweep / "2").rename(tmp_path / "job2")  # job 2 lives elsewhere, linked in
    (sweep / "2").symlink_to(tmp_path / "job2")
    (sweep / "1" / "loop").symlink_to(sweep)
    (sweep / "again").symlink_to(sweep / "0")
    md = report(sweep, plot=False)
    assert "3 jobs expected" in md and "3 finished" in md, md
    assert "Never started" not in md or "## Never started (0)" in md


# -- item 5, a reader the issue does not name: the median stopping rule reads siblings' metrics -------
def test_the_median_stop_rule_reads_a_hostile_siblings_metrics_without_crashing(
    tmp_path, monkeypatch
):
    from rlexp.hooks import builtin

    monkeypatch.setattr(builtin, "SIBLING_READ", 256)  # a read of 256 bytes: the long line spans
    metric = "eval/episode_return"
    lines = [
        json.dumps({"step": 100, metric: 5.0}),
        '{"step": 200, "' + metric + '": 1' + "0" * 400 + "}",  # beyond float's range
        '{"step": 250, "' + metric + '": ' + _deep_json(2000) + "}",
        '{"step": 260, "' + metric + '": 1, "pad": "' + "x" * 600 + '"}',  # longer than a read
        json.dumps({"step": 300, metric: 7.0}),
    ]
    path = tmp_path / "metrics.jsonl"
    path.write_text("\n".join(lines) + "\n")
    rule = builtin.MedianStop(metric)
    looks = [rule._value_at(path, 300) for _ in range(40)]  # each look reads 256 bytes at most
    assert looks[-1] == 7.0 and looks[0] is None
    assert rule._offsets[path][1] == [(100, 5.0), (300, 7.0)]
