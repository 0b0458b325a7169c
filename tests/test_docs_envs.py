"""docs/envs.md's example env, verbatim: trained by ``module:EnvId``, killed after its first
checkpoint and resumed, it ends bit-identical to the run that was never interrupted; the doc's
error line for a module that is not installed is the one users get."""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

import torch
from test_resume import _kill_after_checkpoint
from test_user_envs import SMALL

from conftest import REPO, run_train
from rlexp.checkpoints.files import latest_checkpoint, load_checkpoint

DOC = REPO / "docs" / "envs.md"


def _example() -> str:
    text = DOC.read_text().split("## A complete example", 1)[1]
    return re.search(r"```python\n(.*?)```", text, re.S).group(1)


def test_the_docs_example_env_trains_and_resumes_exactly(tmp_path):
    (tmp_path / "corridor.py").write_text(_example())
    pypath = {"PYTHONPATH": f"{REPO / 'src'}{os.pathsep}{tmp_path}"}
    args = [
        *SMALL,
        "env=hopper",
        "env.name=corridor:Corridor-v0",
        "+env.kwargs.length=10",
        "env.num_envs=2",
        "trainer.total_frames=1024",
        "trainer.save_every=512",
        "seed=2",
    ]
    run_train([*args, f"hydra.run.dir={tmp_path / 'whole'}"], cwd=tmp_path, env_extra=pypath)
    broken = tmp_path / "broken"
    cmd = [*args, f"hydra.run.dir={broken}"]
    _kill_after_checkpoint(cmd, tmp_path, broken / "checkpoints", 512, pypath)
    run_train(cmd, cwd=tmp_path, env_extra=pypath)
    status = json.loads((broken / "status.json").read_text())
    assert status["env_resume"] == "restored (the env's get_state)"
    a = load_checkpoint(latest_checkpoint(tmp_path / "whole" / "checkpoints"))
    b = load_checkpoint(latest_checkpoint(broken / "checkpoints"))
    assert [p["key"] for p in a["observation_layout"]["parts"]] == ["goal", "position"]
    assert a["observation_layout"]["dim"] == 11  # one-hot goal of 10 cells (env.kwargs), position
    for key, value in a["policy"].items():
        assert torch.equal(value, b["policy"][key]), f"policy.{key} differs after resume"
    assert a["windows"]["returns"] == b["windows"]["returns"] and a["windows"]["returns"]


def test_the_docs_error_line_for_a_missing_module_is_what_users_get(tmp_path: Path):
    documented = next(
        line for line in DOC.read_text().splitlines() if line.startswith("config error: env.name=")
    )
    proc = run_train(
        ["env=hopper", "env.name=my_pkg.envs:MyEnv-v0", f"hydra.run.dir={tmp_path / 'r'}"],
        cwd=tmp_path,
        check=False,
    )
    assert proc.returncode == 2 and proc.stderr.strip() == documented
