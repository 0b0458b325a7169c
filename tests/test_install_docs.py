"""Install instructions that work off this machine (#30 items 6-9): rlexp is on no package index,
the torch build is an explicit choice, the quick start uses files the repository ships, and the
dependencies are declared with the versions CI tests."""

from __future__ import annotations

import ast
import re
import shlex
import subprocess
import sys

import pytest
import tomllib

from conftest import REPO
from rlexp import extras

PYPROJECT = tomllib.loads((REPO / "pyproject.toml").read_text())
DOCS = ["README.md", "docs/user_project.md", "examples/user_project/README.md"]


def _code_lines(path) -> list[str]:
    text = (REPO / path).read_text()
    return [
        line
        for block in re.findall(r"```bash\n(.*?)```", text, re.S)
        for line in block.splitlines()
    ]


@pytest.mark.parametrize("path", DOCS)
def test_no_install_command_assumes_rlexp_is_on_an_index(path):
    for line in _code_lines(path):
        for cmd in re.findall(r"pip install ([^`#\n]*)", line):
            words = shlex.split(cmd.replace("\\", ""), comments=True)
            for word in words:
                # `rlexp` / `rlexp[all]` alone would be looked up on an index: a path, a wheel or
                # a git URL is what works
                assert not re.fullmatch(r"rlexp(\[[\w,]+\])?", word), f"{path}: {line.strip()}"


def test_the_readme_says_it_is_not_published_and_how_to_choose_the_torch_build():
    readme = (REPO / "README.md").read_text()
    assert "not published on a package index" in readme
    assert "https://download.pytorch.org/whl/cpu" in readme and "TORCH_INDEX" in readme
    assert "MUJOCO_GL=egl" in readme and "trainer.device=auto" in readme


def test_the_makefile_installs_the_torch_build_named_by_torch_index(tmp_path):
    def dry_run(*args: str) -> str:
        return subprocess.run(
            ["make", "-n", "-B", "install", *args], cwd=REPO, capture_output=True, text=True,
            check=True, timeout=60,
        ).stdout.replace("\\\n", " ")  # fmt: skip

    cuda = dry_run("TORCH_INDEX=https://download.pytorch.org/whl/cu128", "TORCH_VERSION=2.13.1")
    torch_line = next(line for line in cuda.splitlines() if "torch==" in line)
    assert "torch==2.13.1" in torch_line
    assert "--index-url https://download.pytorch.org/whl/cu128" in torch_line
    plain = next(line for line in dry_run().splitlines() if "torch==" in line)
    assert "--index-url" not in plain and "torch==2.13.0" in plain  # pip's own configuration
    assert any("-c constraints.txt" in line for line in dry_run().splitlines())


def test_the_quick_start_uses_files_the_repository_ships():
    for line in _code_lines("README.md"):
        for path in re.findall(r"--config-json (\S+)", line):
            assert not path.startswith(".."), f"README: {line.strip()} reads outside the repository"
            assert (REPO / path).is_file(), f"README: {path} does not exist"


@pytest.mark.parametrize("extra", ["wandb", "slurm", "optuna", "video", "report", "export"])
def test_a_missing_extras_message_installs_that_extras_packages(extra):
    hint = extras.install_hint(extra)
    assert hint.startswith("pip install ") and "rlexp[" not in hint
    named = {re.split(r"[<>=\[ ]", w.strip("'"))[0].lower() for w in shlex.split(hint)[2:]}
    declared = {
        re.split(r"[<>=\[ ]", req)[0].lower()
        for req in PYPROJECT["project"]["optional-dependencies"][extra]
    }
    assert named == declared


def test_every_imported_third_party_module_is_declared():
    """PyYAML was imported but not declared: every top-level import in src/rlexp of a module that
    is not stdlib, rlexp, or a dependency of a declared package, is one pyproject declares."""
    declared = " ".join(
        PYPROJECT["project"]["dependencies"]
        + [r for reqs in PYPROJECT["project"]["optional-dependencies"].values() for r in reqs]
    ).lower()
    import_names = {
        "yaml": "pyyaml", "hydra": "hydra-core", "hydra_plugins": "hydra-", "PIL": "pillow",
        "imageio_ffmpeg": "imageio[ffmpeg]",
    }  # fmt: skip
    found = set()
    for path in (REPO / "src/rlexp").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                found |= {alias.name.split(".")[0] for alias in node.names}
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                found.add(node.module.split(".")[0])
    stdlib = set(sys.stdlib_module_names) | {"rlexp", "__future__"}
    # probed, never required: triton comes with the CUDA build of torch (compile checks for it)
    transitive = {"triton"}
    for mod in sorted(found - stdlib - transitive):
        name = import_names.get(mod, mod.replace("_", "-")).lower()
        assert name in declared, f"src/rlexp imports {mod} but pyproject.toml declares no {name}"


def test_versions_are_ranges_and_ci_pins_the_tested_ones():
    deps = PYPROJECT["project"]["dependencies"]
    torchrl = next(d for d in deps if d.startswith("torchrl"))
    assert "==" not in torchrl and "<0.15" in torchrl  # a library ranges, CI pins
    ruff = next(d for d in PYPROJECT["project"]["optional-dependencies"]["dev"] if "ruff" in d)
    assert "<" in ruff
    pins = dict(
        line.split("==") for line in (REPO / "constraints.txt").read_text().splitlines()
        if "==" in line and not line.startswith("#")
    )  # fmt: skip
    assert pins["torchrl"] == "0.14.1" and pins["ruff"].startswith("0.17")
    ci = (REPO / ".ci/run").read_text()
    assert "make lint" in ci and "make test" in ci
