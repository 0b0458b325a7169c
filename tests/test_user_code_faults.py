"""User envs that exit, interrupt, fail to restore or never end (#43 items 5, 6, 7, 11;
tests/fault_envs.py, docs/faults.md): each is the env's error like any other, one line naming what
was raised and where, with the documented exit code and status; nothing hangs."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from fault_envs import tiny_run

from conftest import REPO, run_train

TESTS = Path(__file__).resolve().parent
PYPATH = {"PYTHONPATH": f"{REPO / 'src'}{os.pathsep}{TESTS}"}  # fault_envs importable
FAULT_ENVS = str(TESTS / "fault_envs.py")

RUN = tiny_run()


def _train(tmp_path: Path, *args: str, run: str = "run") -> tuple[Path, int, str]:
    run_dir = tmp_path / run
    proc = run_train(
        [*RUN, f"hydra.run.dir={run_dir}", *args],
        cwd=tmp_path, check=False, env_extra=PYPATH, timeout=300,
    )  # fmt: skip
    return run_dir, proc.returncode, proc.stdout + proc.stderr


def _status(run_dir: Path) -> dict:
    return json.loads((run_dir / "status.json").read_text())


# -- item 11: the overlap child's error names its type and message -------------------------------
@pytest.mark.parametrize(
    ("what", "expected"),
    [
        ("memory", "MemoryError: Unable to allocate 2.00 PiB"),  # numpy's _ArrayMemoryError
        ("exit0", "SystemExit(0)"),  # user code's exit in the child: the same error
    ],
)
def test_an_error_in_the_overlap_child_names_its_type_message_and_place(tmp_path, what, expected):
    run_dir, code, out = _train(
        tmp_path, "algorithm.overlap=true", "+env.kwargs.exit_at=300",
        f"+env.kwargs.raise_what={what}",
    )  # fmt: skip
    assert code == 1, out[-3000:]
    reason = _status(run_dir)["reason"]
    head = f"CollectionError: in the collection process (algorithm.overlap=true): {expected}"
    assert reason.startswith(head), reason
    assert f"(raised in _raise() at {FAULT_ENVS}:" in reason
    assert "Traceback" not in out, out[-3000:]


# -- item 5: SystemExit / KeyboardInterrupt raised by user code ---------------------------------
@pytest.mark.parametrize(
    ("where", "what", "shown"),
    [
        ("step", "exit0", "SystemExit(0)"),
        ("reset", "exit0", "SystemExit(0)"),
        ("step", "keyboard", "KeyboardInterrupt"),
    ],
)
def test_user_code_that_exits_or_interrupts_mid_run_fails_with_one_line_naming_it(
    tmp_path, where, what, shown
):
    # reset: the 3rd reset (the first is the config check's, the 2nd the run's first): mid-run
    at = 300 if where == "step" else 3
    run_dir, code, out = _train(
        tmp_path, f"+env.kwargs.exit_at={at}", f"+env.kwargs.exit_in={where}",
        f"+env.kwargs.raise_what={what}", "+env.kwargs.episode=5",
    )  # fmt: skip
    assert code == 1, out[-3000:]
    status = _status(run_dir)
    assert status["state"] == "failed", status
    assert f"user code raised {shown} (raised in _raise() at {FAULT_ENVS}:" in status["reason"]
    assert "in the training loop" in status["reason"]
    assert "Traceback" not in out, out[-3000:]
    assert status["reason"].splitlines() == [status["reason"]]


def test_sys_exit_at_the_env_modules_import_is_a_config_error_naming_it(tmp_path):
    (tmp_path / "exits_on_import.py").write_text("import sys\nsys.exit(0)\n")
    run_dir = tmp_path / "run"
    proc = run_train(
        [*tiny_run("env.name=exits_on_import:Walk-v0"), f"hydra.run.dir={run_dir}"],
        cwd=tmp_path, check=False, timeout=300,
        env_extra={"PYTHONPATH": f"{REPO / 'src'}{os.pathsep}{tmp_path}"},
    )  # fmt: skip
    err = proc.stderr.strip().splitlines()
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert len(err) == 1 and "user code raised SystemExit(0)" in err[0], err
    assert f"at {tmp_path / 'exits_on_import.py'}:2" in err[0]
    assert not run_dir.exists()


def test_a_sweep_goes_on_after_a_job_whose_env_exits(tmp_path):
    sweep = tmp_path / "sweep"
    proc = run_train(
        ["-m", *RUN, "+env.kwargs.exit_at=300,0", f"hydra.sweep.dir={sweep}"],
        cwd=tmp_path, check=False, env_extra=PYPATH, timeout=400,
    )  # fmt: skip
    out = proc.stdout + proc.stderr
    assert proc.returncode == 1, out[-3000:]
    assert _status(sweep / "0")["state"] == "failed"
    assert "user code raised SystemExit(0)" in _status(sweep / "0")["reason"]
    assert _status(sweep / "1")["state"] == "finished", out[-3000:]
    assert f"sweep {sweep}: 1 of 2 jobs finished; 1 failed" in out


@pytest.mark.parametrize(
    ("exc", "expected"),
    [
        (KeyError("obs"), "KeyError: obs"),  # config.rules.first_line: no quotes
        (ValueError("  "), "ValueError"),  # no message: the type alone
        (RuntimeError("first line\nsecond line"), "RuntimeError: first line"),
        (SystemExit(3), "SystemExit(3)"),
        (KeyboardInterrupt(), "KeyboardInterrupt"),
    ],
)
def test_describe_is_the_type_the_first_line_of_the_message_and_the_place(exc, expected):
    from rlexp.runtime.user_code import describe

    def raise_it():
        raise exc

    try:
        raise_it()
    except BaseException as caught:  # (SystemExit and KeyboardInterrupt too)
        got = describe(caught)
    where = f"{raise_it.__code__.co_filename}:{raise_it.__code__.co_firstlineno + 1}"
    assert got == f"{expected} (raised in raise_it() at {where})"


# -- item 6: set_state raising on resume --------------------------------------------------------
def test_set_state_raising_on_resume_is_one_line_exit_2_and_the_status_no_longer_finished(
    tmp_path,
):
    run_dir, code, out = _train(tmp_path, "trainer.total_frames=256")
    assert code == 0 and _status(run_dir)["state"] == "finished", out[-3000:]
    proc = run_train(
        [*RUN, f"hydra.run.dir={run_dir}", "trainer.total_frames=512"],
        cwd=tmp_path, check=False, timeout=300,
        env_extra={**PYPATH, "FAULT_ENVS_BAD_SET_STATE": "1"},
    )  # fmt: skip
    assert proc.returncode == 2, proc.stdout + proc.stderr
    out = proc.stdout + proc.stderr
    err = [ln for ln in out.splitlines() if "set_state() raised" in ln]
    assert len(err) == 1, out
    assert "env.name='fault_envs:Walk-v0': its set_state() raised while resuming" in err[0]
    assert "ValueError: set_state: the saved walk does not fit this one" in err[0]
    assert "Traceback" not in proc.stdout + proc.stderr
    status = _status(run_dir)
    assert status["state"] == "failed" and status["exit_code"] == 2
    assert "set_state()" in status["reason"] and status["global_step"] == 256


# -- item 7: episodes that never end ------------------------------------------------------------
def test_an_eval_episode_that_never_ends_is_cut_at_the_bound_and_counted():
    """Two copies, three episodes (quotas 2 and 1), a bound of 4 steps: copy 0 ends every 2 steps,
    copy 1 never does and is cut at its 4th step. By hand: returns [2, 2, 8], lengths [2, 2, 4]."""
    import numpy as np

    from rlexp.training.evaluation import EpisodeTally

    tally = EpisodeTally(2, 3, max_steps=4)
    for step in range(1, 5):
        tally.add(np.array([1.0, 2.0]), np.array([step % 2 == 0, False]), None)
    assert tally.finished and tally.cut == 1
    assert tally.returns == [2.0, 2.0, 8.0] and tally.lengths == [2, 2, 4]
    assert tally.metrics()["eval/episode_return"] == pytest.approx(4.0)


@pytest.mark.slow
def test_a_run_and_rlexp_eval_of_an_env_without_end_finish_with_one_warning(tmp_path):
    """fault_envs:Endless-v0 (no time limit, episodes never end): the run's eval rounds and
    ``rlexp eval`` end after MAX_EPISODE_STEPS steps per episode, each with one warning."""
    from rlexp.training.evaluation import MAX_EPISODE_STEPS

    args = ["env.name=fault_envs:Endless-v0", "trainer.total_frames=256", "trainer.eval_every=256",
            "trainer.eval_episodes=1", "env.num_eval_envs=1", "trainer.eval_async=false"]  # fmt: skip
    run_dir, code, out = _train(tmp_path, *args)
    assert code == 0, out[-3000:]
    warning = f"ran {MAX_EPISODE_STEPS} steps without ending and were cut there"
    assert out.count(warning) == 1 and "env.max_episode_steps=N" in out
    assert _status(run_dir)["final_eval"]["eval/episode_length"] == MAX_EPISODE_STEPS
    proc = subprocess.run(
        [sys.executable, "-m", "rlexp", "eval", str(run_dir), "--episodes", "2"],
        capture_output=True, text=True, timeout=300, env={**os.environ, **PYPATH},
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert "2 of 2 eval episodes of fault_envs:Endless-v0 " + warning in proc.stderr
    assert "over 2 episodes" in proc.stdout


def test_rlexp_eval_of_an_env_that_exits_is_one_line_and_exit_1(tmp_path):
    run_dir, code, out = _train(tmp_path, "trainer.total_frames=128")
    assert code == 0, out[-3000:]
    proc = subprocess.run(
        [sys.executable, "-m", "rlexp", "eval", str(run_dir), "--episodes", "1"],
        capture_output=True, text=True, timeout=300,
        env={**os.environ, **PYPATH, "FAULT_ENVS_EXIT_IN_RESET": "1"},
    )  # fmt: skip
    assert proc.returncode == 1, proc.stdout + proc.stderr
    err = proc.stderr.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("rlexp eval: "), proc.stderr
    assert f"user code raised SystemExit(0) (raised in reset() at {FAULT_ENVS}:" in err[0]
