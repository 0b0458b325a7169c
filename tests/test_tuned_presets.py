"""The per-task presets and their suites: rl-baselines3-zoo's (``+experiment=rl_zoo``,
conf/rl_zoo/<env>.yaml, ``+sweep=rl_zoo_1m``), where every task composes to the values of the
``hyperparams/ppo.yml`` entry it cites (literals copied from that file here, not read from the
presets), and the tuned ones (``+experiment=tuned``, conf/tuned/<env>.yaml, ``+sweep=tuned_1m``),
the best measured per task: rl-zoo's values, rlexp's defaults (Hopper) or Ant's own
(literals below). The values reach the built objects, an env without a preset is one line and exit
2, and each suite expands to 9 tasks x 5 seeds into one fixed sweep dir. docs/results.md, "Tuned
presets"."""

from __future__ import annotations

import dataclasses
import json
import math

import pytest
import torch
from omegaconf import OmegaConf

from conftest import CONF_DIR, REPO, compose, run_train
from rlexp.config.schema import RootConfig
from rlexp.config.validate import ConfigError, to_dict, to_root_config

#: The Gymnasium MuJoCo tasks of conf/env/: each has a tuned preset.
MUJOCO = [
    "half_cheetah",
    "hopper",
    "walker2d",
    "ant",
    "humanoid",
    "swimmer",
    "reacher",
    "inverted_pendulum",
    "inverted_double_pendulum",
]
#: The classic-control presets: env option -> the experiment preset whose values it shares.
CLASSIC = {
    "acrobot": "acrobot_ppo",
    "gym_cartpole": "cartpole_ppo",
    "pendulum": "pendulum_ppo",
    "lunar_lander": "lunar_lander_ppo",
    "cart_pole": "cart_pole_ppo",
}

#: rl-baselines3-zoo hyperparams/ppo.yml (commit eec15dc22e1e), per task, in rlexp's keys:
#: n_steps x n_envs -> frames_per_batch, batch_size -> mini_batch_size, n_epochs -> num_epochs,
#: gae_lambda -> lmbda, learning_rate -> lr (constant: anneal_lr false), clip_range ->
#: clip_epsilon, ent_coef -> entropy_coeff, vf_coef -> critic_coeff; policy_kwargs log_std_init ->
#: init_log_std, ortho_init, activation_fn, net_arch. SB3's defaults where the entry sets nothing.
SB3_POLICY = {"init_log_std": 0.0, "ortho_init": True, "sizes": [64, 64], "activation": "tanh"}
TUNED_POLICY = {
    "init_log_std": -2.0,
    "ortho_init": False,
    "sizes": [256, 256],
    "activation": "relu",
}
ZOO = {
    "half_cheetah": {  # HalfCheetah-v4
        "num_envs": 1, "frames_per_batch": 512, "mini_batch_size": 64, "num_epochs": 20,
        "gamma": 0.98, "lmbda": 0.92, "lr": 2.0633e-05, "clip_epsilon": 0.1,
        "entropy_coeff": 0.000401762, "critic_coeff": 0.58096, "max_grad_norm": 0.8,
        **TUNED_POLICY,
    },
    "hopper": {  # Hopper-v4
        "num_envs": 1, "frames_per_batch": 512, "mini_batch_size": 32, "num_epochs": 5,
        "gamma": 0.999, "lmbda": 0.99, "lr": 9.80828e-05, "clip_epsilon": 0.2,
        "entropy_coeff": 0.00229519, "critic_coeff": 0.835671, "max_grad_norm": 0.7,
        **TUNED_POLICY,
    },
    "walker2d": {  # Walker2d-v4 (no policy_kwargs)
        "num_envs": 1, "frames_per_batch": 512, "mini_batch_size": 32, "num_epochs": 20,
        "gamma": 0.99, "lmbda": 0.95, "lr": 5.05041e-05, "clip_epsilon": 0.1,
        "entropy_coeff": 0.000585045, "critic_coeff": 0.871923, "max_grad_norm": 1.0,
        **SB3_POLICY,
    },
    "ant": {  # Ant-v4: normalize true and SB3's PPO defaults
        "num_envs": 1, "frames_per_batch": 2048, "mini_batch_size": 64, "num_epochs": 10,
        "gamma": 0.99, "lmbda": 0.95, "lr": 3e-4, "clip_epsilon": 0.2,
        "entropy_coeff": 0.0, "critic_coeff": 0.5, "max_grad_norm": 0.5,
        **SB3_POLICY,
    },
    "humanoid": {  # Humanoid-v4
        "num_envs": 1, "frames_per_batch": 512, "mini_batch_size": 256, "num_epochs": 5,
        "gamma": 0.95, "lmbda": 0.9, "lr": 3.56987e-05, "clip_epsilon": 0.3,
        "entropy_coeff": 0.00238306, "critic_coeff": 0.431892, "max_grad_norm": 2.0,
        **TUNED_POLICY,
    },
    "swimmer": {  # Swimmer-v4: n_envs 4 x n_steps 1024
        "num_envs": 4, "frames_per_batch": 4096, "mini_batch_size": 256, "num_epochs": 10,
        "gamma": 0.9999, "lmbda": 0.98, "lr": 6e-4, "clip_epsilon": 0.2,
        "entropy_coeff": 0.0, "critic_coeff": 0.5, "max_grad_norm": 0.5,
        **SB3_POLICY,
    },
    "reacher": {  # Reacher-v2
        "num_envs": 1, "frames_per_batch": 512, "mini_batch_size": 32, "num_epochs": 5,
        "gamma": 0.9, "lmbda": 1.0, "lr": 0.000104019, "clip_epsilon": 0.3,
        "entropy_coeff": 7.52585e-08, "critic_coeff": 0.950368, "max_grad_norm": 0.9,
        **SB3_POLICY,
    },
    "inverted_pendulum": {  # InvertedPendulum-v2: batch_size 64 over a 32-step rollout -> 32
        "num_envs": 1, "frames_per_batch": 32, "mini_batch_size": 32, "num_epochs": 5,
        "gamma": 0.999, "lmbda": 0.9, "lr": 0.000222425, "clip_epsilon": 0.4,
        "entropy_coeff": 1.37976e-07, "critic_coeff": 0.19816, "max_grad_norm": 0.3,
        **SB3_POLICY,
    },
    "inverted_double_pendulum": {  # InvertedDoublePendulum-v2: batch_size 512 over 128 -> 128
        "num_envs": 1, "frames_per_batch": 128, "mini_batch_size": 128, "num_epochs": 10,
        "gamma": 0.98, "lmbda": 0.8, "lr": 0.000155454, "clip_epsilon": 0.4,
        "entropy_coeff": 1.05057e-06, "critic_coeff": 0.695929, "max_grad_norm": 0.5,
        **SB3_POLICY,
    },
}  # fmt: skip


#: rlexp's defaults (conf/algorithm/ppo.yaml, conf/policy/mlp.yaml, conf/trainer/default.yaml) in
#: the keys of ``ZOO``, with the learning rate annealed: the tuned preset of Hopper.
DEFAULTS = {
    "num_envs": 1, "frames_per_batch": 2048, "mini_batch_size": 64, "num_epochs": 10,
    "gamma": 0.99, "lmbda": 0.95, "lr": 3e-4, "clip_epsilon": 0.2,
    "entropy_coeff": 0.0, "critic_coeff": 0.5, "max_grad_norm": 0.5,
    **SB3_POLICY,
}  # fmt: skip
#: Ant's initial log-std (Tianshou's PPO value; -1.0 did less well on the same seed, results.md).
ANT_LOG_STD = -0.5
#: Ant's tuned preset: the defaults with a smaller initial log-std and Ant-v4's observation (no
#: contact forces), measured in docs/results.md.
ANT = {**DEFAULTS, "init_log_std": ANT_LOG_STD}
#: The tuned preset per task: rl-zoo's values where they measured best here, else rlexp's own.
TUNED = {
    **ZOO,
    "hopper": DEFAULTS,
    "ant": ANT,
}
#: The tasks whose tuned preset is rl-zoo's values unchanged (conf/tuned/<env>.yaml includes
#: conf/rl_zoo/<env>.yaml).
AS_ZOO = [e for e in MUJOCO if e not in ("hopper", "ant")]


def tuned(env: str, *extra: str) -> RootConfig:
    """``python train.py env=<env> +experiment=tuned [extra]`` as a typed config."""
    return to_root_config(compose([f"env={env}", "+experiment=tuned", *extra]))


def rl_zoo(env: str, *extra: str) -> RootConfig:
    """``python train.py env=<env> +experiment=rl_zoo [extra]`` as a typed config."""
    return to_root_config(compose([f"env={env}", "+experiment=rl_zoo", *extra]))


def as_zoo(config: RootConfig) -> dict:
    """The composed config in the keys of ``ZOO``."""
    a, p = config.algorithm, config.policy
    return {
        "num_envs": config.env.num_envs,
        "frames_per_batch": config.trainer.frames_per_batch,
        **{k: getattr(a, k) for k in ("mini_batch_size", "num_epochs", "gamma", "lmbda", "lr")},
        **{k: getattr(a, k) for k in ("clip_epsilon", "entropy_coeff", "critic_coeff")},
        "max_grad_norm": a.max_grad_norm,
        "init_log_std": p.init_log_std,
        "ortho_init": p.ortho_init,
        "sizes": p.actor.hidden_sizes,
        "activation": p.actor.activation,
    }


def test_every_mujoco_task_and_classic_preset_has_a_tuned_file():
    envs = {p.stem: p.read_text() for p in (CONF_DIR / "env").glob("*.yaml")}
    mujoco = {e for e, text in envs.items() if "Gymnasium MuJoCo" in text}
    assert mujoco == set(MUJOCO)  # every MuJoCo task of conf/env/ is in the suite
    presets = {p.stem for p in (CONF_DIR / "tuned").glob("*.yaml")} - {"none"}
    assert presets == set(MUJOCO) | set(CLASSIC)
    zoo = {p.stem for p in (CONF_DIR / "rl_zoo").glob("*.yaml")} - {"none"}
    assert zoo == set(MUJOCO)


@pytest.mark.parametrize("env", MUJOCO)
def test_each_task_composes_to_rl_zoos_values(env):
    config = rl_zoo(env)
    assert as_zoo(config) == ZOO[env]
    # the same in every preset: VecNormalize (normalize: true), a constant learning rate, 1M steps
    assert config.env.normalize_observations and config.env.clip_observations == 10.0
    assert config.algorithm.normalize_rewards and config.algorithm.clip_rewards == 10.0
    assert config.algorithm.anneal_lr is False
    assert config.trainer.total_frames == 1_000_000
    assert config.policy.critic.hidden_sizes == ZOO[env]["sizes"]
    assert config.policy.critic.activation == ZOO[env]["activation"]
    # frames_per_batch a multiple of the minibatch (rlexp and SB3 then split rollouts alike)
    assert config.trainer.frames_per_batch % config.algorithm.mini_batch_size == 0
    assert config.env.kwargs == {}  # the env as conf/env/ has it


@pytest.mark.parametrize("env", MUJOCO)
def test_each_task_composes_to_its_tuned_values(env):
    config = tuned(env)
    assert as_zoo(config) == TUNED[env]
    assert config.env.normalize_observations and config.algorithm.normalize_rewards
    assert config.algorithm.clip_rewards == 10.0 and config.trainer.total_frames == 1_000_000
    assert config.policy.critic.hidden_sizes == TUNED[env]["sizes"]
    assert config.policy.critic.activation == TUNED[env]["activation"]
    # rl-zoo's constant rate where its values are the preset; the defaults' annealed one otherwise
    assert config.algorithm.anneal_lr is (env not in AS_ZOO)
    if env in AS_ZOO:  # the same run as +experiment=rl_zoo, key for key
        assert to_dict(config) == to_dict(rl_zoo(env))
    if env == "hopper":  # the same run as the defaults, key for key
        assert to_dict(config) == to_dict(to_root_config(compose([f"env={env}"])))
    expected_kwargs = {"include_cfrc_ext_in_observation": False} if env == "ant" else {}
    assert config.env.kwargs == expected_kwargs


def test_ants_preset_builds_the_v4_observation_without_contact_forces(tmp_path):
    """Ant-v5 observes 105 numbers by default (27 positions and velocities, 78 contact forces);
    the tuned preset observes the 27, as Ant-v4 does by default and rl-zoo's Ant-v3 row did."""
    built = _built(tuned("ant", "env.num_eval_envs=1", "trainer.eval_every=0"), tmp_path)
    try:
        assert built.env.observation_spec["observation"].shape[-1] == 27
        assert torch.equal(built.policy.actor_net.log_std.detach(), torch.full((8,), ANT_LOG_STD))
    finally:
        built.env.close()
    plain = _built(rl_zoo("ant", "env.num_eval_envs=1", "trainer.eval_every=0"), tmp_path / "z")
    try:
        assert plain.env.observation_spec["observation"].shape[-1] == 105
    finally:
        plain.env.close()


def test_the_env_may_come_before_or_after_the_preset_and_overrides_win():
    assert to_dict(tuned("half_cheetah")) == to_dict(
        to_root_config(compose(["+experiment=tuned", "env=half_cheetah"]))
    )
    assert to_dict(rl_zoo("hopper")) == to_dict(
        to_root_config(compose(["+experiment=rl_zoo", "env=hopper"]))
    )
    config = tuned("half_cheetah", "algorithm.lr=0.001", "policy.init_log_std=-1")
    assert (config.algorithm.lr, config.policy.init_log_std) == (0.001, -1.0)
    assert config.algorithm.gamma == 0.98  # the rest of the preset stays
    # without +experiment=tuned: the defaults, whatever conf/tuned/ holds
    plain = to_root_config(compose(["env=hopper"]))
    assert (plain.algorithm.gamma, plain.algorithm.lr, plain.policy.init_log_std) == (
        0.99,
        3e-4,
        0.0,
    )


@pytest.mark.parametrize("env", sorted(CLASSIC))
def test_classic_control_presets_are_the_same_run_either_way(env):
    assert to_dict(tuned(env)) == to_dict(to_root_config(compose([f"+experiment={CLASSIC[env]}"])))


def test_classic_control_values_stay_those_measured():
    acrobot = tuned("acrobot")
    assert (acrobot.env.num_envs, acrobot.trainer.frames_per_batch) == (16, 4096)
    assert (acrobot.algorithm.lmbda, acrobot.algorithm.num_epochs) == (0.94, 4)
    cartpole = tuned("gym_cartpole")
    assert (cartpole.algorithm.gamma, cartpole.algorithm.lmbda, cartpole.algorithm.lr) == (
        0.98,
        0.8,
        1e-3,
    )
    pendulum = tuned("pendulum")
    assert (pendulum.algorithm.gamma, pendulum.algorithm.normalize_rewards) == (0.9, False)
    lander = tuned("lunar_lander")
    assert (lander.algorithm.gamma, lander.algorithm.entropy_coeff) == (0.999, 0.01)
    native = tuned("cart_pole")  # the users' settings: 256x256 ReLU networks
    assert (
        native.policy.actor.hidden_sizes == [256, 256] and native.policy.critic.activation == "relu"
    )
    assert native.trainer.frames_per_batch == 65536


def _orthogonal(weight: torch.Tensor, gain: float) -> bool:
    w = weight.detach().double()
    small = w @ w.T if w.shape[0] <= w.shape[1] else w.T @ w
    return torch.allclose(small, gain**2 * torch.eye(small.shape[0], dtype=w.dtype), atol=1e-6)


def _built(config: RootConfig, tmp_path):
    from rlexp.training.build import build

    return build(config, tmp_path, "cpu", config.trainer.total_frames)


def test_the_values_reach_the_built_policy_and_algorithm(tmp_path):
    config = tuned("half_cheetah", "env.num_eval_envs=1", "trainer.eval_every=0")
    built = _built(config, tmp_path)
    policy, algo = built.policy, built.algorithm
    actor = [m for m in policy.actor_net.mlp if isinstance(m, torch.nn.Linear)]
    critic = [m for m in policy.critic_net.mlp if isinstance(m, torch.nn.Linear)]
    assert [m.out_features for m in actor] == [256, 256, 6]  # HalfCheetah: 6 actions
    assert [m.out_features for m in critic] == [256, 256, 1]
    assert sum(isinstance(m, torch.nn.ReLU) for m in policy.actor_net.mlp) == 2
    assert sum(isinstance(m, torch.nn.ReLU) for m in policy.critic_net.mlp) == 2
    assert torch.equal(policy.actor_net.log_std.detach(), torch.full((6,), -2.0))
    # ortho_init false: PyTorch's own init (uniform weights and biases), as SB3's ortho_init=False
    assert not any(_orthogonal(m.weight, math.sqrt(2)) for m in actor[:-1] + critic[:-1])
    assert all(m.bias.abs().sum() > 0 for m in actor + critic)
    # the algorithm's objects: Adam's rate, the loss's clip and coefficients, GAE's gamma, lambda
    assert algo.optimizer.param_groups[0]["lr"] == pytest.approx(2.0633e-05)
    assert float(algo.loss.clip_epsilon) == pytest.approx(0.1)
    assert float(algo.loss.entropy_coeff) == pytest.approx(0.000401762)
    assert float(algo.loss.critic_coeff) == pytest.approx(0.58096)
    assert float(algo.gae.gamma) == pytest.approx(0.98) and float(algo.gae.lmbda) == pytest.approx(
        0.92
    )
    assert algo.reward_normalizer is not None and algo.reward_normalizer.gamma == 0.98
    built.env.close()


def test_ortho_init_true_gives_orthogonal_layers_and_zero_biases(tmp_path):
    config = tuned("walker2d", "env.num_eval_envs=1", "trainer.eval_every=0")
    built = _built(config, tmp_path)
    actor = [m for m in built.policy.actor_net.mlp if isinstance(m, torch.nn.Linear)]
    assert all(_orthogonal(m.weight, math.sqrt(2)) for m in actor[:-1])
    assert _orthogonal(actor[-1].weight, 0.01)
    assert all(float(m.bias.detach().abs().sum()) == 0.0 for m in actor)
    built.env.close()


def test_a_tuned_run_trains_with_its_preset(tmp_path):
    """HalfCheetah's preset, two 512-step rollouts (20 epochs of 8 minibatches each)."""
    run_dir = tmp_path / "run"
    run_train(
        [
            "env=half_cheetah",
            "+experiment=tuned",
            "trainer.total_frames=1024",
            "trainer.eval_every=0",
            "trainer.save_every=0",
            "trainer.progress=false",
            "logger=none",
            "algorithm.compile=false",
            f"hydra.run.dir={run_dir}",
        ],
        cwd=tmp_path,
        timeout=300,
    )
    status = json.loads((run_dir / "status.json").read_text())
    assert (status["state"], status["global_step"]) == ("finished", 1024)
    saved = OmegaConf.load(run_dir / "config.yaml")
    assert (saved.algorithm.lr, saved.algorithm.num_epochs, saved.policy.init_log_std) == (
        2.0633e-05,
        20,
        -2.0,
    )
    assert saved.trainer.frames_per_batch == 512


@pytest.mark.parametrize("group", ["tuned", "rl_zoo"])
def test_an_env_without_a_preset_is_one_line_and_exit_2(tmp_path, group):
    proc = run_train(
        ["env=push_cube", f"+experiment={group}"], cwd=tmp_path, check=False, timeout=120
    )
    assert proc.returncode == 2, proc.stderr
    err = proc.stderr.strip()
    assert err.splitlines() == [err], "one line, no traceback"
    assert f"+experiment={group} has no preset for env=push_cube (no conf/{group}/push_cube" in err
    assert "'half_cheetah'" in err and "'inverted_double_pendulum'" in err
    assert not (tmp_path / "outputs").exists()


@pytest.mark.parametrize("group", ["tuned", "rl_zoo"])
def test_a_config_json_run_with_a_task_preset_is_one_line_and_exit_2(tmp_path, group):
    from rlexp.launch.json_entry import ENV_NODE
    from rlexp.launch.precheck import JSON_ENV_OPTION

    assert JSON_ENV_OPTION == ENV_NODE
    path = REPO / "examples/json/cart_pole/train_config.json"
    proc = run_train(
        ["--config-json", str(path), f"+experiment={group}"], cwd=tmp_path, check=False, timeout=120
    )
    assert proc.returncode == 2, proc.stderr
    err = proc.stderr.strip()
    assert err.splitlines() == [err]
    assert f"+experiment={group} has no preset for a --config-json run's env" in err


def test_the_missing_preset_message_names_the_env_and_the_tasks():
    from hydra.errors import MissingConfigException

    from rlexp.launch.precheck import missing_tuned_preset

    exc = MissingConfigException("In 'config': Could not find 'tuned/my_env'", "tuned/my_env")
    message = missing_tuned_preset(exc)
    assert message is not None and message.startswith(
        "+experiment=tuned has no preset for env=my_env"
    )
    exc = MissingConfigException("In 'config': Could not find 'rl_zoo/my_env'", "rl_zoo/my_env")
    message = missing_tuned_preset(exc)
    assert message is not None and message.startswith(
        "+experiment=rl_zoo has no preset for env=my_env (no conf/rl_zoo/my_env.yaml)"
    )
    assert missing_tuned_preset(MissingConfigException("Could not find 'env/x'", "env/x")) is None


def _suite_jobs(suite: str = "tuned_1m") -> list[list[str]]:
    """The jobs' overrides of ``python train.py -m +sweep=<suite>``, as Hydra's basic sweeper
    expands them (its params, then the command line's)."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra.core.global_hydra import GlobalHydra
    from hydra.core.override_parser.overrides_parser import OverridesParser

    from rlexp.config.schema import register_configs

    register_configs()
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = hydra_compose(
            config_name="config", overrides=[f"+sweep={suite}"], return_hydra_config=True
        )
    assert cfg.hydra.sweep.dir == f"multirun/{suite}"  # fixed: the same command resumes
    params = [f"{k}={v}" for k, v in cfg.hydra.sweeper.params.items()]
    parsed = OverridesParser.create().parse_overrides([f"+sweep={suite}", *params])
    batches = BasicSweeper.split_arguments(parsed, None)
    return [list(job) for batch in batches for job in batch]


@pytest.mark.parametrize("suite", ["tuned_1m", "rl_zoo_1m"])
def test_the_suite_is_9_tasks_by_5_seeds_with_its_presets(suite):
    expected = TUNED if suite == "tuned_1m" else ZOO
    jobs = _suite_jobs(suite)
    assert len(jobs) == 45
    pairs = [
        (dict(o.split("=") for o in job)["env"], dict(o.split("=") for o in job)["seed"])
        for job in jobs
    ]
    assert sorted(pairs) == sorted((env, str(seed)) for env in MUJOCO for seed in range(5))
    # each job composes with its task's preset (three tasks checked; each composes once per env)
    for task in ("half_cheetah", "hopper", "ant"):
        job = next(j for j in jobs if f"env={task}" in j)
        assert as_zoo(to_root_config(compose(job))) == expected[task]
    for job in (jobs[0], next(j for j in jobs if "env=inverted_pendulum" in j)):
        config = to_root_config(compose(job))
        env = dict(o.split("=") for o in job)["env"]
        assert as_zoo(config) == expected[env]
        assert config.trainer.total_frames == 1_000_000


def test_each_preset_sets_only_schema_keys_and_states_its_source():
    sections = {f.name for f in dataclasses.fields(RootConfig)}
    for env in MUJOCO:
        text = (CONF_DIR / "rl_zoo" / f"{env}.yaml").read_text()
        assert text.startswith("# @package _global_\n")
        assert "rl-baselines3-zoo" in text and "hyperparams/ppo.yml" in text
        assert set(OmegaConf.create(text)) <= sections
        text = (CONF_DIR / "tuned" / f"{env}.yaml").read_text()
        assert text.startswith("# @package _global_\n")
        assert "docs/results.md" in text or f"conf/rl_zoo/{env}.yaml" in text
        assert set(OmegaConf.create(text)) <= sections | {"defaults"}


def test_a_sweep_over_an_env_without_a_preset_is_refused_before_any_job(tmp_path):
    """The first job (hopper) has a preset, the second (push_cube) none: one line, exit 2, no
    sweep dir, rather than Hydra stopping the sweep when it composes the second job."""
    sweep = tmp_path / "sweep"
    proc = run_train(
        ["-m", "+experiment=tuned", "env=hopper,push_cube", f"hydra.sweep.dir={sweep}"],
        cwd=tmp_path,
        check=False,
        timeout=120,
    )
    assert proc.returncode == 2, proc.stderr
    err = proc.stderr.strip()
    assert err.splitlines() == [err]
    assert err.startswith("config error: job 1 (+experiment=tuned env=push_cube")
    assert "+experiment=tuned has no preset for env=push_cube" in err
    assert not sweep.exists()


def test_the_suites_envs_pass_the_sweep_check():
    from hydra.core.global_hydra import GlobalHydra

    from rlexp.config.paths import initialize_hydra
    from rlexp.config.schema import register_configs
    from rlexp.launch.precheck import check_tuned_sweep

    register_configs()  # the schemas the configs name (also when this test runs alone)
    GlobalHydra.instance().clear()
    with initialize_hydra(CONF_DIR, None):
        from hydra import compose as hydra_compose

        loader = GlobalHydra.instance().config_loader()
        cfg = hydra_compose(
            config_name="config", overrides=["+sweep=tuned_1m"], return_hydra_config=True
        )
        check_tuned_sweep(cfg, loader, ["+sweep=tuned_1m"])  # all 9 have one: no error
        with pytest.raises(
            ConfigError, match="job 5 .*experiment=tuned has no preset for env=push"
        ):
            check_tuned_sweep(cfg, loader, ["+sweep=tuned_1m", "env=hopper,push_cube"])
        cfg = hydra_compose(
            config_name="config", overrides=["+sweep=rl_zoo_1m"], return_hydra_config=True
        )
        check_tuned_sweep(cfg, loader, ["+sweep=rl_zoo_1m"])
        with pytest.raises(ConfigError, match="job 5 .*experiment=rl_zoo has no preset for env=pu"):
            check_tuned_sweep(cfg, loader, ["+sweep=rl_zoo_1m", "env=hopper,push_cube"])
    GlobalHydra.instance().clear()
