"""``env=gym env.name=<id>`` (#45 item 5): an env option for any Gymnasium id with defaults for an
env nobody has tuned (several copies, a modest evaluation, observation normalisation, a budget of
about a minute); docs/envs.md's ``rlexp train env=gym ...`` lines run as written (a shrunk budget
appended in the default suite, as written in the slow one); ``env.name=...`` alone says whose
settings it took."""

from __future__ import annotations

import json
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
from test_docs_envs import _example

from conftest import REPO, Children, compose
from rlexp.config.validate import ConfigError, to_root_config

DOC = REPO / "docs" / "envs.md"
SHRINK = [
    "trainer.total_frames=2048",
    "trainer.frames_per_batch=1024",
    "trainer.eval_every=1024",
    "trainer.save_every=2048",
    "trainer.progress=false",
]


def _doc_commands() -> list[str]:
    lines = [
        line.split("#", 1)[0].strip()
        for block in re.findall(r"```bash\n(.*?)```", DOC.read_text(), re.S)
        for line in block.splitlines()
    ]
    return [line for line in lines if re.search(r"\brlexp train env=gym\b", line)]


def test_env_gym_sets_defaults_for_an_unknown_env():
    config = to_root_config(compose(["env=gym", "env.name=Acrobot-v1"]))
    e, t = config.env, config.trainer
    assert (e.name, e.backend, e.num_envs, e.num_eval_envs) == ("Acrobot-v1", "gymnasium", 4, 5)
    assert e.normalize_observations and e.max_episode_steps is None and not e.rescale_actions
    assert (t.total_frames, t.frames_per_batch, t.eval_every, t.eval_episodes) == (
        100_000,
        2048,
        25_000,
        5,
    )
    assert t.exp_name == "Acrobot-v1_ppo"
    # a trainer named on the command line wins over env=gym's trainer=quick
    smoke = to_root_config(compose(["env=gym", "env.name=Acrobot-v1", "trainer=smoke"]))
    assert smoke.trainer.total_frames == 4096 and smoke.env.num_envs == 4


def test_env_gym_without_a_name_asks_for_one():
    with pytest.raises(ConfigError) as err:
        to_root_config(compose(["env=gym"]))
    assert str(err.value).startswith("env.name='' must be a registered Gymnasium id")
    assert "env=gym env.name=" in str(err.value)


def _rlexp_shim(bin_dir: Path) -> None:
    """``rlexp`` on the PATH, as this checkout (a verbatim ``PYTHONPATH=. rlexp ...`` keeps the
    command's own PYTHONPATH and adds this checkout's src, as an install of it would)."""
    bin_dir.mkdir()
    shim = bin_dir / "rlexp"
    shim.write_text(
        f'#!/bin/sh\nPYTHONPATH="{REPO / "src"}${{PYTHONPATH:+:$PYTHONPATH}}" '
        f'exec {shlex.quote(sys.executable)} -m rlexp "$@"\n'
    )
    shim.chmod(0o755)


def _run_doc_commands(tmp_path: Path, extra: list[str]) -> dict[str, Path]:
    commands = _doc_commands()
    assert len(commands) >= 2 and any("corridor:Corridor-v0" in c for c in commands), commands
    _rlexp_shim(tmp_path / "bin")
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    env["PATH"] = f"{tmp_path / 'bin'}{os.pathsep}{env['PATH']}"
    runs = {}
    with Children() as children:
        procs = {}
        for i, command in enumerate(commands):
            cwd = tmp_path / f"cmd{i}"
            cwd.mkdir()
            (cwd / "corridor.py").write_text(_example())
            line = " ".join([command, *extra, f"hydra.run.dir={cwd / 'run'}"])
            log = open(cwd / "console.log", "w")  # noqa: SIM115 (closed below)
            procs[command] = (
                children.popen(["bash", "-c", line], cwd=cwd, env=env, stdout=log, stderr=log),
                log,
            )
            runs[command] = cwd / "run"
        for command, (proc, log) in procs.items():
            code = proc.wait(timeout=900)
            log.close()
            assert code == 0, (command, Path(log.name).read_text())
    return runs


def test_the_docs_env_gym_commands_run(tmp_path):
    """Each documented line as written, a shrunk budget appended; the env line names no other
    env option's settings."""
    for command, run in _run_doc_commands(tmp_path, SHRINK).items():
        status = json.loads((run / "status.json").read_text())
        assert status["state"] == "finished", (command, status)
        log = (run / "train.log").read_text()
        assert "its other settings" not in log
        config = (run / "config.yaml").read_text()
        assert "num_envs: 4" in config and "num_eval_envs: 5" in config
        if "Pendulum-v1" in command:  # Box(-2, 2): warned once, in the run's log
            assert log.count("the action bounds [-2, 2] are not [-1, 1]") == 1, log


@pytest.mark.slow
def test_the_docs_env_gym_commands_run_verbatim_and_learn(tmp_path):
    """The documented lines with their own budget (trainer=quick, about a minute each)."""
    for command, run in _run_doc_commands(tmp_path, []).items():
        status = json.loads((run / "status.json").read_text())
        assert status["state"] == "finished" and status["global_step"] >= 100_000, command
        final = status["final_eval"]["eval/episode_return"]
        if "Corridor" in command:  # the goal in a few steps: +1 minus 0.05 a step (0.92 measured)
            assert final > 0.8, final
        else:  # Pendulum-v1: from about -1200 (random) to -172 measured
            assert final > -400, final


def test_env_name_alone_says_whose_settings_it_took(tmp_path):
    (tmp_path / "corridor.py").write_text(_example())
    env = {**os.environ, "PYTHONPATH": f"{REPO / 'src'}{os.pathsep}{tmp_path}"}
    run = tmp_path / "run"
    args = ["env.name=corridor:Corridor-v0", *SHRINK, "trainer.eval_episodes=2"]
    proc = subprocess.run(
        [sys.executable, str(REPO / "train.py"), *args, f"hydra.run.dir={run}"],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    line = next(x for x in (run / "train.log").read_text().splitlines() if "env corridor" in x)
    assert line.endswith(
        "env corridor:Corridor-v0 x1: obs 9, action 1 (its other settings are env=half_cheetah's: "
        "num_envs=1, num_eval_envs=10, normalize_observations=true, max_episode_steps=None; "
        "env=gym env.name=corridor:Corridor-v0 has defaults for any Gymnasium id)"
    ), line
