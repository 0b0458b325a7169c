"""Event managers: resolution and errors, firing order and modes, the built-in events, their state."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from torchrl.envs import TransformedEnv

from conftest import only_run_dir, run_train
from rlexp.config.native_task import EventTermConfig
from rlexp.config.schema import EnvConfig
from rlexp.envs.factory import make_env
from rlexp.events import EventContext, EventManager, register_event
from rlexp.events.transform import EventTransform

CALLS: list[tuple[str, object]] = []


@register_event("_test_record")
def _record(ctx: EventContext, tag: str = "", **_):
    CALLS.append((tag, ctx.signal if ctx.signal else ctx.global_step))


def _ev(**kw) -> EventTermConfig:
    return EventTermConfig(**kw)


def test_unknown_func_and_mode_name_the_event_and_the_choices():
    with pytest.raises(ValueError) as err:
        EventManager({"dr": _ev(func="randomize_phisics", mode="reset")}, "events.train")
    msg = str(err.value)
    assert (
        "events.train.dr.func='randomize_phisics'" in msg
        and "did you mean 'randomize_physics'" in msg
    )
    with pytest.raises(ValueError) as err:
        EventManager({"dr": _ev(func="randomize_physics", mode="on_reset")}, "events.train")
    assert "events.train.dr.mode='on_reset'" in str(err.value) and "'reset'" in str(err.value)


def test_dotted_paths_only_inside_the_allowlist():
    with pytest.raises(ValueError, match="dotted paths must be inside"):
        EventManager({"x": _ev(func="os.system", mode="startup")}, "events.train")
    m = EventManager(
        {"x": _ev(func="rlexp.events.builtin.observation_noise", mode="step")}, "events.train"
    )
    assert m.has("step")


def test_order_modes_interval_and_triggers():
    CALLS.clear()
    m = EventManager(
        {
            "b": _ev(func="_test_record", mode="interval", interval_step=2, params={"tag": "b"}),
            "a": _ev(func="_test_record", mode="interval", interval_step=1, params={"tag": "a"}),
            "t": _ev(
                func="_test_record", mode="trigger", params={"tag": "t", "signal": "new_best"}
            ),
            "s": _ev(func="_test_record", mode="startup", params={"tag": "s"}),
        },
        "events.train",
    )
    m.fire("startup", EventContext(global_step=0))
    for step in (1, 2, 3, 4):
        m.fire("interval", EventContext(global_step=step))
    m.fire("trigger", EventContext(), signal="eval_end")
    m.fire("trigger", EventContext(), signal="new_best")
    assert CALLS == [
        ("s", 0),
        ("a", 1),
        ("b", 2),
        ("a", 2),
        ("a", 3),
        ("b", 4),
        ("a", 4),
        ("t", "new_best"),
    ]


def test_event_state_round_trip_counters_and_rng():
    cfg = {
        "n": _ev(func="observation_noise", mode="step"),
        "i": _ev(func="_test_record", mode="interval"),
    }
    m = EventManager(cfg, "events.train", seed=3)
    m.fire("interval", EventContext())
    m.rng.normal(size=5)
    sd = m.state_dict()
    expected = m.rng.normal(size=3)
    m2 = EventManager(cfg, "events.train", seed=99)
    m2.load_state_dict(sd)
    assert m2.counters == {"n": 0, "i": 1}
    np.testing.assert_array_equal(m2.rng.normal(size=3), expected)


def _push_cube(n=4):
    from conftest import compose
    from rlexp.config.validate import to_root_config

    cfg = to_root_config(compose(["env=push_cube"])).env
    return make_env(cfg, n, seed=0)


def test_randomize_physics_per_env_id_native():
    env = _push_cube(4)
    m = EventManager(
        {
            "dr": _ev(
                func="randomize_physics",
                mode="reset",
                params={
                    "mass_range": [0.5, 1.5],
                    "friction_range": [0.8, 1.2],
                    "damping_range": [0.9, 1.1],
                    "actuator_gain_range": [0.7, 1.3],
                },
            )
        },
        "events.train",
    )
    nominal_mass = env.model.body_mass.copy()
    m.fire("reset", EventContext(env=env, env_ids=np.array([1, 3])))
    assert (
        env._models[0] is env.model and env._models[2] is env.model
    )  # untouched envs share the model
    for i in (1, 3):
        ratio = env._models[i].body_mass[nominal_mass > 0] / nominal_mass[nominal_mass > 0]
        assert ((ratio >= 0.5) & (ratio <= 1.5)).all() and not np.allclose(ratio, 1.0)
        kp = env._models[i].actuator_gainprm[:, 0] / env.model.actuator_gainprm[:, 0]
        np.testing.assert_allclose(
            env._models[i].actuator_biasprm[:, 1] / env.model.actuator_biasprm[:, 1], kp
        )
    np.testing.assert_array_equal(env.model.body_mass, nominal_mass)
    # The physics really uses the per-env model: same state and action, different outcomes.
    td = env.reset()
    state = env.env_state()
    for key in ("physics_state", "ctrl"):
        state[key][:] = state[key][0]
    env.load_env_state(state)
    td = env.reset()
    td["action"] = torch.ones(4, env.action_spec.shape[-1]) * 0.5
    env.step(td)
    qpos = env.env_state()["qpos"]
    np.testing.assert_array_equal(qpos[0], qpos[2])
    assert not np.array_equal(qpos[0], qpos[1])
    # Its state re-applies on load (a resumed run keeps the randomised physics).
    sd = m.state_dict()
    env2 = _push_cube(4)
    m2 = EventManager(
        {"dr": _ev(func="randomize_physics", mode="reset", params={"mass_range": [0.5, 1.5]})},
        "events.train",
    )
    m2.load_state_dict(sd, env2)
    np.testing.assert_array_equal(env2._models[1].body_mass, env._models[1].body_mass)


def test_randomize_physics_gymnasium():
    env = make_env(EnvConfig(name="Hopper-v5"), 2, seed=0)
    m = EventManager(
        {"dr": _ev(func="randomize_physics", mode="reset", params={"mass_range": [2.0, 3.0]})},
        "events.train",
    )
    m.fire("reset", EventContext(env=env, env_ids=np.array([0])))
    m0, m1 = (env._envs[i].unwrapped.model.body_mass for i in (0, 1))
    assert (m0[1:] / m1[1:] >= 2.0).all() and (m0[1:] / m1[1:] <= 3.0).all()


def test_observation_and_action_noise_through_the_transform():
    base = make_env(EnvConfig(name="InvertedPendulum-v5"), 1, seed=0)
    m = EventManager(
        {
            "on": _ev(func="observation_noise", mode="step", params={"std": 0.5}),
            "an": _ev(func="action_noise", mode="step", params={"std": 0.5}),
        },
        "events.train",
    )
    env = TransformedEnv(base, EventTransform(m))
    td = env.reset()
    td["action"] = torch.zeros(1, 1)
    out = env.step(td)
    # The env executed a noisy action; the stored action is the policy's own.
    assert out["action"].item() == 0.0
    assert abs(base._envs[0].unwrapped.data.ctrl[0]) > 0
    # The observation the policy sees is noisy: it differs from the simulator's own.
    sim_obs = torch.as_tensor(base._envs[0].unwrapped._get_obs(), dtype=torch.float32)
    assert not torch.allclose(out["next", "observation"][0], sim_obs, atol=1e-3)


def _offscreen_gl_or_skip() -> None:
    """Skip, saying why, where this machine has no offscreen GL backend (as
    tests/envs/test_native_render.py does); any other rendering error fails."""
    from rlexp.envs.native import default_task_config, make_native_env
    from rlexp.envs.native.render import GL_FIX, gl_problem

    problem = gl_problem()
    if problem is not None:
        pytest.skip(f"no OpenGL backend: {problem}; {GL_FIX}")
    env = make_native_env(default_task_config("push_cube"), 1, seed=0)
    try:
        env.reset()
        env.render(width=16, height=16, fovy=60)
    except RuntimeError as exc:
        if "offscreen rendering failed" in str(exc):
            pytest.skip(f"no OpenGL backend: {exc}")
        raise
    finally:
        env.close()


def test_record_rollouts_and_eval_video_in_a_run(tmp_path):
    _offscreen_gl_or_skip()
    run_train(
        [
            "env=push_cube",
            "env.num_envs=4",
            "env.num_eval_envs=2",
            "trainer.frames_per_batch=128",
            "trainer.total_frames=256",
            "trainer.eval_every=256",
            "trainer.eval_episodes=2",
            "env.max_episode_steps=20",
            "algorithm.num_epochs=1",
            "events=[record_rollouts,eval_video]",
            "events.eval.record_video.params.resolution=[160,120]",
            "events.eval.record_video.params.intrinsics=[150,150,80,60]",
        ],
        cwd=tmp_path,
    )
    run_dir = only_run_dir(tmp_path)
    files = sorted((run_dir / "rollouts").glob("*.npz"))
    assert [f.name for f in files] == ["step_000000128.npz", "step_000000256.npz"]
    data = np.load(files[0])
    assert data["observation"].shape[:2] == (4, 32) and data["action"].shape[:2] == (4, 32)
    assert data["reward"].shape == data["done"].shape == (4, 32) and int(data["global_step"]) == 128
    videos = list((run_dir / "videos").glob("main_cam_step_*.mp4"))
    assert len(videos) == 1
    import imageio.v2 as imageio

    frames = [f for f in imageio.get_reader(videos[0])]
    assert len(frames) >= 20 and frames[0].shape == (120, 160, 3) and frames[0].std() > 5
    rows = [json.loads(x) for x in (run_dir / "metrics.jsonl").read_text().splitlines()]
    assert any("rewards/reaching_reward" in r for r in rows)
