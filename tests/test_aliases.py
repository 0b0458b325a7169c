"""Keys typed in another library's vocabulary get the key they are here, on the command line and in
the docs (#30 item 4)."""

from __future__ import annotations

import re
import subprocess
import sys

import pytest

from conftest import REPO
from rlexp.config.aliases import ALIASES, alias_hint
from rlexp.config.validate import ConfigError
from rlexp.launch.precheck import check_key


@pytest.mark.parametrize(
    ("key", "expected", "wrong"),
    [
        # difflib guessed the wrong knob for these: value clipping, GRPO's KL, nothing at all
        ("algorithm.clip_range", "`algorithm.clip_epsilon` here", "clip_value"),
        ("algorithm.vf_coef", "`algorithm.critic_coeff` here", "kl_coeff"),
        ("algorithm.learning_rate", "`algorithm.lr` here", None),
        ("trainer.n_steps", "`trainer.frames_per_batch` here", None),
        ("algorithm.update_epochs", "`algorithm.num_epochs` here", None),
        ("policy.log_std_init", "`policy.init_log_std` here", None),
        ("gae_lambda", "`algorithm.lmbda` here", None),  # at the root, not in its section
        ("env.n_envs", "`env.num_envs` here", None),
    ],
)
def test_an_other_librarys_name_gets_its_rlexp_key(key, expected, wrong):
    with pytest.raises(ConfigError) as err:
        check_key(key)
    msg = str(err.value)
    assert msg.startswith(f"{key} is not a config key") and expected in msg
    if wrong:
        assert "did you mean" not in msg and wrong not in msg.split(";", 1)[1]


def test_a_name_of_no_library_still_gets_the_spelling_guess():
    with pytest.raises(ConfigError, match=r"did you mean algorithm\.gamma\?"):
        check_key("algorithm.gamme")
    assert alias_hint("algorithm.gamme") == ""


def test_the_command_line_answers_clip_range_with_clip_epsilon(tmp_path):
    proc = subprocess.run(
        [sys.executable, str(REPO / "train.py"), "algorithm.clip_range=0.1", "env.n_envs=4"],
        cwd=tmp_path, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert proc.returncode == 2
    assert (
        "`clip_range` (Stable-Baselines3, rl-zoo) is `algorithm.clip_epsilon` here" in proc.stderr
    )
    assert "Traceback" not in proc.stderr and not (tmp_path / "outputs").exists()


def test_every_alias_names_a_real_key_and_is_a_row_of_the_docs_table():
    from omegaconf import OmegaConf

    from conftest import compose

    cfg = compose([])
    rows = [
        line for line in (REPO / "docs/ppo.md").read_text().splitlines() if line.startswith("| ")
    ]
    for alias in ALIASES:
        if alias.key is not None:  # the key it points at exists in the composed config
            section, _, leaf = alias.key.rpartition(".")
            node = OmegaConf.select(cfg, section) if section else cfg
            assert node is not None and leaf in node, f"{alias.name} -> {alias.key}: no such key"
        named = [r for r in rows if re.search(rf"`{re.escape(alias.name)}`", r)]
        assert named, f"docs/ppo.md's table has no row naming `{alias.name}`"
        if alias.key is not None:
            assert any(f"`{alias.key}`" in r for r in named), (alias.name, alias.key, named)


def test_the_json_loaders_names_mean_what_the_command_lines_hints_say():
    """The JSON format and the hints know the same library names: they must agree on the key."""
    from rlexp.config.json_format.train_section import PPO_KEYS

    by_name = {alias.name: alias.key for alias in ALIASES}
    shared = [name for name in PPO_KEYS if name in by_name]
    assert len(shared) >= 6, shared  # learning_rate, n_epochs, batch_size, gae_lambda, clip_coef...
    for name in shared:
        assert by_name[name] == f"algorithm.{PPO_KEYS[name][0]}", name
