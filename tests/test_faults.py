"""Faults and hostile input (docs/faults.md): one run per dir, signals save at a safe point and a
resume is exact, nothing is written before a config is known good, names stay inside the run dir."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time
from pathlib import Path

import pytest
import torch

from conftest import CONF_DIR, SHORT, Children, run_train
from rlexp.checkpoints.files import latest_checkpoint, load_checkpoint, step_checkpoints
from rlexp.config.validate import ConfigError

LONG = [
    "env=inverted_pendulum",
    "trainer.total_frames=100000000",
    "trainer.frames_per_batch=256",
    "trainer.save_every=0",
    "trainer.eval_every=0",
    "algorithm.num_epochs=2",
    "algorithm.compile=false",  # auto would compile for a budget this long
]


def _start(
    children: Children, args: list[str], cwd: Path, name: str
) -> tuple[subprocess.Popen, Path]:
    """train.py in the background, killed on teardown if the test fails before it ends."""
    console = cwd / f"{name}.txt"
    return children.train(args, cwd, console), console


def _wait_for(proc: subprocess.Popen, console: Path, text: str, timeout: float = 180) -> None:
    deadline = time.time() + timeout
    while time.time() < deadline:
        if text in console.read_text():
            return
        if proc.poll() is not None:
            break
        time.sleep(0.05)
    proc.kill()
    raise AssertionError(f"never saw {text!r}:\n{console.read_text()}")


def _status(run_dir: Path) -> dict:
    return json.loads((run_dir / "status.json").read_text())


# -- one run per dir; SIGTERM / SIGHUP save ----------------------------------------------------------
def test_a_second_run_on_a_busy_dir_exits_2_and_sigterm_saves_and_the_dir_resumes(
    tmp_path, children
):
    run_dir = tmp_path / "run"
    first, console = _start(children, [*LONG, f"hydra.run.dir={run_dir}"], tmp_path, "first")
    _wait_for(first, console, "[train] step=512")
    hydra_files = {p: p.read_bytes() for p in (run_dir / ".hydra").iterdir()}

    second = run_train(
        [*LONG, "trainer.total_frames=2048", f"hydra.run.dir={run_dir}"], cwd=tmp_path, check=False
    )
    assert second.returncode == 2, second.stdout + second.stderr
    assert f"run dir {run_dir} is in use by another run (PID {first.pid} on host" in second.stderr
    assert "Traceback" not in second.stderr and len(second.stderr.strip().splitlines()) == 1
    assert {p: p.read_bytes() for p in (run_dir / ".hydra").iterdir()} == hydra_files

    first.send_signal(signal.SIGTERM)
    assert first.wait(timeout=120) == 128 + signal.SIGTERM, console.read_text()
    status = _status(run_dir)
    assert status["state"] == "interrupted" and "SIGTERM" in status["reason"]
    ckpt = load_checkpoint(latest_checkpoint(run_dir / "checkpoints"))
    assert ckpt["global_step"] == status["global_step"] >= 512

    # The lock file stays behind; it blocks nobody. resume=auto continues from the SIGTERM save.
    assert (run_dir / ".rlexp.lock").is_file()
    target = ckpt["global_step"] + 512
    proc = run_train(
        [*LONG, f"trainer.total_frames={target}", f"hydra.run.dir={run_dir}"], cwd=tmp_path
    )
    assert f"continuing from {ckpt['path']} at step {ckpt['global_step']}" in proc.stdout
    assert _status(run_dir)["state"] == "finished" and _status(run_dir)["global_step"] == target


def test_sighup_checkpoints_like_ctrl_c(tmp_path, children):
    run_dir = tmp_path / "run"
    proc, console = _start(children, [*LONG, f"hydra.run.dir={run_dir}"], tmp_path, "hup")
    _wait_for(proc, console, "[train] step=256")
    proc.send_signal(signal.SIGHUP)
    assert proc.wait(timeout=120) == 128 + signal.SIGHUP, console.read_text()
    status = _status(run_dir)
    assert status["state"] == "interrupted" and "SIGHUP" in status["reason"]
    assert load_checkpoint(latest_checkpoint(run_dir))["global_step"] == status["global_step"]


# -- Ctrl-C + resume == uninterrupted, eval included --------------------------------------------------
EXACT = [
    "env=hopper",
    "env.num_eval_envs=2",
    "trainer.total_frames=2560",
    "trainer.frames_per_batch=256",
    "trainer.save_every=0",
    "trainer.eval_every=512",
    "trainer.eval_episodes=3",
    "algorithm.num_epochs=6",
    "seed=11",
]


def _evals(run_dir: Path) -> dict[int, float]:
    rows = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    return {r["step"]: r["eval/episode_return"] for r in rows if "eval/episode_return" in r}


def test_ctrl_c_mid_update_and_resume_is_bit_identical_and_evaluates_the_same(tmp_path, children):
    whole, broken = tmp_path / "whole", tmp_path / "broken"
    run_train([*EXACT, f"hydra.run.dir={whole}"], cwd=tmp_path, timeout=600)

    proc, console = _start(children, [*EXACT, f"hydra.run.dir={broken}"], tmp_path, "broken")
    _wait_for(proc, console, "[train] step=768")  # the next update is under way
    proc.send_signal(signal.SIGINT)
    assert proc.wait(timeout=120) == 128 + signal.SIGINT, console.read_text()
    stopped = _status(broken)
    assert stopped["state"] == "interrupted" and 768 <= stopped["global_step"] < 2560
    assert step_checkpoints(broken / "checkpoints")[-1].name.endswith(
        f"_step_{stopped['global_step']:09d}.pt"
    )
    run_train([*EXACT, f"hydra.run.dir={broken}"], cwd=tmp_path, timeout=600)

    a = load_checkpoint(latest_checkpoint(whole / "checkpoints"))
    b = load_checkpoint(latest_checkpoint(broken / "checkpoints"))
    assert a["global_step"] == b["global_step"] == 2560
    assert a["algorithm"]["iteration"] == b["algorithm"]["iteration"] == 10
    for key, value in a["policy"].items():
        assert torch.equal(value, b["policy"][key]), f"policy.{key} differs after Ctrl-C + resume"
    for i, state in a["algorithm"]["optimizer"]["state"].items():
        for k, v in state.items():
            assert torch.equal(v, b["algorithm"]["optimizer"]["state"][i][k]), f"optimizer {i}.{k}"
    assert a["windows"]["returns"] == b["windows"]["returns"]
    # Every eval round starts fresh episodes: the resumed run's evals are the uninterrupted run's.
    assert _evals(whole) == _evals(broken) and len(_evals(whole)) == 5
    best_a = load_checkpoint(whole / "checkpoints" / "best.pt")
    best_b = load_checkpoint(broken / "checkpoints" / "best.pt")
    assert best_a["global_step"] == best_b["global_step"]
    assert best_a["best_metric"] == best_b["best_metric"]


# -- what a dir holds ---------------------------------------------------------------------------------
def test_a_failed_start_holds_no_experiment_and_temp_files_are_cleaned(tmp_path):
    run_dir = tmp_path / "run"
    # Inf (noise of std 1e300 overflows float32) from the first rollout on: exit 3 before any
    # checkpoint; config.yaml was written.
    bad = [*SHORT, "events=noise", "events.train.observation_noise.params.std=1e300"]
    proc = run_train([*bad, f"hydra.run.dir={run_dir}"], cwd=tmp_path, check=False)
    assert proc.returncode == 3, proc.stdout + proc.stderr
    assert (run_dir / "config.yaml").is_file() and not step_checkpoints(run_dir / "checkpoints")
    assert "None" not in _status(run_dir)["reason"]
    assert "no checkpoint was written" in _status(run_dir)["reason"]
    # A kill during a write left temporary files behind.
    (run_dir / "checkpoints").mkdir(exist_ok=True)
    stale = [
        run_dir / "checkpoints" / ".x_step_000000256.pt.tmp-99999",
        run_dir / ".status.json.tmp-1",
    ]
    for path in stale:
        path.write_bytes(b"half a file")
    # The corrected config runs in the same dir: no checkpoint, so no experiment to protect.
    run_train([*SHORT, f"hydra.run.dir={run_dir}"], cwd=tmp_path)
    assert _status(run_dir)["state"] == "finished"
    assert not any(p.exists() for p in stale)
    assert not list(run_dir.rglob("*.tmp-*"))


def test_eval_every_0_means_no_evaluation(tmp_path):
    run_dir = tmp_path / "run"
    run_train([*SHORT, f"hydra.run.dir={run_dir}"], cwd=tmp_path)
    assert _evals(run_dir) == {}
    assert _status(run_dir)["final_eval"] == {}
    assert not (run_dir / "checkpoints" / "best.pt").exists()


def test_an_unwritable_checkpoints_dir_fails_at_once_with_one_line(tmp_path):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "checkpoints").write_text("a file where the checkpoints dir should be")
    proc = run_train([*SHORT, f"hydra.run.dir={run_dir}"], cwd=tmp_path, check=False)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    assert "Traceback" not in proc.stdout + proc.stderr
    status = _status(run_dir)
    assert status["state"] == "failed" and "checkpoints" in status["reason"]
    assert status["global_step"] == 0, "it failed before training, not after"
    errors = [ln for ln in proc.stdout.splitlines() if "[ERROR]" in ln]
    assert len(errors) == 1 and "checkpoints" in errors[0]


# -- every config error: one line, exit 2, nothing written ------------------------------------------
def _precheck(args: list[str]):
    from rlexp.launch.precheck import precheck

    return precheck(args, CONF_DIR)


BASE = ["env=inverted_pendulum", "trainer.total_frames=256", "trainer.frames_per_batch=256"]


@pytest.mark.parametrize(
    "override, message",
    [
        ("policy.actor.activation=foo", "policy.actor.activation='foo'; choose from"),
        ("policy.critic.activation=rellu", "did you mean 'relu'?"),
        ("env.name=Foo-v9", "env.name='Foo-v9' is not a registered Gymnasium environment"),
        ("seed=-1", "seed=-1 must be in [0, 2147483647]"),
        ("seed=4294967296", "seed=4294967296 must be in"),
        ("algorithm.lr=nan", "algorithm.lr=nan must be a finite number"),
        ("algorithm.clip_epsilon=inf", "algorithm.clip_epsilon=inf must be a finite number"),
        ("trainer.device=cudafoo", "trainer.device='cudafoo' must be auto, cpu, cuda or cuda:N"),
        ("trainer.exp_name=../../x", "trainer.exp_name='../../x' is not a safe file name"),
        ("trainer.exp_name=/tmp/abs", "trainer.exp_name='/tmp/abs' is not a safe file name"),
        ("trainer.exp_name=team/exp1", "trainer.exp_name='team/exp1' is not a safe file name"),
        (f"trainer.exp_name={'x' * 300}", "trainer.exp_name is 300 characters long; at most 128"),
        ("trainer.log_every=0", "trainer.log_every=0 must be >= 1"),
        ("trainer.eval_episodes=-1", "trainer.eval_episodes=-1 must be >= 0"),
        ("algorithm.clip_epsiln=0.1", "did you mean algorithm.clip_epsilon?"),
        ("+trainer.unknown_key=3", "trainer.unknown_key is not a config key"),
        ("+logger._target_=os.system", "logger._target_ is not a config key"),
        ("env=hoper", "env=hoper is not an option of env"),
        ("trainer.resume=/no/such/file.pt", "checkpoint '/no/such/file.pt' does not exist"),
        ("+env.kwargs.foo=1", "env.kwargs.foo is not an argument of InvertedPendulum-v5"),
    ],
)
def test_config_errors_name_the_key(override, message):
    with pytest.raises(ConfigError) as err:
        _precheck([*BASE, override])
    assert message in str(err.value)
    assert "\n" not in str(err.value)


def test_env_kwargs_on_a_native_task_are_refused_not_ignored():
    with pytest.raises(ConfigError, match=r"env.kwargs=\{'foo': 1\} is for Gymnasium envs"):
        _precheck(["env=cart_pole", "+env.kwargs.foo=1"])


def test_a_misspelled_group_option_does_not_offer_the_schemas():
    with pytest.raises(ConfigError) as err:
        _precheck([*BASE, "algorithm=ppoo"])
    assert "did you mean algorithm=ppo?" in str(err.value) and "_schema" not in str(err.value)


def test_unknown_event_functions_and_modes_from_overrides():
    with pytest.raises(ConfigError, match=r"events.train.action_noise.func='nope' is not a known"):
        _precheck([*BASE, "events=noise", "events.train.action_noise.func=nope"])
    with pytest.raises(ConfigError, match=r"dotted paths must be inside"):
        _precheck([*BASE, "events=noise", "events.train.action_noise.func=os.system"])


def _checkpoint(tmp_path: Path) -> Path:
    run_dir = tmp_path / "src_run"
    run_train([*SHORT, f"hydra.run.dir={run_dir}"], cwd=tmp_path)
    return latest_checkpoint(run_dir / "checkpoints")


def test_bad_resume_checkpoints_are_one_line(tmp_path):
    good = _checkpoint(tmp_path)
    cases = {
        "zero.pt": b"",
        "truncated.pt": good.read_bytes()[:2000],
        "text.pt": b"not a checkpoint at all",
    }
    for name, data in cases.items():
        (tmp_path / name).write_bytes(data)
        with pytest.raises(ConfigError, match="is unreadable"):
            _precheck([*BASE, f"trainer.resume={tmp_path / name}"])
    # A pickle that would run code when loaded without weights_only.
    import pickle

    class Hostile:
        def __reduce__(self):
            return (os.system, ("touch " + str(tmp_path / "pwned"),))

    (tmp_path / "hostile.pt").write_bytes(pickle.dumps({"format": "x", "obj": Hostile()}))
    with pytest.raises(ConfigError, match="is unreadable"):
        _precheck([*BASE, f"trainer.resume={tmp_path / 'hostile.pt'}"])
    assert not (tmp_path / "pwned").exists()
    # A symlink loop.
    (tmp_path / "loop.pt").symlink_to(tmp_path / "loop.pt")
    with pytest.raises(ConfigError, match="trainer.resume="):
        _precheck([*BASE, f"trainer.resume={tmp_path / 'loop.pt'}"])
    # Another env's checkpoint, and the same env with other policy shapes.
    with pytest.raises(ConfigError, match="the checkpoint is of env.name='InvertedPendulum-v5'"):
        _precheck(["env=hopper", f"trainer.resume={good}"])
    with pytest.raises(ConfigError, match="does not fit this config's policy"):
        _precheck([*BASE, "policy=mlp_256", f"trainer.resume={good}"])


@pytest.mark.parametrize(
    "override", ["algorithm.lr=nan", "trainer.exp_name=../../x", "trainer.resume=/no/such.pt"]
)
def test_config_errors_on_the_command_line_exit_2_and_write_nothing(tmp_path, override):
    proc = run_train([*BASE, override], cwd=tmp_path, check=False, timeout=120)
    assert proc.returncode == 2, proc.stdout + proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("config error: "), proc.stderr
    assert not (tmp_path / "outputs").exists()
    assert not (tmp_path.parent / "x").exists()
