"""A lean install (#45 item 3): ``make train`` installs rlexp's core dependencies only and ``make
test`` everything the tests need, each with its own stamp (``make test`` after ``make train`` adds
the rest); the default training runs with every package only an extra brings made unimportable,
and a missing extra is one line naming it."""

from __future__ import annotations

import re
import subprocess
import sys
import textwrap
from importlib import metadata
from pathlib import Path

import tomllib
from packaging.requirements import Requirement

from conftest import REPO

PYPROJECT = tomllib.loads((REPO / "pyproject.toml").read_text())


def _make(*args: str) -> list[str]:
    out = subprocess.run(
        ["make", "-n", *args], cwd=REPO, capture_output=True, text=True, check=True, timeout=60
    ).stdout.replace("\\\n", " ")
    return [line for line in out.splitlines() if "pip install" in line]


def test_make_train_installs_the_core_and_make_test_adds_the_rest(tmp_path):
    core = [line for line in _make("-B", "train") if "torch==" not in line]
    assert len(core) == 1 and core[0].rstrip().endswith("-c constraints.txt -e ."), core
    full = [line for line in _make("-B", "test") if "torch==" not in line]
    assert full[0] == core[0] and full[1].rstrip().endswith('-e ".[all,dev]"'), full
    # a venv `make train` installed (its stamps newer than pyproject.toml): `make test` adds the
    # extras and nothing else; after that, nothing
    venv = tmp_path / "venv"
    venv.mkdir()
    for stamp in (".created", ".torch", ".installed-core"):
        (venv / stamp).touch()
    [rest] = _make(f"VENV={venv}", "test")
    assert rest.rstrip().endswith('-e ".[all,dev]"')
    (venv / ".installed-all").touch()
    assert _make(f"VENV={venv}", "test") == [] and _make(f"VENV={venv}", "train") == []


def _name(dist: str) -> str:
    return re.sub(r"[-_.]+", "-", dist).lower()


def _closure(requirements: list[str]) -> set[str]:
    """The installed distributions ``requirements`` bring, transitively (extras followed)."""
    seen: set[str] = set()
    todo = [(Requirement(r), "") for r in requirements]
    while todo:
        req, extra = todo.pop()
        if req.marker is not None and not req.marker.evaluate({"extra": extra}):
            continue
        name = _name(req.name)
        try:
            requires = metadata.requires(req.name) or []
        except metadata.PackageNotFoundError:
            continue
        for want in ("", *sorted(req.extras)):
            key = f"{name}[{want}]"
            if key in seen:
                continue
            seen.add(key)
            todo += [(Requirement(r), want) for r in requires]
    return {key.split("[")[0] for key in seen}


def _extra_only() -> tuple[set[str], set[str]]:
    """The distributions that only the optional extras (and dev) bring, not the core, and their
    top-level modules."""
    optional = PYPROJECT["project"]["optional-dependencies"]
    core = _closure(PYPROJECT["project"]["dependencies"])
    extras = _closure(
        [r for name, reqs in optional.items() for r in reqs if not r.startswith("rlexp")]
    )
    only = extras - core
    modules = {
        module
        for module, dists in metadata.packages_distributions().items()
        if {_name(d) for d in dists} <= only
    }
    return only, modules


#: train.py in a process where the extras' modules cannot be imported (as in a core install).
_BLOCKED_RUN = textwrap.dedent(
    """
    import importlib.machinery, re, runpy, sys
    blocked, dists = set(sys.argv[1].split(",")), set(sys.argv[2].split(","))
    path_finder = importlib.machinery.PathFinder
    class Lean(path_finder):  # the path finder, blind to the blocked packages: as not installed
        @classmethod
        def find_spec(cls, name, path=None, target=None):
            if name.split(".")[0] in blocked:
                return None  # import: ModuleNotFoundError; importlib.util.find_spec: None
            return path_finder.find_spec(name, path, target)
        @classmethod
        def find_distributions(cls, *args, **kwargs):  # their metadata too (torch probes optree's)
            for dist in path_finder.find_distributions(*args, **kwargs):
                if re.sub(r"[-_.]+", "-", dist.metadata["Name"] or "").lower() not in dists:
                    yield dist
    sys.meta_path[:] = [Lean if f is path_finder else f for f in sys.meta_path]
    assert Lean in sys.meta_path
    if sys.argv[3] == "-m":  # python -m rlexp ...
        sys.argv = [sys.argv[4], *sys.argv[5:]]
        runpy.run_module(sys.argv[0], run_name="__main__", alter_sys=True)
    else:
        sys.argv = [sys.argv[3], *sys.argv[4:]]
        runpy.run_path(sys.argv[0], run_name="__main__")
    """
)


def _lean_train(
    tmp_path: Path, args: list[str], command: tuple[str, ...] | None = None
) -> subprocess.CompletedProcess:
    """``train.py ARGS`` (or ``command``) in a process that sees the core dependencies only."""
    dists, blocked = _extra_only()
    for module in ("wandb", "optuna", "matplotlib", "scipy", "onnx", "onnxruntime", "Box2D"):
        assert module in blocked, module  # the extras' packages are there to block
    assert not blocked & {"torch", "tensorboard", "gymnasium", "mujoco", "hydra", "torchrl"}
    (tmp_path / "lean.py").write_text(_BLOCKED_RUN)
    return subprocess.run(
        [sys.executable, str(tmp_path / "lean.py"), ",".join(sorted(blocked)),
         ",".join(sorted(dists)),
         *(command or (str(REPO / "train.py"), *args, f"hydra.run.dir={tmp_path / 'run'}"))],
        cwd=tmp_path, capture_output=True, text=True, timeout=300,
        env={**__import__("os").environ, "PYTHONPATH": str(REPO / "src")},
    )  # fmt: skip


def test_the_default_training_needs_only_the_core_dependencies(tmp_path):
    small = ["trainer.total_frames=2048", "env.num_eval_envs=2", "env.max_episode_steps=100"]
    proc = _lean_train(tmp_path, ["trainer=smoke", *small, "trainer.progress=false"])
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert (tmp_path / "run" / "tensorboard").is_dir()  # the default logger is core
    # a TorchScript export is core too
    proc = _lean_train(tmp_path, [], ("-m", "rlexp", "export", "run"))
    assert proc.returncode == 0, proc.stderr[-3000:]
    # rlexp eval builds the env and the policy, then the mp4 needs the video extra: one line
    proc = _lean_train(tmp_path, [], ("-m", "rlexp", "eval", "run", "--episodes", "1", "--video"))
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr
    assert lines[0].startswith(
        "rlexp eval: rlexp eval --video needs rlexp's optional 'video' extra (imageio_ffmpeg is not "
        "installed): pip install "
    ), lines


def test_a_missing_box2d_extra_is_one_line_naming_it(tmp_path):
    proc = _lean_train(tmp_path, ["env=lunar_lander", "trainer=smoke"])
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr
    assert lines[0].startswith(
        "config error: env.name='LunarLander-v3' needs rlexp's optional 'box2d' extra (Box2D is "
        "not installed): pip install "
    ), lines
    assert "gymnasium[box2d]" in lines[0]
