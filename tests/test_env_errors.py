"""Env-side mistakes as one line (#45 item 7): an ``env.kwargs`` key the env's constructor does not
take gets a did-you-mean from its signature; a video (the ``record_video`` event, a
``render_mode`` kwarg, ``rlexp eval --video``) on an env whose constructor takes no ``render_mode``
says so in one line, exit 2, instead of Gymnasium's TypeError."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from conftest import REPO, compose, rlexp_cli, run_train

TESTS = Path(__file__).resolve().parent
PYPATH = {"PYTHONPATH": f"{REPO / 'src'}{os.pathsep}{TESTS}"}
KNOBS = ["env=hopper", "env.name=toy_envs:Knobs-v0"]


def _check(overrides: list[str]) -> str:
    from rlexp.config.validate import ConfigError, to_root_config
    from rlexp.launch.checks import check_buildable

    with pytest.raises(ConfigError) as err:
        check_buildable(to_root_config(compose(overrides)))
    text = str(err.value)
    assert len(text.splitlines()) == 1, text
    return text


@pytest.mark.parametrize(
    ("overrides", "words"),
    [
        (
            [*KNOBS, "+env.kwargs.sped=2"],
            ["env.kwargs.sped is not an argument", "did you mean 'speed'?", "takes: size, speed"],
        ),
        (
            [*KNOBS, "+env.kwargs.sise=2", "+env.kwargs.speed=1"],
            ["env.kwargs.sise", "did you mean 'size'?"],
        ),
        (
            ["env=hopper", "env.name=Pendulum-v1", "+env.kwargs.rendr_mode=rgb_array"],
            ["env.kwargs.rendr_mode", "did you mean 'render_mode'?", "takes: render_mode, g"],
        ),
        (  # a MuJoCo task's constructor also takes **kwargs: its named arguments still suggest
            ["env=half_cheetah", "+env.kwargs.forward_reward=2"],
            ["env.kwargs.forward_reward", "did you mean 'forward_reward_weight'?"],
        ),
    ],
)
def test_an_env_kwarg_typo_names_the_closest_constructor_argument(overrides, words):
    text = _check(overrides)
    for word in words:
        assert word in text, text


@pytest.mark.parametrize(
    "extra",
    [["events=eval_video"], ["+env.kwargs.render_mode=rgb_array"]],
    ids=["record_video", "render_mode_kwarg"],
)
def test_a_video_on_an_env_that_cannot_render_is_one_line(extra):
    text = _check([*KNOBS, *extra])
    assert "env.name='toy_envs:Knobs-v0' cannot render" in text, text
    assert "constructor takes no render_mode (it takes: size, speed)" in text, text


def test_the_command_line_says_it_in_one_line_and_exit_2(tmp_path):
    proc = run_train(
        [*KNOBS, "+env.kwargs.sped=2", f"hydra.run.dir={tmp_path / 'r'}"],
        cwd=tmp_path, env_extra=PYPATH, check=False,
    )  # fmt: skip
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr and "did you mean 'speed'?" in proc.stderr
    assert not (tmp_path / "r").exists()


def test_rlexp_eval_video_of_an_env_that_cannot_render_is_one_line_exit_2(tmp_path):
    run_dir = tmp_path / "knobs"
    run_train(
        [
            *KNOBS,
            "trainer.frames_per_batch=128",
            "trainer.total_frames=128",
            "trainer.eval_every=128",
            "trainer.eval_episodes=1",
            "trainer.save_every=128",
            "trainer.progress=false",
            f"hydra.run.dir={run_dir}",
        ],
        cwd=tmp_path,
        env_extra=PYPATH,
    )
    code, out, err = rlexp_cli("eval", run_dir, "--video", tmp_path / "v.mp4")
    assert code == 2, err
    assert err.strip() == (
        "rlexp eval: --video: env.name='toy_envs:Knobs-v0' cannot render: its constructor takes "
        "no render_mode (it takes: size, speed); give it a render_mode='rgb_array' argument that "
        "returns frames from render(), or record no video"
    )
    assert not (tmp_path / "v.mp4").exists()
