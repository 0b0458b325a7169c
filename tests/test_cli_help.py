"""What ``--help`` tells a new user (#30 item 5): only options that can be chosen, every default,
and a help text for every argument."""

from __future__ import annotations

import argparse
import os
import subprocess
import sys

import pytest

from conftest import REPO
from rlexp import cli

SUBCOMMANDS = ("eval", "export", "report", "runs", "compare")


def test_train_help_lists_the_group_options_but_not_the_schemas(tmp_path):
    out = subprocess.run(
        [sys.executable, "-m", "rlexp", "train", "--help"],
        cwd=tmp_path, capture_output=True, text=True, timeout=120,
        env={**os.environ, "PYTHONPATH": str(REPO / "src")},
    )  # fmt: skip
    assert out.returncode == 0, out.stderr
    groups = {
        line.split(":", 1)[0]: line.split(":", 1)[1].split(", ")
        for line in out.stdout.split("== Config ==")[0].splitlines()
        if ": " in line and not line.startswith(" ")
    }
    assert [o.strip() for o in groups["algorithm"]] == ["grpo", "ppo", "sac", "td3"]
    assert "hopper" in [o.strip() for o in groups["env"]]
    assert "_schema" not in out.stdout.split("== Config ==")[0]


def _parsers() -> dict[str, argparse.ArgumentParser]:
    """The subcommands' parsers, as ``rlexp`` builds them (``--help`` exits before running)."""
    found: dict[str, argparse.ArgumentParser] = {}
    original = argparse.ArgumentParser.parse_args

    def capture(self, args=None, namespace=None):
        for action in self._actions:
            if isinstance(action, argparse._SubParsersAction):
                found.update(action.choices)
        raise SystemExit(0)

    argparse.ArgumentParser.parse_args = capture  # type: ignore[method-assign]
    try:
        with pytest.raises(SystemExit):
            cli.main(["runs"])
    finally:
        argparse.ArgumentParser.parse_args = original  # type: ignore[method-assign]
    return found


@pytest.mark.parametrize("command", SUBCOMMANDS)
def test_every_argument_has_help_and_every_default_is_shown(command, capsys):
    parser = _parsers()[command]
    for action in parser._actions:
        if isinstance(action, argparse._HelpAction):
            continue
        assert action.help, f"rlexp {command}: {action.dest} has no help text"
    with pytest.raises(SystemExit):
        parser.parse_args(["--help"])
    text = " ".join(capsys.readouterr().out.split())  # argparse wraps lines: compare words
    for action in parser._actions:
        default = action.default
        if action.option_strings and default not in (None, False, argparse.SUPPRESS, []):
            shown = f"(default: {default})" in text or "default:" in (action.help or "")
            assert shown, (
                f"rlexp {command} --help: {action.dest}'s default {default!r} is not shown"
            )


def test_the_documented_defaults_are_the_values_used():
    parsers = _parsers()
    # None: the run's own trainer.eval_episodes, as its eval rounds (#45: the same numbers)
    assert parsers["eval"].parse_args(["x"]).episodes is None
    assert "the run's trainer.eval_episodes" in " ".join(parsers["eval"].format_help().split())
    assert parsers["export"].parse_args(["x"]).format == "torchscript"
    assert parsers["compare"].parse_args(["a", "b"]).metric == "eval/episode_return"
