"""The users' JSON experiment format: mapping onto the typed config, round trip, older keys, bad files.

In-process (fast): the loader, Hydra composition through the ConfigStore, and ``json_entry.main`` up to
the point where it would hand over to Hydra. The command lines themselves run in test_json_cli.py.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import random
from pathlib import Path

import pytest
from omegaconf import OmegaConf, open_dict

from conftest import REPO, SHARED, compose
from rlexp.config.json_format import (
    escape_interpolations,
    flatten,
    load_json_experiment,
    to_json_experiment,
    write_json_experiment,
)
from rlexp.config.schema import RootConfig
from rlexp.config.validate import ConfigError, to_dict, to_root_config
from rlexp.envs.native import make_native_env
from rlexp.launch import json_entry
from rlexp.launch.json_entry import compose_json_experiment, prepare, split_config_arg

SEED = SHARED / "seed-configs"
TASKS = ("push_cube", "cart_pole")
EXAMPLES = REPO / "examples" / "json"


def seed_file(task: str, name: str = "train_config.json") -> Path:
    """One of our users' real files (../shared/seed-configs): the tests that check how rlexp reads
    them fail, not skip, where they are missing."""
    path = SEED / task / name
    if not path.is_file():
        pytest.fail(
            f"{path} is missing: these tests check rlexp against our users' real experiment files; "
            "put the shared seed configs at ../shared/seed-configs"
        )
    return path


def _load(task: str, folder: Path = EXAMPLES) -> tuple[dict, dict]:
    """The (train, task) pair of ``task`` from the project's examples (or ``folder``)."""
    return (
        json.loads((folder / task / "train_config.json").read_text()),
        json.loads((folder / task / "gym_config.json").read_text()),
    )


def _write(folder: Path, train: dict, gym: dict | None, raw_train: str | None = None) -> Path:
    """The pair in ``folder`` as the shared files lay them out (gym_config found by base name)."""
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "train_config.json"
    path.write_text(raw_train if raw_train is not None else json.dumps(train, indent=2))
    if gym is not None:
        (folder / "gym_config.json").write_text(json.dumps(gym, indent=2))
    return path


def _compose(path: Path, overrides: tuple[str, ...] = ()) -> RootConfig:
    return compose_json_experiment(load_json_experiment(path), overrides)


# ------------------------------------------------------------------------------ the shared files


def test_push_cube_file_maps_key_by_key(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    exp = load_json_experiment(seed_file("push_cube"))
    assert exp.gym_path == seed_file("push_cube", "gym_config.json").resolve()
    assert (
        "by base name" in exp.notes[0]
    )  # configs/agents/rl/... does not exist: the sibling file is used
    c = compose_json_experiment(exp)
    t, e, a, p = c.trainer, c.env, c.algorithm, c.policy
    assert (c.seed, t.exp_name, t.device) == (42, "push_cube_ppo", "cuda:0")
    assert (e.name, e.backend, e.native.task, e.num_envs, e.max_episode_steps) == (
        "push_cube",
        "native",
        "push_cube",
        64,
        100,
    )
    # total env steps = iterations x buffer_size x num_envs
    assert (t.iterations, t.frames_per_batch) == (1000, 1024 * 64)
    assert (t.eval_every, t.save_every, e.num_eval_envs, t.eval_episodes) == (100, 100, 16, 3 * 16)
    assert (a.lr, a.num_epochs, a.mini_batch_size, a.gamma, a.lmbda) == (1e-4, 10, 8192, 0.99, 0.95)
    assert (a.clip_epsilon, a.entropy_coeff, a.critic_coeff, a.max_grad_norm) == (
        0.2,
        0.01,
        0.5,
        0.5,
    )
    # what their PPO did: no reward scaling, a constant rate (rlexp's own defaults differ)
    assert (a.normalize_rewards, a.clip_rewards, a.anneal_lr) == (False, None, False)
    assert compose([]).algorithm.normalize_rewards is True
    assert (p.name, p.actor.hidden_sizes, p.actor.activation, p.critic.hidden_sizes) == (
        "actor_critic",
        [256, 256],
        "relu",
        [256, 256],
    )
    assert (c.logger.wandb.enabled, c.logger.wandb.project) == (True, "embodichain-push_cube")
    assert c.events.train == {}
    video = c.events.eval["record_camera"]
    assert (video.func, video.mode, video.interval_step) == ("record_video", "interval", 1)
    assert video.params["resolution"] == [640, 480] and video.params["intrinsics"] == [
        600,
        600,
        320,
        240,
    ]
    # the task file's terms, weights honoured
    n = e.native
    assert list(n.rewards) == [
        "reaching_reward",
        "goal_distance_reward",
        "action_penalty",
        "success_bonus",
    ]
    assert [r.weight for r in n.rewards.values()] == [0.03, 0.8, 0.01, 10.0]
    assert list(n.observations) == ["robot_qpos", "robot_ee_pos", "cube_pos", "goal_pos"] + [
        "cube_vel",  # conf/env/push_cube.yaml's critic group, kept beside the file's terms (#47)
        "cube_to_goal",
    ]
    assert {k: t.group for k, t in n.observations.items() if t.group != "policy"} == {
        "cube_vel": "critic",
        "cube_to_goal": "critic",
    }
    assert list(n.events) == ["randomize_cube", "randomize_goal"]
    assert n.actions["delta_qpos"].params == {"scale": 0.1} and n.extensions == {
        "success_threshold": 0.1
    }
    assert n.scene == {
        "init_qpos": [0.0, -1.57, 1.57, -1.57, -1.57, 0.0],  # the gripper's two values do not apply
        "cube_size": [0.1, 0.1, 0.1],
        "cube_init_pos": [-0.6, -0.4, 0.05],
        "cube_mass": 2.0,
        "cube_friction": [0.8],  # dynamic_friction
    }
    na = next(note for note in exp.notes if note.startswith("accepted but not applicable"))
    for key in (
        "trainer.headless",
        "trainer.gpu_id",
        "trainer.renderer",
        "max_episodes",
        "robot.urdf_cfg",
        "robot.drive_pros",
        "robot.solver_cfg",
        "robot.init_qpos[6:]",
        "rigid_object[0].attrs.restitution",
    ):
        assert key in na


def test_cart_pole_file_terms_add_to_the_task_terms():
    exp = load_json_experiment(seed_file("cart_pole"))
    c = compose_json_experiment(exp)
    t, e = c.trainer, c.env
    assert (e.name, e.num_envs, e.max_episode_steps, t.frames_per_batch, t.iterations) == (
        "cart_pole",
        64,
        500,
        65536,
        1000,
    )
    # enable_eval absent (false): no evaluation at all
    assert (t.eval_every, e.num_eval_envs) == (0, 0)
    assert c.logger.wandb.enabled is False
    # The task's own upright reward and start randomisation stay; the file's penalty comes on top.
    assert list(e.native.rewards) == ["upright", "velocity_penalty"]
    assert e.native.rewards["velocity_penalty"].weight == 0.005
    assert list(e.native.events) == ["randomize_start"]
    assert e.native.scene == {"init_qpos": [-0.2, 0.07]}
    assert any("kept beside the file's" in n and "rewards.upright" in n for n in exp.notes)


#: What the native task built from each file pair is (the same for the shared files and the
#: examples, which differ in the train file only): observation layout and size, action size, reward
#: terms in order, time limit, robot start pose, extensions.
BUILT = {
    "push_cube": {
        "layout": [
            "object/cube_pos", "object/goal_pos", "robot/ee_pos", "robot/qf", "robot/qpos",
            "robot/qvel", "privileged/cube_to_goal", "privileged/cube_vel",  # conf/env's critic
        ],
        "obs_dim": 59,
        "action_dim": 6,
        "rewards": ["reaching_reward", "goal_distance_reward", "action_penalty", "success_bonus"],
        "max_episode_steps": 100,
        "init_qpos": [0.0, -1.57, 1.57, -1.57, -1.57, 0.0],
        "extensions": {"success_threshold": 0.1, "cube_min_z": -0.1},
    },
    "cart_pole": {
        "layout": ["robot/qf", "robot/qpos", "robot/qvel"],
        "obs_dim": 6,
        "action_dim": 1,
        "rewards": ["upright", "velocity_penalty"],
        "max_episode_steps": 500,
        "init_qpos": [-0.2, 0.07],
        "extensions": {"pole_angle_limit": 0.4, "track_limit": 1.8},
    },
}  # fmt: skip


def _check_built(task: str, config: RootConfig) -> None:
    """Build the task of ``config`` with two envs and compare it with BUILT[task]."""
    want = BUILT[task]
    env = make_native_env(config.env.native, 2, config.seed, config.env.max_episode_steps)
    try:
        assert env.task_spec.name == task
        assert [name for name, *_ in env.observation_layout] == want["layout"]
        assert tuple(env.observation_spec["observation"].shape) == (2, want["obs_dim"])
        assert tuple(env.action_spec.shape) == (2, want["action_dim"])
        assert env.reward_names == want["rewards"]
        assert env.max_episode_steps == want["max_episode_steps"]
        assert env.robot_init_qpos.tolist() == want["init_qpos"]
        assert env.extensions == want["extensions"]
        if (
            task == "push_cube"
        ):  # the file's rigid_object[0]: size 0.1 (half-size 0.05), mass 2, friction 0.8
            assert env.model.body("cube").mass.tolist() == [2.0]
            assert env.model.geom("cube").size.tolist() == pytest.approx([0.05] * 3)
            assert env.model.geom("cube").friction[0] == pytest.approx(0.8)
    finally:
        env.close()


@pytest.mark.parametrize("task", TASKS)
def test_shared_file_prepares_and_builds(task, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    exp = prepare(seed_file(task))  # loads, composes, builds the task with one env
    assert exp.env_group == task
    _check_built(task, compose_json_experiment(exp))


def test_command_line_overrides_win_over_the_file():
    path = EXAMPLES / "push_cube" / "train_config.json"
    c = _compose(
        path,
        (
            "seed=7",
            "trainer.iterations=2",
            "algorithm.lr=0.5",
            "env.native.rewards.success_bonus.weight=3",
        ),
    )
    assert (c.seed, c.trainer.iterations, c.algorithm.lr) == (7, 2, 0.5)
    assert c.env.native.rewards["success_bonus"].weight == 3.0
    assert c.trainer.frames_per_batch == 64 * 32  # untouched keys keep the file's values


# ---------------------------------------------------------------------------------- round trip


def _roundtrip(config: RootConfig, folder: Path) -> RootConfig:
    folder.mkdir()
    write_json_experiment(config, folder)
    assert (folder / "train_config.json").is_file() and (folder / "gym_config.json").is_file()
    return _compose(folder / "train_config.json")


@pytest.mark.parametrize("source", ["examples", "shared"])
@pytest.mark.parametrize("task", TASKS)
def test_round_trip_of_the_shared_files(task, source, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    path = EXAMPLES / task / "train_config.json" if source == "examples" else seed_file(task)
    config = _compose(path)
    again = _roundtrip(config, tmp_path / "run")
    assert again == config
    train = json.loads((tmp_path / "run" / "train_config.json").read_text())
    assert train["trainer"]["gym_config"] == "gym_config.json"
    assert set(train) == {
        "trainer",
        "policy",
        "algorithm",
        "rlexp",
    }  # rlexp: the keys the format lacks
    assert train["trainer"]["events"]["eval"]["record_camera"]["func"] == "record_camera_data_async"


@pytest.mark.parametrize(
    "overrides",
    [
        [],  # HalfCheetah-v5, total_frames instead of iterations
        [
            "env=inverted_pendulum",
            "trainer.eval_episodes=3",
            "env.num_eval_envs=2",
            "trainer.eval_every=0",
        ],
        [
            "env=push_cube",
            "logger=[tensorboard,wandb]",
            "trainer.iterations=3",
            "+env.native.scene.cube_mass=1.5",
        ],
        ["env=cart_pole", "env.num_eval_envs=0", "policy=mlp_256", "algorithm.anneal_lr=true"],
        ["env.name=Pusher-v5", "env.max_episode_steps=50"],  # a Gymnasium id no env YAML has
    ],
)
def test_round_trip_of_yaml_configs(overrides, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    config = to_root_config(compose(overrides))
    again = _roundtrip(config, tmp_path / "run")
    a, b = flatten(to_dict(config), RootConfig), flatten(to_dict(again), RootConfig)
    assert {k: (a.get(k), b.get(k)) for k in a.keys() | b.keys() if a.get(k) != b.get(k)} == {}
    assert again == config


def test_to_json_writes_the_format_keys():
    config = to_root_config(
        compose(
            [
                "env=push_cube",
                "trainer.iterations=4",
                "env.num_envs=8",
                "trainer.frames_per_batch=256",
                "env.num_eval_envs=4",
                "trainer.eval_episodes=8",
            ]
        )
    )
    train, gym = to_json_experiment(config)
    t = train["trainer"]
    assert (t["num_envs"], t["buffer_size"], t["iterations"]) == (8, 32, 4)
    assert (t["enable_eval"], t["num_eval_envs"], t["num_eval_episodes"]) == (True, 4, 2)
    assert train["algorithm"]["cfg"]["batch_size"] == config.algorithm.mini_batch_size
    assert gym["id"] == "PushCubeRL" and set(gym["env"]) == {
        "events",
        "observations",
        "rewards",
        "actions",
        "extensions",
    }


# --------------------------------------------------------------------------- strings are data

#: An environment variable the files below try to read through OmegaConf interpolations.
SECRET_VAR, SECRET = "RLEXP_TEST_SECRET", "s3cr3t-9f3c1e"
ENV = "${oc.env:" + SECRET_VAR + "}"


def _file_with_interpolations(folder: Path, names: bool) -> Path:
    """The cart_pole example with OmegaConf interpolations in string values everywhere: train file,
    task file, nested params, lists, the rlexp section; with and without backslashes before them.
    ``names``: in the names validate() restricts (exp_name, W&B project, video name) too."""
    train, gym = _load("cart_pole")
    t = train["trainer"]
    params = t["events"]["eval"]["record_camera"]["params"]
    params["save_path"] = "\\" + ENV + "/\\\\${trainer.seed}"
    if names:
        t["exp_name"] = ENV
        t["wandb_project_name"] = "${seed}"
        params["name"] = "cam-" + ENV + "-${oc.env:RLEXP_TEST_UNSET,x}"
    gym["env"]["extensions"]["note"] = {"deep": [ENV, "${now:%Y}"]}
    gym["env"]["events"]["randomize_start"]["params"]["tag"] = ENV
    train["rlexp"] = {"logger": {"wandb": {"entity": ENV, "tags": ["${oc.env:HOME}"]}}}
    return _write(folder, train, gym)


def test_strings_in_the_files_are_never_resolved(tmp_path, monkeypatch):
    monkeypatch.setenv(SECRET_VAR, SECRET)
    monkeypatch.chdir(tmp_path)
    c = _compose(_file_with_interpolations(tmp_path / "files", names=False))
    assert c.logger.wandb.entity == ENV
    assert c.logger.wandb.tags == ["${oc.env:HOME}"]
    assert c.events.eval["record_camera"].params["save_path"] == (
        "\\" + ENV + "/\\\\${trainer.seed}"
    )
    n = c.env.native
    assert n.extensions["note"] == {"deep": [ENV, "${now:%Y}"]}
    assert n.events["randomize_start"].params["tag"] == ENV
    # rlexp's own interpolations still work: exp_name is conf/trainer/default.yaml's ${env.name}_ppo
    # (the file's exp_name is data: see the next test); the task YAML's terms are merged in
    assert c.trainer.exp_name == "cart_pole_ppo"
    assert list(n.rewards) == ["upright", "velocity_penalty"]
    assert SECRET not in json.dumps(dataclasses.asdict(c))
    # written back and loaded again: the same literal strings
    train, gym = to_json_experiment(c)
    assert SECRET not in json.dumps([train, gym])
    assert gym["env"]["extensions"]["note"] == {"deep": [ENV, "${now:%Y}"]}
    assert _roundtrip(c, tmp_path / "run") == c


def test_the_nodes_hydra_composes_hold_the_files_strings(tmp_path, monkeypatch):
    """Every string, the names included (exp_name names files: a "${...}" in it must not become a
    path; validate() then refuses its characters, so the node is read here before validation), and
    the notes each run logs, which quote the files' paths."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    monkeypatch.setenv(SECRET_VAR, SECRET)
    monkeypatch.chdir(tmp_path)
    folder = tmp_path / ENV
    exp = load_json_experiment(_file_with_interpolations(folder, names=True))
    json_entry.register_json_experiment(exp)
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
            cfg = hydra_compose(
                config_name="config",
                overrides=[f"+experiment={json_entry.EXPERIMENT}"],
                return_hydra_config=True,
            )
    finally:
        GlobalHydra.instance().clear()
    with open_dict(cfg):
        callbacks = cfg.pop("hydra").callbacks  # the rest of hydra resolves only in a job
    notes = OmegaConf.to_container(callbacks, resolve=True)["rlexp_json_notes"]["notes"]
    assert str(folder / "train_config.json") in notes[0]
    plain = OmegaConf.to_container(cfg, resolve=True)
    assert plain["trainer"]["exp_name"] == ENV
    assert plain["logger"]["wandb"]["project"] == "${seed}"
    assert plain["logger"]["wandb"]["entity"] == ENV
    params = plain["events"]["eval"]["record_camera"]["params"]
    assert params["name"] == "cam-" + ENV + "-${oc.env:RLEXP_TEST_UNSET,x}"
    assert params["save_path"] == "\\" + ENV + "/\\\\${trainer.seed}"
    assert plain["env"]["native"]["extensions"]["note"] == {"deep": [ENV, "${now:%Y}"]}
    assert SECRET not in json.dumps([notes, plain])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_escape_interpolations_gives_back_every_string(seed):
    """Random strings of $ { } \\ and letters: OmegaConf reads each escaped string back unchanged."""
    rng = random.Random(seed)
    strings = [
        "".join(rng.choice("${}\\\\a:.") for _ in range(rng.randint(0, 12))) for _ in range(400)
    ]
    strings += ["${", "\\${x}", "\\\\${x}", "${a${b}}", "$${x}", "x\\", "\\\\\\${oc.env:HOME}\\"]
    node = OmegaConf.create({"v": escape_interpolations(strings)})
    assert list(node.v) == strings


def test_an_escaped_string_in_a_number_field_of_the_rlexp_section(tmp_path):
    train, gym = _load("cart_pole")
    train["rlexp"] = {"trainer": {"log_every": "${oc.env:RLEXP_TEST_LOG_EVERY}"}}
    with pytest.raises(ConfigError) as info:
        load_json_experiment(_write(tmp_path / "files", train, gym))
    msg = str(info.value)
    assert "rlexp.trainer.log_every" in msg and "${oc.env:RLEXP_TEST_LOG_EVERY}" in msg
    assert "\\$" not in msg and len(msg.splitlines()) == 1


# ---------------------------------------------------------------------------- the logger choice


@pytest.mark.parametrize(
    ("overrides", "sinks"),
    [
        ((), (True, True)),  # the format's TensorBoard, plus W&B for use_wandb
        (("logger=none",), (False, False)),
        (("logger=wandb",), (False, True)),
        (("logger=[tensorboard,wandb]",), (True, True)),
        (("logger.wandb.enabled=false",), (True, False)),
    ],
)
def test_logger_on_the_command_line_wins_over_use_wandb(overrides, sinks, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    train, gym = _load("cart_pole")
    train["trainer"]["use_wandb"] = True
    c = _compose(_write(tmp_path / "files", train, gym), overrides)
    assert (c.logger.tensorboard.enabled, c.logger.wandb.enabled) == sinks
    assert c.logger.wandb.project == "embodichain-cart_pole"  # the file's setting stays


def test_logger_none_wins_over_the_rlexp_section(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    config = to_root_config(compose(["env=cart_pole", "logger=[tensorboard,wandb]"]))
    write_json_experiment(config, tmp_path / ".")
    path = tmp_path / "train_config.json"
    assert json.loads(path.read_text())["trainer"]["use_wandb"] is True
    assert _compose(path).logger == config.logger
    c = _compose(path, ("logger=none",))
    assert (c.logger.tensorboard.enabled, c.logger.wandb.enabled, c.logger.jsonl) == (
        False,
        False,
        True,
    )


# ----------------------------------------------------------------------------------- older files


def test_older_keys(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    train, gym = _load("push_cube")
    t = train["trainer"]
    t["rollout_steps"] = t.pop("buffer_size")  # older name
    t["enable_rt"] = True  # instead of renderer
    del t["renderer"], t["num_envs"]
    gym["env"]["num_envs"] = 12  # num_envs only in the task file's env
    exp = load_json_experiment(_write(tmp_path / "old", train, gym))
    c = compose_json_experiment(exp)
    assert (c.env.num_envs, c.trainer.frames_per_batch) == (12, 64 * 12)
    assert any("rollout_steps" in n for n in exp.notes)
    assert any("trainer.enable_rt" in n for n in exp.notes if n.startswith("accepted"))

    del gym["env"]["num_envs"]
    gym["num_envs"] = 8  # top level of the task file
    c = _compose(_write(tmp_path / "old2", train, gym))
    assert (c.env.num_envs, c.trainer.frames_per_batch) == (8, 64 * 8)


def test_task_file_relative_to_the_working_dir_comes_first(tmp_path, monkeypatch):
    train, gym = _load("cart_pole")
    (tmp_path / "configs").mkdir()
    (tmp_path / "configs" / "task.json").write_text(json.dumps({**gym, "max_episode_steps": 77}))
    train["trainer"]["gym_config"] = "configs/task.json"
    path = _write(tmp_path / "elsewhere", train, None)
    monkeypatch.chdir(tmp_path)
    exp = load_json_experiment(path)
    assert exp.gym_path == tmp_path / "configs" / "task.json" and "working dir" in exp.notes[0]
    assert compose_json_experiment(exp).env.max_episode_steps == 77


@pytest.mark.parametrize("task", TASKS)
def test_examples_load_and_build(task, monkeypatch):
    monkeypatch.chdir(REPO)
    exp = load_json_experiment(EXAMPLES / task / "train_config.json")
    assert exp.gym_path == (EXAMPLES / task / "gym_config.json").resolve()
    assert "working dir" in exp.notes[0]
    c = compose_json_experiment(exp)
    assert (c.trainer.device, c.env.num_envs, c.env.native.task) == ("cpu", 32, task)
    json_entry.check_task_builds(exp, c)
    _check_built(task, c)


def test_the_experiment_override_joins_the_other_overrides():
    ins = json_entry.insert_override
    assert ins([], "+e=x") == ["+e=x"]
    assert ins(["seed=1", "--cfg", "job"], "+e=x") == ["+e=x", "seed=1", "--cfg", "job"]
    assert ins(["--cfg", "job", "seed=1"], "+e=x") == ["--cfg", "job", "+e=x", "seed=1"]
    assert ins(["-m", "seed=0,1"], "+e=x") == ["-m", "+e=x", "seed=0,1"]
    assert ins(["--info", "defaults"], "+e=x") == ["--info", "defaults", "+e=x"]
    assert ins(["--cfg=job", "a=1"], "+e=x") == ["--cfg=job", "+e=x", "a=1"]


def test_split_config_arg():
    assert split_config_arg(["--config-json", "a.json", "seed=1"]) == ("a.json", ["seed=1"])
    assert split_config_arg(["-m", "--config=a.json", "seed=0,1"]) == ("a.json", ["-m", "seed=0,1"])
    assert split_config_arg(["--config-name", "x", "seed=1"]) == (
        None,
        ["--config-name", "x", "seed=1"],
    )
    with pytest.raises(ConfigError, match="needs a file"):
        split_config_arg(["--config-json"])
    with pytest.raises(ConfigError, match="one JSON experiment file"):
        split_config_arg(["--config", "a.json", "--config-json", "b.json"])


# -------------------------------------------------------------------------------------- bad files


def _set(d: dict, dotted: str, value) -> None:
    *parents, last = dotted.split(".")
    for p in parents:
        d = d[int(p)] if isinstance(d, list) else d[p]
    d[last] = value


def _del(d: dict, dotted: str) -> None:
    *parents, last = dotted.split(".")
    for p in parents:
        d = d[p]
    del d[last]


#: (id, which file, change, what the one-line message must contain)
BROKEN = [
    ("malformed-train", "raw", '{"trainer": {"seed": 1,}}', "invalid JSON at line 1, column 24"),
    (
        "malformed-train-multiline",
        "raw",
        '{\n  "trainer": {\n    "seed": 1\n  \n',
        "invalid JSON at line",
    ),
    ("duplicate-key", "raw", '{"trainer": {"seed": 1, "seed": 2}}', "duplicate key 'seed'"),
    ("nan", "raw", '{"trainer": {"seed": NaN}}', "NaN"),
    ("not-an-object", "raw", "[1, 2]", "must hold a JSON object"),
    (
        "unknown-section",
        "train",
        ("set", "trainr", {}),
        "unknown key 'trainr'; did you mean 'trainer'?",
    ),
    (
        "unknown-trainer-key",
        "train",
        ("set", "trainer.eval_frq", 5),
        "unknown key 'trainer.eval_frq'; did you mean 'trainer.eval_freq'?",
    ),
    (
        "iterations-type",
        "train",
        ("set", "trainer.iterations", "ten"),
        "trainer.iterations='ten' must be an integer",
    ),
    (
        "iterations-float",
        "train",
        ("set", "trainer.iterations", 2.5),
        "trainer.iterations=2.5 must be an integer",
    ),
    (
        "iterations-range",
        "train",
        ("set", "trainer.iterations", 0),
        "trainer.iterations=0 is out of range",
    ),
    (
        "num-envs-range",
        "train",
        ("set", "trainer.num_envs", -4),
        "trainer.num_envs=-4 is out of range",
    ),
    ("seed-bool", "train", ("set", "trainer.seed", True), "trainer.seed=true must be an integer"),
    ("device", "train", ("set", "trainer.device", "gpu"), "trainer.device='gpu'"),
    (
        "enable-eval-type",
        "train",
        ("set", "trainer.enable_eval", "yes"),
        "trainer.enable_eval='yes' must be true or false",
    ),
    (
        "eval-freq-negative",
        "train",
        ("set", "trainer.eval_freq", -100),
        "trainer.eval_freq=-100 is out of range",
    ),
    ("no-gym-config", "train", ("del", "trainer.gym_config"), "trainer.gym_config is required"),
    (
        "missing-task-file",
        "train",
        ("set", "trainer.gym_config", "nowhere/task.json"),
        "task file not found; tried",
    ),
    (
        "buffer-and-rollout",
        "train",
        ("set", "trainer.rollout_steps", 16),
        "rollout_steps is the older name",
    ),
    (
        "policy-actor-only",
        "train",
        ("set", "policy.name", "actor_only"),
        "algorithm.name='ppo' needs a critic, but policy.name='actor_only' has none",
    ),
    (
        "policy-unknown",
        "train",
        ("set", "policy.name", "actor_critc"),
        "choose from ['actor_critic', 'actor_only']; did you mean 'actor_critic'?",
    ),
    (
        "activation",
        "train",
        ("set", "policy.actor.network_cfg.activation", "sigmoid"),
        "policy.actor.network_cfg.activation='sigmoid': choose from",
    ),
    (
        "hidden-sizes",
        "train",
        ("set", "policy.critic.network_cfg.hidden_sizes", [256, "x"]),
        "policy.critic.network_cfg.hidden_sizes[1]",
    ),
    (
        "net-type",
        "train",
        ("set", "policy.actor.type", "cnn"),
        "policy.actor.type='cnn': choose from ['mlp']",
    ),
    (
        "algorithm-grpo",
        "train",
        ("set", "algorithm.name", "grpo"),
        "unknown key 'algorithm.cfg.vf_coef'",  # GRPO has no critic: PPO's vf_coef is not its key
    ),
    (
        "algorithm-unknown",
        "train",
        ("set", "algorithm.name", "sac"),
        "algorithm.name='sac': choose from ['ppo', 'grpo']",
    ),
    (
        "algorithm-key",
        "train",
        ("set", "algorithm.cfg.learning_rat", 0.1),
        "did you mean 'algorithm.cfg.learning_rate'?",
    ),
    (
        "grpo-key-in-ppo",
        "train",
        ("set", "algorithm.cfg.kl_coef", 0.02),
        "unknown key 'algorithm.cfg.kl_coef'",
    ),
    (
        "gamma-range",
        "train",
        ("set", "algorithm.cfg.gamma", 1.5),
        "algorithm.cfg.gamma=1.5 is out of range: must be in [0, 1]",
    ),
    (
        "lr-range",
        "train",
        # 0 is allowed: a baseline that does not learn
        ("set", "algorithm.cfg.learning_rate", -0.001),
        "algorithm.cfg.learning_rate=-0.001 is out of range: must be >= 0",
    ),
    (
        "batch-too-big",
        "train",
        ("set", "algorithm.cfg.batch_size", 10**7),
        "algorithm.cfg.batch_size=10000000 is larger than a rollout",
    ),
    (
        "event-func",
        "train",
        ("set", "trainer.events.eval.record_camera.func", "record_camera_data"),
        "did you mean 'record_camera_data_async'?",
    ),
    (
        "event-mode",
        "train",
        ("set", "trainer.events.eval.record_camera.mode", "sometimes"),
        "trainer.events.eval.record_camera.mode='sometimes': choose from",
    ),
    (
        "event-phase",
        "train",
        ("set", "trainer.events.test", {}),
        "unknown key 'trainer.events.test'",
    ),
    (
        "video-resolution",
        "train",
        ("set", "trainer.events.eval.record_camera.params.resolution", [640]),
        "params.resolution=[640] must have 2 values",
    ),
    (
        "video-param",
        "train",
        ("set", "trainer.events.eval.record_camera.params.fov", 60),
        "unknown key 'trainer.events.eval.record_camera.params.fov'",
    ),
    (
        "rlexp-section",
        "train",
        ("set", "rlexp", {"trainer": {"log_evry": 2}}),
        "rlexp.trainer.log_evry",
    ),
    (
        "rlexp-event-func",
        "train",
        ("set", "rlexp", {"events": {"train": {"noise": {"func": "no_such_event"}}}}),
        "events.train.noise.func='no_such_event' is not a known event function",
    ),
    (
        "rlexp-event-import",
        "train",
        ("set", "rlexp", {"events": {"eval": {"shell": {"func": "os.system"}}}}),
        "events.eval.shell.func='os.system': dotted paths must be inside",
    ),
    (
        "malformed-gym",
        "gym-raw",
        '{"id": "PushCubeRL",\n "env": {]}',
        "invalid JSON at line 2, column",
    ),
    ("task-id", "gym", ("set", "id", "PushCube"), "id='PushCube' is not a known task; choose from"),
    (
        "gym-unknown-key",
        "gym",
        ("set", "robots", {}),
        "unknown key 'robots'; did you mean 'robot'?",
    ),
    (
        "gym-env-key",
        "gym",
        ("set", "env.reward", {}),
        "unknown key 'env.reward'; did you mean 'env.rewards'?",
    ),
    (
        "reward-func",
        "gym",
        ("set", "env.rewards.goal_distance_reward.func", "distance_to_targt"),
        "did you mean 'distance_to_target'?",
    ),
    (
        "reward-weight",
        "gym",
        ("set", "env.rewards.success_bonus.weight", "high"),
        "env.rewards.success_bonus.weight='high' must be a number",
    ),
    (
        "reward-mode",
        "gym",
        ("set", "env.rewards.success_bonus.mode", "multiply"),
        "env.rewards.success_bonus.mode='multiply': choose from ['add', 'replace']",
    ),
    (
        "observation-name",
        "gym",
        ("set", "env.observations.cube_pos.name", "cube_pos"),
        "env.observations.cube_pos.name='cube_pos' must be 'group/key'",
    ),
    (
        "event-term-func",
        "gym",
        ("set", "env.events.randomize_cube.func", "randomise_rigid_object_pose"),
        "did you mean 'randomize_rigid_object_pose'?",
    ),
    (
        "action-func",
        "gym",
        ("set", "env.actions.delta_qpos.func", "DeltaQpos"),
        "env.actions.delta_qpos.func='DeltaQpos'",
    ),
    (
        "term-key",
        "gym",
        ("set", "env.rewards.success_bonus.wieght", 2),
        "did you mean 'env.rewards.success_bonus.weight'?",
    ),
    (
        "max-episode-steps",
        "gym",
        ("set", "max_episode_steps", 0),
        "max_episode_steps=0 is out of range",
    ),
    ("init-qpos-short", "gym", ("set", "robot.init_qpos", [0.0]), "robot.init_qpos has 1 values"),
    (
        "cube-mass",
        "gym",
        ("set", "rigid_object.0.attrs.mass", -2.0),
        "rigid_object[0].attrs.mass=-2.0 is out of range",
    ),
    (
        "term-param",
        "gym",
        ("set", "env.actions.delta_qpos.params", {"scal": 0.1}),
        "unknown parameter(s) ['scal']",
    ),
    (
        "action-dim",
        "train",
        ("set", "policy.action_dim", 7),
        "policy.action_dim=7 but the push_cube task's actions have 6",
    ),
]


def _broken_files(tmp_path: Path, kind: str, change) -> Path:
    train, gym = _load("push_cube")
    folder = tmp_path / "files"
    if kind == "raw":
        return _write(folder, train, gym, raw_train=change)
    if kind == "gym-raw":
        path = _write(folder, train, gym)
        (folder / "gym_config.json").write_text(change)
        return path
    target = train if kind == "train" else gym
    target = copy.deepcopy(target)
    if change[0] == "set":
        _set(target, change[1], change[2])
    else:
        _del(target, change[1])
    return _write(folder, target if kind == "train" else train, target if kind == "gym" else gym)


@pytest.mark.parametrize(
    ("kind", "change", "expected"), [b[1:] for b in BROKEN], ids=[b[0] for b in BROKEN]
)
def test_broken_file_exits_2_with_one_line(kind, change, expected, tmp_path, monkeypatch, capsys):
    path = _broken_files(tmp_path, kind, change)
    cwd = tmp_path / "cwd"
    cwd.mkdir()
    monkeypatch.chdir(cwd)
    monkeypatch.setattr("sys.argv", ["train.py"])
    with pytest.raises(SystemExit) as exit_info:
        json_entry.main(["--config-json", str(path), "trainer.iterations=1"])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("config error: "), err
    assert expected in lines[0], lines[0]
    assert "Traceback" not in err
    assert list(cwd.iterdir()) == [], "a run dir (or anything else) was created"


def test_missing_train_file(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exit_info:
        json_entry.main(["--config", "nope.json"])
    assert exit_info.value.code == 2
    assert capsys.readouterr().err.strip() == "config error: nope.json: no such file"
