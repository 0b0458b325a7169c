"""``rlexp eval``: options out of range and unusable checkpoints are one line on stderr (exit 2),
a run dir falls back past a corrupt newest checkpoint, and NaN policy weights say so (exit 3)."""

from __future__ import annotations

import os
import pickle
import shutil
import subprocess
import sys

import pytest
import torch

from conftest import REPO, TINY, run_train
from rlexp.checkpoints.files import load_checkpoint, save_checkpoint, step_checkpoints


def _eval(*args: str, cwd=None) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "rlexp.cli", "eval", *map(str, args)],
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONPATH": str(REPO / "src")},
        cwd=cwd,
        timeout=120,
    )


def _one_line_exit(proc: subprocess.CompletedProcess, code: int) -> str:
    """The single stderr line of a run that failed with ``code`` and printed no result."""
    assert proc.returncode == code, proc.stdout + proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, f"expected one line on stderr, got:\n{proc.stderr}"
    assert "mean return" not in proc.stdout
    return lines[0]


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    """A tiny finished run: checkpoints at steps 256 and 512 (and best.pt)."""
    root = tmp_path_factory.mktemp("eval_run")
    run_train([*TINY, f"hydra.run.dir={root / 'run'}"], cwd=root)
    return root / "run"


@pytest.fixture
def copied(run_dir, tmp_path):
    """A copy of the run dir that a test may damage."""
    return shutil.copytree(run_dir, tmp_path / "run")


@pytest.mark.parametrize(
    ("option", "value"),
    [
        ("--episodes", "0"),
        ("--episodes", "-2"),
        ("--episodes", "ten"),
        ("--num-envs", "0"),
        ("--num-envs", "-3"),
    ],
)
def test_an_option_out_of_range_is_one_line_naming_it(run_dir, option, value):
    ckpt = step_checkpoints(run_dir / "checkpoints")[-1]
    line = _one_line_exit(_eval(ckpt, option, value), 2)
    assert line.startswith(f"rlexp eval: argument {option}: ") and value in line, line


def test_evaluate_refuses_no_episodes_and_no_envs(run_dir):
    """The function behind the command (tests/test_learning.py calls it) checks the same."""
    from rlexp.cli import evaluate

    with pytest.raises(ValueError, match=r"^episodes=0; "):
        evaluate(str(run_dir), 0, None, seed=1)
    with pytest.raises(ValueError, match=r"^num_envs=-3; "):
        evaluate(str(run_dir), 1, -3, seed=1)


def test_a_run_dir_falls_back_past_a_corrupt_newest_checkpoint(copied):
    older, newest = step_checkpoints(copied / "checkpoints")
    newest.write_bytes(newest.read_bytes()[: newest.stat().st_size // 2])  # a write cut short
    proc = _eval(copied, "--episodes", "2", "--num-envs", "1")
    assert proc.returncode == 0, proc.stderr
    assert f"checkpoint {older} (step 256; the last checkpoint): mean return" in proc.stdout
    skipped = [line for line in proc.stderr.splitlines() if "skipped" in line]
    assert len(skipped) == 1 and newest.name in skipped[0], proc.stderr
    assert "Traceback" not in proc.stderr


def test_a_run_dir_with_no_readable_checkpoint_names_each_and_exits_2(copied):
    older, newest = step_checkpoints(copied / "checkpoints")
    newest.write_bytes(b"")
    older.write_bytes(older.read_bytes()[:100])
    proc = _eval(copied)
    assert proc.returncode == 2 and "mean return" not in proc.stdout, proc.stdout + proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert [newest.name in lines[0], older.name in lines[1]] == [True, True], proc.stderr
    assert lines[2] == f"rlexp eval: none of the 2 checkpoints in {str(copied)!r} can be read " + (
        "(each skipped above)"
    )
    assert len(lines) == 3 and "Traceback" not in proc.stderr


def _unusable(kind: str, tmp_path, good):
    path = tmp_path / f"{kind}.pt"
    if kind == "zero-byte":
        path.write_bytes(b"")
    elif kind == "truncated":
        path.write_bytes(good.read_bytes()[:3000])
    elif kind == "text":
        path.write_text("not a checkpoint\n")
    elif kind == "foreign torch file":  # loads, but is not an rlexp checkpoint
        torch.save({"state_dict": {"w": torch.ones(2)}}, path)
    elif kind == "pickled module":  # weights_only refuses it: torch's message is several lines
        torch.save(torch.nn.Linear(2, 2), path)
    elif kind == "pickle":
        path.write_bytes(pickle.dumps({"x": object}))
    elif kind == "empty dir":
        path = tmp_path / "no_checkpoints"
        path.mkdir()
    return path


@pytest.mark.parametrize(
    "kind",
    [
        "missing",
        "zero-byte",
        "truncated",
        "text",
        "foreign torch file",
        "pickled module",
        "pickle",
        "empty dir",
    ],
)
def test_an_unusable_checkpoint_is_one_line_exit_2(run_dir, tmp_path, kind):
    path = _unusable(kind, tmp_path, step_checkpoints(run_dir / "checkpoints")[-1])
    line = _one_line_exit(_eval(path), 2)
    assert line.startswith("rlexp eval: ") and repr(str(path)) in line, line
    assert "\x1b" not in line, "terminal colour codes in the message"


def test_nan_policy_weights_say_so_instead_of_a_return(run_dir, tmp_path):
    ckpt = load_checkpoint(step_checkpoints(run_dir / "checkpoints")[-1])
    ckpt.pop("path")
    name = next(k for k in ckpt["policy"] if k.startswith("actor") and k.endswith("weight"))
    ckpt["policy"][name] = torch.full_like(ckpt["policy"][name], float("nan"))
    path = save_checkpoint(tmp_path / "nan_step_000000512.pt", ckpt)
    line = _one_line_exit(_eval(path), 3)
    assert line == (
        f"rlexp eval: checkpoint {str(path)!r} holds non-finite policy weights ({name}); there is "
        "nothing to evaluate: use an earlier checkpoint of the run"
    )


def test_a_checkpoint_from_another_machine_or_older_event_params_still_evaluates(run_dir, tmp_path):
    """Evaluation rebuilds env and policy only: the run's events and thread count don't matter."""
    ckpt = load_checkpoint(step_checkpoints(run_dir / "checkpoints")[-1])
    ckpt.pop("path")
    ckpt["config"]["trainer"]["torch_threads"] = 4096  # a big node's setting
    ckpt["config"]["events"]["train"] = {
        "old": {"func": "record_rollouts", "mode": "interval", "params": {"every": 3}}
    }
    path = save_checkpoint(tmp_path / "other_step_000000512.pt", ckpt)
    proc = _eval(path, "--episodes", "2")
    assert proc.returncode == 0, proc.stderr
    assert "mean return" in proc.stdout


def test_evaluation_is_deterministic_and_rlexp_eval_agrees_with_the_trainers_eval(run_dir):
    """Each checkpoint holds the Trainer's eval of its own weights (eval_once runs just before the
    save); rebuilt by ``rlexp eval`` with the Trainer's eval seed (seed + EVAL_SEED_OFFSET), the
    same episodes give the same numbers, every time."""
    import re

    from rlexp.cli import evaluate
    from rlexp.training.build import EVAL_SEED_OFFSET

    ckpts = step_checkpoints(run_dir / "checkpoints")
    assert [load_checkpoint(c)["global_step"] for c in ckpts] == [256, 512]
    for path in ckpts:
        ckpt = load_checkpoint(path)
        seed = ckpt["config"]["seed"] + EVAL_SEED_OFFSET
        episodes = ckpt["config"]["trainer"]["eval_episodes"]
        first = evaluate(str(path), episodes, None, seed)
        assert evaluate(str(path), episodes, None, seed) == first, "two evaluations differ"
        trainer_eval = ckpt["last_eval"]
        assert first["episodes"] == episodes
        assert (first["mean_return"], first["std_return"]) == (
            trainer_eval["eval/episode_return"],
            trainer_eval["eval/episode_return_std"],
        ), f"{path.name}: rlexp eval {first} != the Trainer's eval {trainer_eval}"

    # The command line too (it prints three decimals).
    ckpt = load_checkpoint(ckpts[-1])
    seed = ckpt["config"]["seed"] + EVAL_SEED_OFFSET
    episodes = ckpt["config"]["trainer"]["eval_episodes"]
    # The default seed is the run's own eval seed: no --seed needed to agree with the Trainer.
    assert evaluate(str(ckpts[-1]), episodes, None) == evaluate(
        str(ckpts[-1]), episodes, None, seed
    )
    proc = _eval(ckpts[-1], "--episodes", episodes)
    assert proc.returncode == 0, proc.stderr
    m = re.search(r"mean return (\S+) \+- (\S+) over (\d+) episodes", proc.stdout)
    assert m, proc.stdout
    assert float(m.group(1)) == pytest.approx(ckpt["last_eval"]["eval/episode_return"], abs=5e-4)
    assert float(m.group(2)) == pytest.approx(
        ckpt["last_eval"]["eval/episode_return_std"], abs=5e-4
    )
    assert int(m.group(3)) == episodes
