"""The resume command ``rlexp runs`` prints for a died run (#29, item 3): the command that resumes
exactly that run, from its working dir, through the same entry (``train.py``, ``-m rlexp train``,
the ``rlexp`` script, ``--config-json``), the same launch of its ranks (torchrun, SLURM), its own
overrides, and ``hydra.run.dir`` quoted for Hydra's override grammar and for the shell. A real run
in a dir named with Hydra's and the shell's special characters is killed and resumed with it."""

from __future__ import annotations

import json
import os
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from hydra.core.override_parser.overrides_parser import OverridesParser
from omegaconf import OmegaConf

from conftest import REPO, _live_descendants
from rlexp.analysis import runs
from rlexp.runtime import relaunch
from rlexp.runtime.relaunch import hydra_quote, resume_command

PY = "/opt/venv/bin/python"


def _launch(args: list[str], entry=("train.py",), cwd="/home/u/proj", ranks=None) -> dict:
    return {
        "launch": {"cwd": cwd, "python": PY, "entry": list(entry), "args": args, "ranks": ranks}
    }


def _run_dir_value(command: str) -> str:
    """What Hydra and OmegaConf make of the command's ``hydra.run.dir=`` argument."""
    (arg,) = [a for a in shlex.split(command) if a.startswith("hydra.run.dir=")]
    value = OverridesParser.create().parse_override(arg).value()
    return OmegaConf.create({"d": value}).d


# -- the builder -----------------------------------------------------------------------------------
TRICKY = [
    "a=b,c[d]{e}'f#g ${x} é",
    "quote\"double and 'single'",
    "back\\slash\\",
    "esc\\${not} and \\\\${x}",
    "${now:%Y-%m-%d} interp",
    "spaces  and\ttab",
    "$(touch pwned) `touch pwned2` ; rm -rf ~ *",
    "-leading dash, colon: ~tilde !bang % @ ? |",
    "new\nline",
    "ünïcödé/日本語",
]


@pytest.mark.parametrize("name", TRICKY)
def test_the_run_dir_reads_back_exactly_through_the_shell_hydra_and_omegaconf(name):
    run_dir = Path("/data/runs") / name
    cmd = resume_command(run_dir, ["seed=1"], _launch(["seed=1"], cwd=f"/home/u/{name}"))
    words = shlex.split(cmd)
    assert words[:3] == ["cd", f"/home/u/{name}", "&&"]  # one word each, as bash reads them
    assert words[3:] == [PY, "train.py", "seed=1", words[-1]]
    assert _run_dir_value(cmd) == str(run_dir)


def test_a_plain_path_stays_unquoted_and_hydra_quote_round_trips():
    assert hydra_quote("/tmp/x/outputs/2026-11-23/16-06-13") == "/tmp/x/outputs/2026-11-23/16-06-13"
    assert hydra_quote("/r/a b") == "'/r/a b'"
    assert hydra_quote("/r/it's") == "'/r/it\\'s'"
    assert hydra_quote("/r/${x}") == "'/r/\\${x}'"
    assert hydra_quote("/r/x\\") == "'/r/x\\\\'"  # a backslash before the closing quote: doubled


def test_a_two_rank_torchrun_run_resumes_through_torchrun_with_its_own_options():
    typed = ["--distributed", "env=hopper", "seed=3", "hydra.run.dir=outputs/x"]
    torchrun = [PY, "/opt/venv/bin/torchrun", "--nnodes=1", "--nproc_per_node", "2",
                "--master_port=29611", "train.py", *typed]  # fmt: skip
    ranks = {"world_size": 2, "local_world_size": 2, "nnodes": 1, "launcher": "torchrun",
             "launcher_argv": torchrun}  # fmt: skip
    prov = _launch(typed, entry=["-u", "train.py"], cwd="/home/u/my proj", ranks=ranks)
    cmd = resume_command(Path("/r/run"), ["env=hopper", "seed=3"], prov)
    assert cmd == (
        "cd '/home/u/my proj' && /opt/venv/bin/python /opt/venv/bin/torchrun --nnodes=1 "
        "--nproc_per_node 2 --master_port=29611 train.py --distributed env=hopper seed=3 "
        "hydra.run.dir=/r/run"
    )
    # The ranks' counts alone (no torchrun command line readable): torchrun built from them.
    del ranks["launcher_argv"]
    assert resume_command(Path("/r/run"), ["seed=3"], prov) == (
        "cd '/home/u/my proj' && /opt/venv/bin/python -m torch.distributed.run --standalone "
        "--nproc_per_node=2 train.py --distributed seed=3 hydra.run.dir=/r/run"
    )
    ranks.update(world_size=8, local_world_size=4, nnodes=2)
    assert "torch.distributed.run --nnodes=2 --nproc_per_node=4 train.py --distributed" in (
        resume_command(Path("/r/run"), ["seed=3"], prov)
    )
    ranks.update(launcher="slurm")
    assert resume_command(Path("/r/run"), ["seed=3"], prov) == (
        "cd '/home/u/my proj' && srun --nodes=2 --ntasks-per-node=4 /opt/venv/bin/python "
        "train.py --distributed seed=3 hydra.run.dir=/r/run"
    )


def test_entries_json_files_options_and_sweep_jobs_are_kept_or_dropped_as_a_single_run_needs():
    # `rlexp train` (the console script) with a JSON file, a config dir and a resume checkpoint.
    typed = ["--config-json", "exp/train.json", "-cd", "my conf", "trainer.resume=/x/a.pt", "seed=2",
             "hydra.job.env_set.OMP_NUM_THREADS=1", "hydra.run.dir=out/r"]  # fmt: skip
    prov = _launch(typed, entry=["/opt/venv/bin/rlexp", "train"])
    overrides = ["+experiment=json_experiment", "trainer.resume=/x/a.pt", "seed=2"]
    assert resume_command(Path("/r/j"), overrides, prov) == (
        "cd /home/u/proj && /opt/venv/bin/python /opt/venv/bin/rlexp train --config-json "
        "exp/train.json -cd 'my conf' seed=2 hydra.job.env_set.OMP_NUM_THREADS=1 "
        "trainer.resume=auto hydra.run.dir=/r/j"
    )
    # A sweep job (`python -m rlexp train -m ...`): one run in the job's dir, the job's own
    # overrides; not -m, the sweep lists, the launcher or the sweep dir.
    typed = ["-m", "seed=1,2,3", "algorithm.lr=1e-3", "hydra/launcher=local", "hydra.sweep.dir=s"]
    prov = _launch(typed, entry=["-m", "rlexp", "train"])
    assert resume_command(Path("/s/1"), ["seed=2", "algorithm.lr=1e-3"], prov) == (
        "cd /home/u/proj && /opt/venv/bin/python -m rlexp train seed=2 algorithm.lr=1e-3 "
        "hydra.run.dir=/s/1"
    )


def test_the_launch_is_recorded_as_typed_for_each_entry(monkeypatch):
    monkeypatch.setattr(sys, "executable", "/v/bin/python3")
    cases = [
        (["/v/bin/python3", "/v/bin/rlexp", "train", "seed=1"], ["/v/bin/rlexp", "train"]),
        (["python", "-m", "rlexp", "train", "seed=1"], ["-m", "rlexp", "train"]),
        (["/v/bin/python3", "-u", "train.py", "seed=1"], ["-u", "train.py"]),
    ]
    for orig, entry in cases:
        monkeypatch.setattr(sys, "orig_argv", orig)
        relaunch.record_launch(["seed=1"])
        info = json.loads(os.environ[relaunch.ENV_VAR])
        assert (info["entry"], info["args"], info["python"]) == (
            entry,
            ["seed=1"],
            "/v/bin/python3",
        )
    monkeypatch.setenv("WORLD_SIZE", "2")
    monkeypatch.setenv("LOCAL_WORLD_SIZE", "2")
    monkeypatch.setenv("TORCHELASTIC_RUN_ID", "none")
    ranks = relaunch.launch_info()["ranks"]
    assert (ranks["world_size"], ranks["local_world_size"], ranks["nnodes"]) == (2, 2, 1)
    assert ranks["launcher"] == "torchrun" and isinstance(ranks["launcher_argv"], list)


def test_a_run_from_before_the_launch_record_keeps_the_older_command():
    cmd = runs.resume_command(Path("/r/a b"), ["seed=1"], ["train.py", "--distributed", "seed=1"])
    assert shlex.split(cmd) == ["python", "train.py", "--distributed", "seed=1",
                                "hydra.run.dir='/r/a b'"]  # fmt: skip


# -- a real run, killed and resumed with the printed command ----------------------------------------
def test_a_died_run_in_a_dir_with_special_characters_resumes_there_with_the_printed_command(
    tmp_path, children
):
    """`python -m rlexp train` from its project dir into `runs/a=b,c[d]{e}'f#g ${x} é`, SIGKILLed
    after its first checkpoints; `rlexp runs --json` from elsewhere; its command run with bash
    from a third dir continues the run in that dir from its newest checkpoint."""
    proj, elsewhere = tmp_path / "proj", tmp_path / "elsewhere"
    proj.mkdir()
    elsewhere.mkdir()
    run_dir = tmp_path / "runs" / "a=b,c[d]{e}'f#g ${x} é"
    quoted = f"'{tmp_path}/runs/a=b,c[d]{{e}}\\'f#g \\${{x}} é'"  # Hydra's grammar, by hand
    args = ["env=inverted_pendulum", "trainer.total_frames=16384", "trainer.frames_per_batch=256",
            "trainer.save_every=256", "trainer.eval_every=0", "algorithm.num_epochs=1",
            "trainer.progress=false", "seed=5", f"hydra.run.dir={quoted}"]  # fmt: skip
    env = {**os.environ, "PYTHONPATH": str(REPO / "src"), "MUJOCO_GL": "egl"}
    with open(tmp_path / "first.txt", "w") as out:
        proc = children.popen([sys.executable, "-m", "rlexp", "train", *args], cwd=proj, env=env,
                              stdout=out, stderr=subprocess.STDOUT)  # fmt: skip
    deadline = time.time() + 300
    while time.time() < deadline and proc.poll() is None:
        if list((run_dir / "checkpoints").glob("*_step_000000512.pt")):
            proc.send_signal(signal.SIGKILL)
            break
        time.sleep(0.02)
    proc.wait(timeout=60)
    assert proc.returncode == -signal.SIGKILL, (tmp_path / "first.txt").read_text()[-3000:]
    newest = max(int(p.stem.rsplit("_", 1)[1]) for p in run_dir.glob("checkpoints/*_step_*.pt"))
    assert 512 <= newest < 16384

    listed = subprocess.run([sys.executable, "-m", "rlexp", "runs", "--json", str(tmp_path / "runs")],
                            cwd=elsewhere, env=env, capture_output=True, text=True, timeout=120)  # fmt: skip
    (row,) = json.loads(listed.stdout)
    assert (row["status"], row["path"]) == ("died", str(run_dir))
    assert row["resume"].startswith(
        f"cd {shlex.quote(str(proj))} && {sys.executable} -m rlexp train "
    )

    with open(tmp_path / "resume.txt", "w") as out:
        again = children.popen(["bash", "-c", row["resume"]], cwd=elsewhere, env=env, stdout=out,
                               stderr=subprocess.STDOUT)  # fmt: skip
    again.wait(timeout=600)
    log = (tmp_path / "resume.txt").read_text()
    assert again.returncode == 0, log[-3000:]
    assert f"[resume] continuing from {run_dir}/checkpoints/" in log
    assert f"at step {newest}" in log
    status = json.loads((run_dir / "status.json").read_text())
    assert (status["state"], status["global_step"]) == ("finished", 16384)
    # That dir and no other: nothing under the project dir, the cwd, or beside the run.
    assert sorted(p.name for p in (tmp_path / "runs").iterdir()) == [run_dir.name]
    assert not (proj / "outputs").exists() and not (elsewhere / "outputs").exists()
    steps = [
        json.loads(line)["step"] for line in (run_dir / "metrics.jsonl").read_text().splitlines()
    ]
    assert steps[-1] == 16384 and newest + 256 in steps


def test_a_died_two_rank_run_resumes_as_two_ranks_with_the_printed_command(tmp_path, children):
    """torchrun, 2 ranks (gloo on CPU), SIGKILLed with its ranks after a checkpoint: the printed
    command is torchrun's own command line again, and both ranks continue from that checkpoint."""
    run_dir = tmp_path / "outputs" / "two ranks"
    args = ["env=inverted_pendulum", "trainer.frames_per_batch=256", "algorithm.num_epochs=1",
            "trainer.eval_every=0", "trainer.save_every=512", "trainer.total_frames=8192",
            "trainer.progress=false", "seed=11", f"hydra.run.dir='{run_dir}'"]  # fmt: skip
    torchrun = [sys.executable, "-m", "torch.distributed.run", "--standalone",
                "--nproc_per_node=2", str(REPO / "train.py")]  # fmt: skip
    env = {**os.environ, "PYTHONPATH": str(REPO / "src"), "OMP_NUM_THREADS": "1"}
    with open(tmp_path / "first.txt", "w") as out:
        proc = children.popen([*torchrun, "--distributed", *args], cwd=tmp_path, env=env,
                              stdout=out, stderr=subprocess.STDOUT)  # fmt: skip
    deadline = time.time() + 300
    while time.time() < deadline and proc.poll() is None:
        if list((run_dir / "checkpoints").glob("*_step_000001024.pt")):
            ranks = _live_descendants(proc.pid)  # torchrun starts each in a session of its own
            for pid in ranks:
                os.kill(pid, signal.SIGKILL)  # both ranks and torchrun, as a lost node
            os.killpg(proc.pid, signal.SIGKILL)
            break
        time.sleep(0.02)
    proc.wait(timeout=60)
    assert proc.returncode == -signal.SIGKILL, (tmp_path / "first.txt").read_text()[-3000:]
    assert len(ranks) >= 2 and not set(ranks) & set(_live_descendants(os.getpid()))
    newest = max(int(p.stem.rsplit("_", 1)[1]) for p in run_dir.glob("checkpoints/*_step_*.pt"))

    deadline = time.time() + 60  # a killed process of ~1 GB takes a moment to be gone
    while time.time() < deadline and runs.read_run(run_dir).status != "died":
        time.sleep(0.1)
    (row,) = [r.to_json() for r in runs.read_runs([tmp_path / "outputs"])]
    assert row["status"] == "died", row
    overrides = " ".join(shlex.quote(a) for a in args[:-1])
    assert row["resume"] == (
        f"cd {shlex.quote(str(tmp_path))} && {shlex.join(torchrun)} --distributed {overrides} "
        f"{shlex.quote(f'hydra.run.dir={hydra_quote(str(run_dir))}')}"
    )
    with open(tmp_path / "resume.txt", "w") as out:
        again = children.popen(["bash", "-c", row["resume"]], cwd=REPO, env=env, stdout=out,
                               stderr=subprocess.STDOUT)  # fmt: skip
    again.wait(timeout=600)
    assert again.returncode == 0, (tmp_path / "resume.txt").read_text()[-3000:]
    for log in ("train.log", "train_rank1.log"):  # rank 0's and rank 1's own logs
        assert f"at step {newest}" in (run_dir / log).read_text().split("[resume]")[-1], log
    status = json.loads((run_dir / "status.json").read_text())
    assert (status["state"], status["global_step"]) == ("finished", 8192)
    assert [p.name for p in (tmp_path / "outputs").iterdir()] == [run_dir.name]
