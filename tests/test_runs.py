"""``rlexp runs``: the table of run dirs, the heartbeat and the died rule (docs/runs.md)."""

from __future__ import annotations

import json
import os
import shlex
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

from conftest import REPO, run_train
from rlexp.analysis import runs
from rlexp.run.rundir import (
    HEARTBEAT_INTERVAL_S,
    Heartbeat,
    process_start_ticks,
    read_heartbeat,
    stale_after,
)

HOST = socket.gethostname()
T0 = "2026-11-20T10:00:00+0000"


def make_run(
    path: Path,
    state: str | None = "finished",
    host: str = "node-7",
    pid: int = 4242,
    beat: dict | None = None,
    env: str = "hopper",
    algo: str = "ppo",
    seed: int = 0,
    final: float | None = 100.0,
    metrics: list[dict] | None = None,
    overrides: list[str] | None = None,
) -> Path:
    """A run dir as rlexp writes it, without training: the small files ``rlexp runs`` reads."""
    (path / ".hydra").mkdir(parents=True)
    cfg = f"seed: {seed}\ntrainer:\n  total_frames: 1000\n  iterations: null\n"
    cfg += "  frames_per_batch: 100\n"
    cfg += f"env:\n  name: {env}\n  num_envs: 1\nalgorithm:\n  name: {algo}\n  lr: 0.0003\n"
    (path / "config.yaml").write_text(cfg)
    ovs = overrides if overrides is not None else [f"env={env}", f"seed={seed}"]
    (path / ".hydra" / "overrides.yaml").write_text("".join(f"- {o}\n" for o in ovs))
    prov = {"git_commit": "0123456789abcdef", "git_dirty": True, "host": host, "start_time": T0}
    prov["argv"] = ["train.py", *ovs]
    (path / "provenance.json").write_text(json.dumps(prov))
    if state is not None:
        status = {"state": state, "global_step": 1000 if state == "finished" else 300}
        status |= {"final_eval": {"eval/episode_return": final} if final is not None else {}}
        status |= {"time": "2026-11-20T10:05:00+0000", "pid": pid, "host": host}
        (path / "status.json").write_text(json.dumps(status))
    if beat is not None:
        (path / "heartbeat.json").write_text(json.dumps({"host": host, "pid": pid, **beat}))
    if metrics is not None:
        (path / "metrics.jsonl").write_text("".join(json.dumps(m) + "\n" for m in metrics))
    return path


def dead_pid() -> int:
    """The PID of a process that has exited and been reaped."""
    proc = subprocess.Popen(["true"])
    proc.wait()
    return proc.pid


def rlexp(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(REPO / "src")}
    return subprocess.run(
        [sys.executable, "-m", "rlexp", *args], cwd=cwd, capture_output=True, text=True, env=env
    )


# -- the died rule ---------------------------------------------------------------------------------
def test_stale_heartbeat_from_another_host_is_died_with_the_resume_command(tmp_path):
    run = make_run(tmp_path / "r", "running", beat={"time": time.time() - 3600, "interval_s": 10})
    row = runs.read_run(run)
    assert row.status == "died"
    assert "no heartbeat for 1h00m" in row.note and "node-7" in row.note
    assert row.resume == (f"python train.py env=hopper seed=0 hydra.run.dir={run.resolve()}")


def test_fresh_heartbeat_from_another_host_is_running(tmp_path):
    run = make_run(tmp_path / "r", "running", beat={"time": time.time() - 5, "global_step": 700})
    row = runs.read_run(run)
    assert (row.status, row.note, row.step, row.resume) == ("running", "", 700, None)


def test_the_stale_limit_follows_the_runs_own_interval(tmp_path):
    assert stale_after(HEARTBEAT_INTERVAL_S) == 3 * HEARTBEAT_INTERVAL_S + 30
    age = stale_after(2.0) + 1  # stale for a run that beats every 2 s, fresh at the default
    run = make_run(tmp_path / "r", "running", beat={"time": time.time() - age, "interval_s": 2.0})
    assert runs.read_run(run).status == "died"
    run2 = make_run(tmp_path / "r2", "running", beat={"time": time.time() - age})
    assert runs.read_run(run2).status == "running"


def test_no_heartbeat_on_another_host_cannot_be_told(tmp_path):
    row = runs.read_run(make_run(tmp_path / "r", "running"))
    assert row.status == "running?" and "node-7" in row.note and row.resume is None


def test_same_host_pid_gone_is_died_with_or_without_heartbeat(tmp_path):
    pid = dead_pid()
    fresh = {"time": time.time(), "pid_start_ticks": 1}
    with_beat = make_run(tmp_path / "a", "running", host=HOST, pid=pid, beat=fresh)
    without = make_run(tmp_path / "b", "running", host=HOST, pid=pid)
    for run in (with_beat, without):
        row = runs.read_run(run)
        assert (row.status, row.note) == ("died", f"PID {pid} is gone; no checkpoint yet")


def test_same_host_pid_reused_by_another_process_is_died(tmp_path):
    me = os.getpid()
    ticks = process_start_ticks(me)
    beat = {"time": time.time(), "pid_start_ticks": ticks + 1}
    row = runs.read_run(make_run(tmp_path / "a", "running", host=HOST, pid=me, beat=beat))
    assert (row.status, row.note) == ("died", f"PID {me} is now another process; no checkpoint yet")
    # No heartbeat: this process started before status.json said running -> could be the run;
    # a status.json written long before this process started -> the PID was reused.
    old = make_run(tmp_path / "b", "running", host=HOST, pid=me)
    assert runs.read_run(old).status == "died"
    status = json.loads((old / "status.json").read_text())
    status["time"] = time.strftime("%Y-%m-%dT%H:%M:%S%z")
    (old / "status.json").write_text(json.dumps(status))
    assert runs.read_run(old).status == "running"


def test_same_host_live_process_with_a_stale_heartbeat_is_stalled(tmp_path):
    me = os.getpid()
    beat = {"time": time.time() - 600, "pid_start_ticks": process_start_ticks(me)}
    row = runs.read_run(make_run(tmp_path / "a", "running", host=HOST, pid=me, beat=beat))
    assert row.status == "stalled" and row.resume is None
    beat["time"] = time.time()
    (tmp_path / "a" / "heartbeat.json").write_text(json.dumps({"host": HOST, "pid": me, **beat}))
    assert runs.read_run(tmp_path / "a").status == "running"


def test_ended_runs_keep_their_state_whatever_the_heartbeat(tmp_path):
    beat = {"time": time.time() - 3600}
    for state in ("finished", "failed", "interrupted", "stopped_early"):
        assert runs.read_run(make_run(tmp_path / state, state, beat=beat)).status == state
    assert runs.read_run(make_run(tmp_path / "none", None)).status == "unknown"


def test_resume_command_keeps_the_json_file_and_resets_resume(tmp_path):
    argv = ["train.py", "--config-json", "exp.json", "+experiment=json_experiment", "x=1"]
    ovs = ["+experiment=json_experiment", "x=1", "trainer.resume=never", "a=[1, 2]"]
    cmd = runs.resume_command(Path("/r"), ovs, argv)
    assert cmd == (
        "python train.py --config-json exp.json x=1 'a=[1, 2]' trainer.resume=auto hydra.run.dir=/r"
    )


# -- the heartbeat ---------------------------------------------------------------------------------
def test_heartbeat_writes_now_every_interval_and_a_last_beat_on_stop(tmp_path):
    step = {"n": 0}
    beat = Heartbeat(tmp_path, lambda: {"global_step": step["n"], "best": float("-inf")}, 0.05)
    beat.start()
    first = read_heartbeat(tmp_path)
    assert (first["host"], first["pid"], first["global_step"]) == (HOST, os.getpid(), 0)
    assert first["pid_start_ticks"] == process_start_ticks(os.getpid())
    assert first["best"] is None and first["interval_s"] == 0.05  # -inf: strict JSON
    step["n"] = 5
    deadline = time.time() + 10
    while read_heartbeat(tmp_path).get("global_step") != 5 and time.time() < deadline:
        time.sleep(0.02)
    assert read_heartbeat(tmp_path)["global_step"] == 5
    step["n"] = 9
    beat.stop()
    assert read_heartbeat(tmp_path)["global_step"] == 9
    assert not beat._thread and not list(tmp_path.glob(".heartbeat*"))


# -- the table -------------------------------------------------------------------------------------
def _ten(root: Path) -> None:
    for i in range(10):
        env = "hopper" if i % 2 else "walker2d"
        make_run(root / "multirun" / "s" / str(i), env=env, seed=i, final=float(i))
    make_run(root / "outputs" / "d" / "t", "failed", final=None, algo="grpo", env="ant")


def test_filters_sort_and_json(tmp_path):
    _ten(tmp_path)
    out = rlexp("runs", "--where", "env.name=hopper", "--sort", "-best", "--json", cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    rows = json.loads(out.stdout)
    assert [r["best"] for r in rows] == [9.0, 7.0, 5.0, 3.0, 1.0]
    assert rows[0]["git"] == "01234567+dirty" and rows[0]["overrides"] == ["env=hopper", "seed=9"]
    assert rows[0]["wall_s"] == 300 and rows[0]["task"] == "hopper"
    rows = json.loads(rlexp("runs", "--status", "failed", "--json", cwd=tmp_path).stdout)
    assert [r["algorithm"] for r in rows] == ["grpo"]
    rows = json.loads(
        rlexp(
            "runs",
            "--where",
            "algorithm.lr=3e-4",
            "--where",
            "seed!=1",
            "--where",
            "env.name=w*",
            "--json",
            cwd=tmp_path,
        ).stdout
    )
    assert sorted(r["path"] for r in rows) == [f"multirun/s/{i}" for i in (0, 2, 4, 6, 8)]


def test_plain_table_and_one_line_errors(tmp_path):
    _ten(tmp_path)
    beat = {"time": time.time() - 999}
    make_run(tmp_path / "outputs" / "d" / "k", "running", beat=beat, overrides=["seed=5"])
    out = rlexp("runs", "--sort", "status,dir", cwd=tmp_path)
    lines = out.stdout.splitlines()
    assert lines[0].split() == list(runs.COLUMNS)
    assert lines[1].split()[:2] == ["outputs/d/k", "died"]
    assert "12 run(s): 1 died, 1 failed, 10 finished" in out.stdout
    resume = f"resume: python train.py seed=5 hydra.run.dir={(tmp_path / 'outputs/d/k').resolve()}"
    assert resume in out.stdout
    for args, message in [
        (["--sort", "bets"], "--sort 'bets': not a column"),
        (["--where", "env.nme=x"], "did you mean 'env.name'?"),
        (["--where", "env.name"], "write KEY=VALUE"),
        (["--status", "dead"], "did you mean 'died'?"),
        (["nowhere"], "nowhere: no such dir"),
    ]:
        out = rlexp("runs", *args, cwd=tmp_path)
        assert out.returncode == 2 and message in out.stderr and len(out.stderr.splitlines()) == 1


def test_best_from_a_metrics_tail_is_marked_when_the_file_is_longer(tmp_path, monkeypatch):
    rows = [{"step": s, "eval/episode_return": float(s % 7), "loss/x": 1} for s in range(200)]
    run = make_run(tmp_path / "r", "running", final=None, metrics=rows)
    assert runs.tail_metric(run / "metrics.jsonl", "eval/episode_return") == (3.0, 6.0, True, 199)
    monkeypatch.setattr(runs, "TAIL_BYTES", 300)
    last, best, exact, step = runs.tail_metric(run / "metrics.jsonl", "eval/episode_return")
    assert (last, exact, step) == (3.0, False, 199) and best <= 6.0
    row = runs.read_run(run)
    assert not row.best_exact and runs.cells(row)[6].startswith(">=")


def _two_thousand_runs(root: Path) -> None:
    """2000 run dirs under ``root/multirun`` with config.yaml as rlexp writes it (the default
    config, ~2 KB) and a heartbeat naming task, algorithm and best (as a live run writes it)."""
    from omegaconf import OmegaConf

    from conftest import compose

    config_yaml = OmegaConf.to_yaml(compose(["env=hopper"]))
    now = time.time()
    for i in range(2000):
        beat = {
            "time": now,
            "global_step": 1000,
            "total": 1000,
            "best": float(i),
            "best_metric": "eval/episode_return",
            "task": "Hopper-v5",
            "algorithm": "ppo",
        }
        run = make_run(
            root / "multirun" / f"s{i // 100}" / str(i % 100),
            beat=beat,
            seed=i,
            final=float(i % 50),
        )
        (run / "config.yaml").write_text(config_yaml.replace("seed: 0", f"seed: {i}", 1))


def test_two_thousand_runs_list_reading_four_small_files_each(tmp_path, monkeypatch):
    """What keeps a listing of thousands of runs at about a second (timed in
    benchmarks/runs_list.py, not here: a timer fails on a loaded machine), counted: the walk lists
    each dir once and never enters a run dir; each run's status.json, heartbeat.json,
    provenance.json and .hydra/overrides.yaml are opened once, as JSON / plain lines; no config.yaml
    (YAML: ~0.5 ms a run) and no metrics.jsonl for the table, a sort and a filter on task and
    algorithm. A filter on another config key reads each config.yaml once, and a second filter
    reads none again."""
    import collections

    from rlexp.files import dirwalk, safe_read

    _two_thousand_runs(tmp_path)
    opened, parsed, listed = collections.Counter(), collections.Counter(), []
    open_regular, parse_yaml, parse_json = (
        safe_read.open_regular,
        safe_read.parse_yaml,
        safe_read.parse_json,
    )
    scandir = os.scandir

    def counting_open(path):
        opened[Path(path).name] += 1
        return open_regular(path)

    def counting_scandir(path):
        listed.append(Path(path))
        return scandir(path)

    monkeypatch.setattr(safe_read, "open_regular", counting_open)
    monkeypatch.setattr(
        safe_read, "parse_yaml", lambda *a, **k: parsed.update(["yaml"]) or parse_yaml(*a, **k)
    )
    monkeypatch.setattr(
        safe_read, "parse_json", lambda *a, **k: parsed.update(["json"]) or parse_json(*a, **k)
    )
    monkeypatch.setattr(dirwalk.os, "scandir", counting_scandir)
    monkeypatch.chdir(tmp_path)
    rows = runs.read_runs([Path("multirun")])
    rows = runs.sort_runs(runs.select(rows, ["env.name=Hopper-v5", "algorithm.name=ppo"]), "-best")
    cells = [runs.cells(r) for r in rows]
    assert len(cells) == 2000 and rows[0].best == 1999.0 and rows[0].task == "Hopper-v5"
    # the walk: multirun/ and its 20 sweep dirs, plus each run dir (to see it is one), once each
    assert len(listed) == len(set(listed)) == 1 + 20 + 2000, len(listed)
    assert not any(p.name == ".hydra" for p in listed)
    assert opened == {
        "status.json": 2000,
        "heartbeat.json": 2000,
        "provenance.json": 2000,
        "overrides.yaml": 2000,
        "config.yaml": 1,  # --where checks that its key is one: found in the first run's config
    }, opened
    # overrides.yaml: plain "- item" lines, no YAML parser
    assert parsed == {"json": 3 * 2000, "yaml": 1}, parsed
    opened.clear(), parsed.clear()
    assert len(runs.select(rows, ["seed=1?"])) == 10  # reads each config.yaml (one was read)
    assert opened == {"config.yaml": 1999} and parsed == {"yaml": 1999}, (opened, parsed)
    assert len(runs.select(rows, ["trainer.frames_per_batch=2048"])) == 2000  # (read once)
    assert opened == {"config.yaml": 1999} and parsed == {"yaml": 1999}, (opened, parsed)
    out = rlexp("runs", "--sort", "-best", cwd=tmp_path)
    assert out.returncode == 0 and "2000 run(s): 2000 finished" in out.stdout


# -- a real run, killed and resumed ----------------------------------------------------------------
def test_a_sigkilled_run_shows_died_and_its_resume_command_finishes_it(tmp_path, children):
    run_dir = tmp_path / "outputs" / "killed"
    args = [
        "env=inverted_pendulum",
        "trainer.total_frames=4096",
        "trainer.frames_per_batch=256",
        "trainer.save_every=512",
        "trainer.eval_every=0",
        "algorithm.num_epochs=1",
        "trainer.progress=false",
        f"hydra.run.dir={run_dir}",
    ]
    proc = children.train(args, tmp_path, tmp_path / "killed.txt")  # its group killed on teardown
    deadline = time.time() + 300
    while time.time() < deadline and proc.poll() is None:
        if list((run_dir / "checkpoints").glob("*_step_000001024.pt")):
            proc.send_signal(signal.SIGKILL)
            break
        time.sleep(0.02)
    proc.wait(timeout=60)
    assert proc.returncode == -signal.SIGKILL, (tmp_path / "killed.txt").read_text()
    assert json.loads((run_dir / "status.json").read_text())["state"] == "running"
    assert read_heartbeat(run_dir)["pid"] == proc.pid

    out = rlexp("runs", "--json", cwd=tmp_path)
    (row,) = json.loads(out.stdout)
    newest = max(int(p.stem.rsplit("_", 1)[1]) for p in run_dir.glob("checkpoints/*_step_*.pt"))
    assert newest >= 1024
    assert (row["status"], row["note"]) == (
        "died",
        f"PID {proc.pid} is gone; resumes from step {newest}",
    )
    assert row["step"] >= newest  # from the end of metrics.jsonl: the heartbeat beats every 10 s
    assert row["task"] == "InvertedPendulum-v5" and row["total"] == 4096
    assert row["resume"].endswith(f"hydra.run.dir={run_dir.resolve()}")
    table = rlexp("runs", cwd=tmp_path).stdout
    assert f"resume: {row['resume']}" in table

    cmd = shlex.split(row["resume"])  # from the run's dir, with its interpreter and entry
    assert cmd[:5] == ["cd", str(tmp_path), "&&", sys.executable, str(REPO / "train.py")]
    env = {**os.environ, "PYTHONPATH": str(REPO / "src")}
    proc = subprocess.run(["bash", "-c", row["resume"]], cwd=tmp_path / "outputs", env=env,
                          capture_output=True, text=True, timeout=300)  # fmt: skip
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert "[resume] continuing from" in proc.stdout + proc.stderr
    (row,) = json.loads(rlexp("runs", "--json", cwd=tmp_path).stdout)
    assert (row["status"], row["step"], row["resume"]) == ("finished", 4096, None)
    assert read_heartbeat(run_dir)["global_step"] == 4096


def test_a_finished_real_run_keeps_its_heartbeat(tmp_path):
    """A finished run's heartbeat holds the final step and the best eval (what the table shows)."""
    run_dir = tmp_path / "outputs" / "r"
    run_train(
        [
            "env=inverted_pendulum",
            "trainer.total_frames=512",
            "trainer.frames_per_batch=256",
            "trainer.eval_every=256",
            "trainer.eval_episodes=2",
            "algorithm.num_epochs=1",
            f"hydra.run.dir={run_dir}",
        ],
        cwd=tmp_path,
    )
    beat, status = read_heartbeat(run_dir), json.loads((run_dir / "status.json").read_text())
    assert status["state"] == "finished" and beat["global_step"] == 512 and beat["total"] == 512
    assert beat["last_eval"] == status["final_eval"]
    assert beat["best"] >= beat["last_eval"]["eval/episode_return"]
    row = runs.read_run(run_dir)
    assert (row.status, row.last, row.best) == (
        "finished",
        beat["last_eval"]["eval/episode_return"],
        beat["best"],
    )
