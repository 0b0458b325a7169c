"""docs/api.md is the public API: every name it lists imports, and every import the docs and the
example user project show is listed there."""

# layout_move.py: written for the new layout (it names old paths on purpose)

from __future__ import annotations

import importlib
import re

import pytest

from conftest import REPO

API = REPO / "docs" / "api.md"


def _rows() -> list[tuple[str, list[str]]]:
    rows = []
    for line in API.read_text().splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) >= 3 and cells[0].startswith("`rlexp"):
            rows.append((cells[0].strip("`"), re.findall(r"`(\w+)`", cells[1])))
    return rows


def test_the_api_page_lists_the_user_facing_modules():
    modules = {m for m, _ in _rows()}
    assert {"rlexp.events", "rlexp.hooks", "rlexp.envs.native", "rlexp.envs.batched"} <= modules
    assert "rlexp.checkpoint" in modules  # the moved module's shim
    assert all(names for _, names in _rows())


@pytest.mark.parametrize("module,names", _rows(), ids=lambda x: x if isinstance(x, str) else "")
def test_every_public_name_imports(module, names):
    mod = importlib.import_module(module)
    missing = [n for n in names if not hasattr(mod, n)]
    assert not missing, f"docs/api.md: {module} has no {missing}"


def test_the_shim_is_the_moved_module():
    from rlexp import checkpoint
    from rlexp.checkpoints import files

    assert checkpoint.load_checkpoint is files.load_checkpoint
    assert checkpoint.latest_good_checkpoint is files.latest_good_checkpoint  # any name, not a list
    assert "rlexp.checkpoints.files" in checkpoint.__doc__


def _shown_imports() -> set[tuple[str, str]]:
    """``from rlexp.x import a, b`` in docs/*.md, README.md and examples/user_project."""
    files = [*sorted((REPO / "docs").glob("*.md")), REPO / "README.md"]
    files += sorted((REPO / "examples" / "user_project").rglob("*.py"))
    found = set()
    for path in files:
        for module, names in re.findall(r"from (rlexp[\w.]*) import ([\w, ]+)", path.read_text()):
            found |= {(module, n.strip()) for n in names.split(",") if n.strip()}
    return found


def test_every_import_the_docs_show_is_on_the_api_page():
    listed = {(m, n) for m, names in _rows() for n in names}
    shown = _shown_imports()
    assert ("rlexp.events", "register_event") in shown
    unlisted = sorted(shown - listed)
    assert not unlisted, (
        f"docs/ or examples/user_project import names docs/api.md does not list: {unlisted}"
    )
