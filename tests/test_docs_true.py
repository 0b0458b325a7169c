"""The docs say what the code does (#30 item 11), and stay so: every relative link resolves, every
extra and subcommand is in the README, the README's config table lists exactly the schemas' fields,
its layout every module, and no config file names a backend it does not use."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import pytest
import tomllib

from conftest import REPO
from rlexp.config import schema

README = (REPO / "README.md").read_text()
DOCS = sorted(
    [REPO / "README.md", *(REPO / "docs").glob("*.md"), *(REPO / "examples").rglob("*.md")]
)
LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")


def _slug(heading: str) -> str:
    """GitHub's anchor for a heading."""
    text = re.sub(r"[^\w\- ]", "", heading.strip().lower().replace("`", ""))
    return text.replace(" ", "-")


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: str(p.relative_to(REPO)))
def test_every_relative_link_resolves(doc: Path):
    text = re.sub(r"```.*?```", "", doc.read_text(), flags=re.S)  # code is not a link
    for target in LINK.findall(text):
        if re.match(r"[a-z]+:", target):  # http:, https:, mailto:
            continue
        path, _, anchor = target.partition("#")
        file = (doc.parent / path).resolve() if path else doc
        assert file.exists(), f"{doc.relative_to(REPO)}: link {target} -> {file} does not exist"
        if anchor and file.suffix == ".md":
            headings = re.findall(r"^#+ (.+)$", file.read_text(), re.M)
            assert anchor in {_slug(h) for h in headings}, (
                f"{doc.relative_to(REPO)}: link {target}: no heading #{anchor} in {file.name}"
            )


def test_every_extra_and_subcommand_is_in_the_readme():
    extras = tomllib.loads((REPO / "pyproject.toml").read_text())["project"][
        "optional-dependencies"
    ]
    for extra in extras:
        assert f"`{extra}`" in README, f"the README's extras table has no row for {extra!r}"
    from test_cli_help import _parsers

    for command in ["train", *_parsers()]:
        assert f"rlexp {command}" in README, f"the README never mentions `rlexp {command}`"


def _fields(cls) -> set[str]:
    return {f.name for f in dataclasses.fields(cls)} - {"name"}


def _table_row(group: str) -> str:
    return next(line for line in README.splitlines() if line.startswith(f"| `{group}` |"))


@pytest.mark.parametrize(
    ("group", "classes"),
    [
        ("trainer", [schema.TrainerConfig]),
        ("policy", [schema.PolicyConfig, schema.ActorOnlyConfig]),
        ("algorithm", [schema.AlgorithmConfig, schema.GRPOConfig]),
        ("env", [schema.EnvConfig]),
        ("events", [schema.EventsConfig]),
        ("logger", [schema.LoggerConfig]),
    ],
)
def test_the_readme_config_table_lists_exactly_the_schemas_fields(group, classes):
    """The schema column names each field as `field` (or `{a, b}` inside a nested one)."""
    cell = _table_row(group).split(" | ")[2]
    listed = set(re.findall(r"`([a-z_]+)`", cell)) | {
        name for inner in re.findall(r"\{([^}]*)\}", cell) for name in re.findall(r"[a-z_]+", inner)
    }
    fields = set().union(*(_fields(c) for c in classes))
    nested = {f.name for c in classes for f in dataclasses.fields(c)
              if dataclasses.is_dataclass(f.type if not isinstance(f.type, str) else None)}  # fmt: skip
    missing = fields - listed
    assert not missing, f"README's {group} row does not list {sorted(missing)}"
    unknown = {
        name for name in listed - fields - nested
        if re.fullmatch(r"[a-z]+(_[a-z]+)+", name) and name not in _sub_fields(classes)
    }  # fmt: skip
    assert not unknown, f"README's {group} row lists {sorted(unknown)}, which the schema lacks"


def _sub_fields(classes) -> set[str]:
    """Fields of the nested schemas (policy.actor's hidden_sizes) and of group options' files."""
    out: set[str] = set()
    nested = [
        schema.MLPConfig,
        schema.EncoderConfig,
        schema.MemoryConfig,
        schema.TensorBoardConfig,
        schema.WandbConfig,
    ]
    for cls in [*nested, *classes]:
        out |= {f.name for f in dataclasses.fields(cls)}
    return out


def test_the_readme_layout_names_every_module():
    layout = README.split("## Layout", 1)[1].split("```", 2)[1]
    src = REPO / "src" / "rlexp"
    for path in sorted(src.iterdir()):
        if path.name.startswith(("_", ".")) or path.name == "__pycache__":
            continue
        name = f"{path.name}/" if path.is_dir() else path.name
        if path.is_dir() or path.suffix == ".py":
            assert re.search(rf"(?<![\w.]){re.escape(name)}", layout), (
                f"README's layout does not name src/rlexp/{name}"
            )


def test_no_env_config_names_a_backend_it_does_not_use():
    for path in sorted((REPO / "conf" / "env").glob("*.yaml")):
        text = path.read_text()
        if "TorchRL's GymEnv" in text:
            assert "backend: torchrl_gym" in text, f"{path.name} says TorchRL's GymEnv"


def test_no_doc_heading_is_doubled():
    for doc in DOCS:
        lines = [line for line in doc.read_text().splitlines() if line.strip()]
        for a, b in zip(lines, lines[1:], strict=False):
            assert not (a.startswith("#") and a == b), f"{doc.name}: heading {a!r} twice"
