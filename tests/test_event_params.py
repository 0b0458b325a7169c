"""Event parameters: every one has a rule, a bad one is a config error naming its key before the run
writes anything, event files stay inside the run dir, and record_video checks that it can render."""

from __future__ import annotations

import inspect
import json
import re
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from tensordict import TensorDict

from conftest import REPO, TINY, compose, run_train
from rlexp.config.native_task import EventTermConfig
from rlexp.config.validate import ConfigError, to_root_config
from rlexp.envs.factory import make_env
from rlexp.events import EventContext, EventManager, builtin
from rlexp.events.manager import EVENT_FUNCS

BUILTIN = {n: f for n, f in EVENT_FUNCS.items() if getattr(f, "__module__", "") == builtin.__name__}


def _manager(func: str, params: dict, mode: str, phase: str = "train") -> EventManager:
    ev = EventTermConfig(func=func, mode=mode, params=params)
    return EventManager({func: ev}, f"events.{phase}")


# --- A: paths ----------------------------------------------------------------------------------------

PATH_CASES = [
    ("record_rollouts", "interval", "train", {"save_path": "../../x"}, "params.save_path", "leaves the run dir"),
    ("record_rollouts", "interval", "train", {"save_path": "a/../../x"}, "params.save_path", "leaves the run dir"),
    ("record_rollouts", "interval", "train", {"save_path": "/x"}, "params.save_path", "outside the run dir"),
    ("record_video", "interval", "eval", {"name": "../../x"}, "params.name", "safe file name"),
    ("record_video", "interval", "eval", {"name": "a/b"}, "params.name", "safe file name"),
    ("record_video", "interval", "eval", {"name": ".."}, "params.name", "safe file name"),
    ("record_video", "interval", "eval", {"save_path": "../x"}, "params.save_path", "leaves the run dir"),
    ("record_video", "interval", "eval", {"save_path": "/tmp/v"}, "params.save_path", "allow_outside_run_dir=true"),
    ("record_video", "interval", "eval", {"allow_outside_run_dir": True, "save_path": "v"}, "allow_outside_run_dir", "absolute save_path"),
]  # fmt: skip


@pytest.mark.parametrize(("func", "mode", "phase", "params", "key", "why"), PATH_CASES)
def test_paths_that_would_leave_the_run_dir_are_config_errors(func, mode, phase, params, key, why):
    with pytest.raises(ValueError) as err:
        _manager(func, params, mode, phase)
    msg = str(err.value)
    assert msg.startswith(f"events.{phase}.{func}.") and key in msg and why in msg, msg


def _batch(n: int = 2, t: int = 3) -> TensorDict:
    obs = torch.zeros(n, t, 4)
    flags = torch.zeros(n, t, 1, dtype=torch.bool)
    nxt = {"observation": obs, "reward": torch.ones(n, t, 1), "done": flags}
    nxt.update(terminated=flags, truncated=flags)
    return TensorDict({"observation": obs, "action": torch.zeros(n, t, 1), "next": nxt}, [n, t])


def _fire_rollouts(run_dir: Path, **params) -> None:
    m = _manager("record_rollouts", params, "interval")
    m.fire("interval", EventContext(run_dir=run_dir, batch=_batch(), global_step=7))


def test_write_time_refuses_links_out_of_the_run_dir(tmp_path):
    outside, run_dir = tmp_path / "outside", tmp_path / "run"
    outside.mkdir()
    run_dir.mkdir()
    # a folder of the run dir that is a link to elsewhere: refused, nothing written there
    (run_dir / "rollouts").symlink_to(outside, target_is_directory=True)
    with pytest.raises(ValueError, match=r"events.train.record_rollouts.params.save_path='rollouts' resolves to .*outside the run dir"):  # fmt: skip
        _fire_rollouts(run_dir)
    (run_dir / "rollouts").unlink()
    # the file itself a link to a file elsewhere: the link is replaced, the target untouched
    (run_dir / "rollouts").mkdir()
    victim = outside / "victim.txt"
    victim.write_text("keep")
    (run_dir / "rollouts" / "step_000000007.npz").symlink_to(victim)
    _fire_rollouts(run_dir)
    assert victim.read_text() == "keep"
    written = run_dir / "rollouts" / "step_000000007.npz"
    assert not written.is_symlink() and int(np.load(written)["global_step"]) == 7
    assert sorted(p.name for p in (run_dir / "rollouts").iterdir()) == ["step_000000007.npz"]
    # a relative save_path inside the run dir
    _fire_rollouts(run_dir, save_path="data/rollouts")
    assert (run_dir / "data" / "rollouts" / "step_000000007.npz").is_file()
    assert sorted(p.name for p in outside.iterdir()) == ["victim.txt"]


def test_an_outside_folder_only_with_the_explicit_absolute_opt_in(tmp_path):
    scratch, run_dir = tmp_path / "scratch", tmp_path / "run"
    run_dir.mkdir()
    _fire_rollouts(run_dir, save_path=str(scratch), allow_outside_run_dir=True)
    assert [p.name for p in scratch.iterdir()] == ["step_000000007.npz"]


def test_video_name_and_links_checked_again_when_the_file_is_written(tmp_path):
    """The video's folder is checked when it is written, even if the run dir changed meanwhile."""
    outside, run_dir = tmp_path / "outside", tmp_path / "run"
    outside.mkdir()
    run_dir.mkdir()
    (run_dir / "videos").symlink_to(outside, target_is_directory=True)
    m = _manager("record_video", {"name": "cam"}, "interval", "eval")
    video = m.events[0][2]
    video.frames = [np.zeros((8, 8, 3), np.uint8)] * 2
    with pytest.raises(ValueError, match="outside the run dir"):
        m.finalize(EventContext(run_dir=run_dir, global_step=1))
    assert list(outside.iterdir()) == []


def test_a_path_error_exits_2_before_anything_is_written(tmp_path):
    cwd = tmp_path / "a" / "b"
    cwd.mkdir(parents=True)
    proc = run_train(
        [*TINY, "events=record_rollouts", "+events.train.record_rollouts.params.save_path=../../x"],
        cwd=cwd,
        check=False,
    )
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert (
        "events.train.record_rollouts.params.save_path='../../x' leaves the run dir" in proc.stderr
    )
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["a", "b"]


def test_the_json_formats_camera_event_paths_are_checked_the_same(tmp_path):
    """record_camera_data_async runs as record_video: its save_path / name obey the same rules."""
    folder = tmp_path / "files"
    folder.mkdir()
    src = REPO / "examples" / "json" / "push_cube"
    train = json.loads((src / "train_config.json").read_text())
    params = train["trainer"]["events"]["eval"]["record_camera"]["params"]
    params["save_path"] = "../../x"
    (folder / "train_config.json").write_text(json.dumps(train))
    (folder / "gym_config.json").write_text((src / "gym_config.json").read_text())
    work = tmp_path / "work" / "w"
    work.mkdir(parents=True)
    proc = run_train(["--config-json", str(folder / "train_config.json")], cwd=work, check=False)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert "events.eval.record_camera.params.save_path='../../x' leaves the run dir" in proc.stderr
    assert list(work.iterdir()) == [] and not (tmp_path / "x").exists()


# --- B: values ---------------------------------------------------------------------------------------

BAD = [
    ("randomize_physics", "reset", "train", {"mass_range": [0, 1.2]}, "params.mass_range=[0, 1.2]", "low 0 is not > 0"),
    ("randomize_physics", "reset", "train", {"mass_range": [1.2, 0.8]}, "params.mass_range=[1.2, 0.8]", "low 1.2 > high 0.8"),
    ("randomize_physics", "reset", "train", {"friction_range": [-0.5, 1.0]}, "params.friction_range", "low > 0"),
    ("randomize_physics", "reset", "train", {"damping_range": [0.5]}, "params.damping_range", "2 values, got 1"),
    ("randomize_physics", "reset", "train", {"actuator_gain_range": [0.9, float("inf")]}, "params.actuator_gain_range[1]=inf", "finite"),
    ("randomize_physics", "reset", "train", {"mass_range": "0.8-1.2"}, "params.mass_range='0.8-1.2'", "[low, high]"),
    ("randomize_physics", "reset", "train", {"mass_rnge": [0.8, 1.2]}, "params.mass_rnge", "did you mean 'mass_range'?"),
    ("randomize_physics", "reset", "train", {}, "params is empty", "at least one of"),
    ("randomize_physics", "step", "train", {"mass_range": [0.8, 1.2]}, "mode='step'", "reset"),
    ("randomize_object_pose", "reset", "train", {"entity_cfg": {"uid": "cube"}, "position_range": [[0.2, 0, 0], [-0.2, 0, 0]]}, "params.position_range", "x low 0.2 > high -0.2"),
    ("randomize_object_pose", "reset", "train", {"entity_cfg": "cube", "position_range": [[0, 0, 0], [0, 0, 0]]}, "params.entity_cfg='cube'", "{uid:"),
    ("randomize_goal_pose", "reset", "train", {"position_range": [[0, 0], [1, 1]]}, "params.position_range[0]=[0, 0]", "3 values"),
    ("randomize_goal_pose", "reset", "train", {}, "params", "needs parameter(s) ['position_range']"),
    ("observation_noise", "step", "train", {"std": -1}, "params.std=-1", ">= 0"),
    ("observation_noise", "step", "train", {"std": 0.1, "clip": 0}, "params.clip=0", "> 0"),
    ("observation_noise", "step", "train", {"sdt": 0.1}, "params.sdt", "did you mean 'std'?"),
    ("observation_noise", "reset", "train", {"std": 0.1}, "mode='reset'", "step only"),
    ("observation_noise", "step", "eval", {"std": 0.1}, "observation_noise", "events.train only"),
    ("action_noise", "step", "train", {"std": float("nan")}, "params.std=nan", "finite"),
    ("action_noise", "step", "train", {"std": True}, "params.std=True", "a number"),
    ("record_rollouts", "interval", "train", {"every": 2}, "params.every", "unknown parameter"),
    ("record_rollouts", "interval", "eval", {}, "record_rollouts", "events.train only"),
    ("record_video", "interval", "eval", {"resolution": [0, 480]}, "params.resolution=[0, 480]", "width=0"),
    ("record_video", "interval", "eval", {"resolution": [640, 480, 3]}, "params.resolution", "2 values, got 3"),
    ("record_video", "interval", "eval", {"resolution": [640.5, 480]}, "params.resolution[0]=640.5", "integer"),
    ("record_video", "interval", "eval", {"fps": 0}, "params.fps=0", "> 0"),
    ("record_video", "interval", "eval", {"fps": -25}, "params.fps=-25", "> 0"),
    ("record_video", "interval", "eval", {"intrinsics": [600, 600, 320]}, "params.intrinsics", "[fx, fy, cx, cy] (4 values, got 3)"),
    ("record_video", "interval", "eval", {"intrinsics": [0, 600, 320, 240]}, "params.intrinsics", "fx=0"),
    ("record_video", "interval", "eval", {"intrinsics": [600, 600, 320, 240], "fovy": 45}, "params", "intrinsics or fovy, not both"),
    ("record_video", "interval", "eval", {"fovy": 180}, "params.fovy=180", "< 180"),
    ("record_video", "interval", "eval", {"eye": [1, 1, 1], "target": [1, 1, 1]}, "params", "same point"),
    ("record_video", "interval", "eval", {"eye": [0, 0, 2], "target": [0, 0, 0]}, "params.up", "parallel"),
    ("record_video", "interval", "eval", {"eye": [0, 0]}, "params.eye", "3 values"),
    ("record_video", "interval", "eval", {"env_id": -1}, "params.env_id=-1", ">= 0"),
    ("record_video", "interval", "eval", {"max_frames": 0}, "params.max_frames=0", ">= 1"),
    ("record_video", "interval", "eval", {"resolution": [1280, 960], "max_frames": 5000}, "params", "GiB"),
    ("record_video", "interval", "eval", {"resolutoin": [64, 48]}, "params.resolutoin", "did you mean 'resolution'?"),
    ("record_video", "interval", "train", {}, "record_video", "events.eval only"),
    ("record_video", "trigger", "eval", {"signal": "eval_end"}, "mode='trigger'", "interval / step"),
]  # fmt: skip


@pytest.mark.parametrize(("func", "mode", "phase", "params", "key", "why"), BAD)
def test_bad_event_params_name_the_key(func, mode, phase, params, key, why):
    with pytest.raises((ValueError, TypeError, KeyError)) as err:
        _manager(func, params, mode, phase)
    msg = str(err.value.args[0])
    assert msg.startswith(f"events.{phase}.{func}") and key in msg and why in msg, msg
    assert "\n" not in msg


def test_trigger_signals_and_modes_the_managers_never_fire():
    cases = [
        ("train", "trigger", {"signal": "new_bset"}, "did you mean 'new_best'?"),
        ("train", "trigger", {}, "params.signal is needed with mode=trigger"),
        ("train", "reset", {"signal": "new_best"}, "applies to mode=trigger only"),
        ("eval", "trigger", {"signal": "new_best"}, "is never sent"),
        ("eval", "startup", {}, "events.eval never fires startup events"),
    ]
    for phase, mode, extra, why in cases:
        ev = EventTermConfig(func="randomize_physics", mode=mode)
        ev.params = {"mass_range": [0.8, 1.2], **extra}
        with pytest.raises(ValueError, match=re.escape(why)):
            EventManager({"dr": ev}, f"events.{phase}")
    ev = EventTermConfig(func="randomize_physics", mode="trigger")
    ev.params = {"mass_range": [0.8, 1.2], "signal": "checkpoint"}
    EventManager({"dr": ev}, "events.train")
    with pytest.raises(TypeError, match="interval_step='2' must be an integer"):
        EventManager({"dr": EventTermConfig(func="randomize_physics", interval_step="2")}, "x")


def test_the_config_validation_refuses_them_before_any_env_is_built():
    """``to_root_config`` (what train.py's precheck runs first) checks the params: a mass range
    with 0 used to run 'unstable' to exit 0."""
    with pytest.raises(ConfigError, match=r"events.train.randomize_physics.params.mass_range=\[0, 1.2\]"):  # fmt: skip
        to_root_config(
            compose(
                [
                    "events=domain_randomization",
                    "events.train.randomize_physics.params.mass_range=[0,1.2]",
                ]
            )  # fmt: skip
        )
    with pytest.raises(ConfigError, match=r"events.eval.record_video.params.fps=0 must be"):
        to_root_config(compose(["events=eval_video", "+events.eval.record_video.params.fps=0"]))
    for preset in ("domain_randomization", "eval_video", "noise", "record_rollouts", "none"):
        to_root_config(compose([f"events={preset}"]))  # the shipped presets pass


def test_events_without_rules_are_held_to_their_signature():
    from rlexp.events import register_event

    @register_event("_test_sig")
    def _sig(ctx: EventContext, gain: float, offset: float = 0.0) -> None:
        return None

    with pytest.raises(TypeError, match=r"events.train.s.params.gian: .*did you mean 'gain'\?"):
        EventManager({"s": EventTermConfig(func="_test_sig", params={"gian": 1})}, "events.train")
    with pytest.raises(TypeError, match=r"needs parameter\(s\) \['gain'\]"):
        EventManager({"s": EventTermConfig(func="_test_sig", params={"offset": 1})}, "events.train")
    EventManager({"s": EventTermConfig(func="_test_sig", params={"gain": 1})}, "events.train")


def _doc_rows(path: Path) -> dict[tuple[str, str], str]:
    rows = {}
    for line in path.read_text().splitlines():
        m = re.match(r"\| `([\w.]+)` \| `(\w+)` \| [^|]* \| (.*?) \|$", line)
        if m:  # | func | param | default | rule |
            rows[(m.group(1), m.group(2))] = m.group(3)
    return rows


def test_every_builtin_event_parameter_has_a_rule_and_a_docs_row():
    rows = _doc_rows(REPO / "docs" / "events.md")
    assert set(BUILTIN) == {
        "randomize_physics", "randomize_object_pose", "randomize_goal_pose", "observation_noise",
        "action_noise", "record_rollouts", "record_video",
    }  # fmt: skip
    for name, func in BUILTIN.items():
        rules = func.PARAMS
        targets = (
            [func.__call__, getattr(func, "finalize", None)] if isinstance(func, type) else [func]
        )
        for target in filter(None, targets):
            for p in list(inspect.signature(target).parameters.values())[1:]:
                if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY) and p.name != "ctx":
                    assert p.name in rules, f"{name}({p.name}) has no rule"
        for key, rule in rules.items():
            assert rows.get((name, key)) == rule.text, f"docs/events.md row for {name}.{key}"
    assert {k for k in rows if k[0] in BUILTIN} == {
        (n, k) for n, f in BUILTIN.items() for k in f.PARAMS
    }


# --- C: can it render? ---------------------------------------------------------------------------------


def _video(**params) -> EventManager:
    return _manager("record_video", params, "interval", "eval")


def _native(task: str = "push_cube"):
    return make_env(to_root_config(compose([f"env={task}"])).env, 1, seed=0)


def test_record_video_renders_one_frame_before_the_run():
    env = _native("cart_pole")
    _video(resolution=[64, 48], eye=[0, -3, 1], target=[0, 0, 0.5]).check_env(env, num_envs=2)
    with pytest.raises(ValueError) as err:
        _video(resolution=[2000, 480], max_frames=100).check_env(env, num_envs=2)
    msg = str(err.value)
    assert (
        msg.startswith("events.eval.record_video: cannot render 2000x480 offscreen")
        and "1280x960" in msg
    )
    with pytest.raises(ValueError, match=r"params.env_id=2 but the eval env has 2 copies"):
        _video(env_id=2).check_env(env, num_envs=2)


def test_record_video_without_a_gl_backend_is_one_line(monkeypatch):
    """MuJoCo keeps the backend it read at import: simulate GLFW on a machine without a display."""
    import mujoco  # noqa: F401

    gl = sys.modules["mujoco.rendering.classic.gl_context"]
    env = _native("cart_pole")
    for backend, why in (
        ("glfw", "renders through a window system and DISPLAY is not set"),
        ("disable", "turns rendering off"),
    ):
        monkeypatch.setattr(gl, "_MUJOCO_GL", backend)
        monkeypatch.delenv("DISPLAY", raising=False)
        monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
        with pytest.raises(ValueError) as err:
            _video().check_env(env)
        assert str(err.value) == (
            f"events.eval.record_video: cannot render 640x480 offscreen: MUJOCO_GL={backend!r} {why}; "
            "use MUJOCO_GL=egl (Debian: libegl1 libegl-mesa0) or MUJOCO_GL=osmesa (libosmesa6)"
        )


def test_a_mujoco_gl_mujoco_cannot_import_with_is_a_config_error(tmp_path):
    proc = run_train([*TINY, "events=eval_video"], cwd=tmp_path, check=False, env_extra={"MUJOCO_GL": "foo"})  # fmt: skip
    assert proc.returncode == 2, proc.stderr[-2000:]
    # Caught before MuJoCo loads (it would abort every MuJoCo env, not only the video).
    assert proc.stderr.strip().splitlines()[-1] == (
        "config error: MUJOCO_GL='foo' "
        "is not a MuJoCo GL backend (MuJoCo accepts ['egl', 'osmesa'] or glfw/glx); use "
        "MUJOCO_GL=egl (Debian: libegl1 libegl-mesa0) or MUJOCO_GL=osmesa (libosmesa6)"
    )
    assert list(tmp_path.iterdir()) == []


def test_a_gymnasium_env_needs_render_mode_to_record_video(caplog):
    env = make_env(to_root_config(compose(TINY[:1])).env, 1, seed=0)
    with pytest.raises(ValueError) as err:
        _video().check_env(env)
    assert str(err.value).startswith("events.eval.record_video: cannot render 640x480 offscreen: ")
    assert "render_mode=rgb_array" in str(err.value)
    config = to_root_config(compose([TINY[0], "+env.kwargs.render_mode=rgb_array"]))
    _video().check_env(make_env(config.env, 1, seed=0), num_envs=1)  # its own size: a warning
    assert "renders 480x480 frames with its own camera" in caplog.text


def test_env_checks_of_the_randomisation_events():
    gym_env = make_env(to_root_config(compose(TINY[:1])).env, 1, seed=0)
    pose = {"entity_cfg": {"uid": "cube"}, "position_range": [[0, 0, 0], [0.1, 0.1, 0]]}
    with pytest.raises(TypeError, match="events.train.randomize_object_pose: .*native tasks"):
        _manager("randomize_object_pose", pose, "reset").check_env(gym_env)
    env = _native("push_cube")
    _manager("randomize_object_pose", pose, "reset").check_env(env)
    bad = {**pose, "entity_cfg": {"uid": "cub"}}
    with pytest.raises(KeyError, match=r"params.entity_cfg.uid='cub' .*did you mean 'cube'"):
        _manager("randomize_object_pose", bad, "reset").check_env(env)
    _manager("randomize_physics", {"mass_range": [0.8, 1.2]}, "reset").check_env(gym_env)
