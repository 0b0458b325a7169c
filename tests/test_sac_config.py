"""algorithm=sac / td3: the composed config, the derived frames_per_batch, and the one-line
refusals of what does not combine (checked before anything is built or written)."""

from __future__ import annotations

import pytest

from conftest import compose, run_train
from rlexp.config.schema_offpolicy import SACConfig, SACPolicyConfig, TD3Config, TD3PolicyConfig
from rlexp.config.validate import ConfigError, to_root_config


def test_sac_and_td3_compose_with_their_networks_and_rollouts_of_train_freq_steps():
    c = to_root_config(compose(["algorithm=sac", "env.num_envs=3", "algorithm.train_freq=4"]))
    assert isinstance(c.algorithm, SACConfig) and type(c.policy) is SACPolicyConfig
    assert c.trainer.frames_per_batch == 12  # env.num_envs * train_freq
    assert c.policy.actor.hidden_sizes == [256, 256] and c.policy.critic.activation == "relu"
    assert c.algorithm.target_entropy == "auto" and c.algorithm.learning_starts == 10_000
    t = to_root_config(compose(["algorithm=td3", "algorithm.policy_delay=3"]))
    assert isinstance(t.algorithm, TD3Config) and type(t.policy) is TD3PolicyConfig
    assert (t.algorithm.policy_delay, t.algorithm.lr, t.trainer.frames_per_batch) == (3, 1e-3, 1)


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (["algorithm=sac", "policy=mlp"], "algorithm=sac needs policy.name='sac'"),
        (["algorithm=td3", "policy=sac"], "algorithm=td3 needs policy.name='td3'"),
        (
            ["algorithm=sac", "algorithm.clip_epsilon=0.1"],
            "algorithm.clip_epsilon=0.1 is a PPO / GRPO option",
        ),
        (
            ["algorithm=td3", "algorithm.num_epochs=4"],
            "algorithm.num_epochs=4 is a PPO / GRPO option",
        ),
        (
            ["algorithm=sac", "algorithm.mini_batch_size=32"],
            "algorithm.mini_batch_size=32 is a PPO",
        ),
        (["policy=sac"], "policy.name='sac' is for algorithm=sac"),
        (["algorithm=grpo", "policy=td3"], "policy.name='td3' is for algorithm=td3"),
        (
            ["algorithm=sac", "algorithm.batch_size=512", "algorithm.buffer_size=100"],
            "algorithm.batch_size=512 must be at most algorithm.buffer_size=100",
        ),
        (
            ["algorithm=sac", "algorithm.target_entropy=big"],
            "algorithm.target_entropy='big' must be auto",
        ),
        (["algorithm=sac", "algorithm.tau=1.5"], "algorithm.tau=1.5 must be in [0.0, 1.0]"),
        (["algorithm=td3", "algorithm.policy_delay=0"], "algorithm.policy_delay=0 must be >= 1"),
        (["algorithm=sac", "algorithm.updates_per_step=0"], "algorithm.updates_per_step=0"),
        (["algorithm=sac", "algorithm.buffer_storage=disk"], "algorithm.buffer_storage='disk'"),
    ],
)
def test_what_does_not_combine_is_refused_in_one_line(overrides, message):
    with pytest.raises(ConfigError) as err:
        to_root_config(compose(overrides))
    assert message in str(err.value) and "\n" not in str(err.value)


def test_discrete_actions_are_refused_with_exit_2_before_the_run_dir(tmp_path):
    run_dir = tmp_path / "run"
    proc = run_train(["algorithm=sac", "env=gym_cartpole", f"hydra.run.dir={run_dir}"],
                     cwd=tmp_path, check=False, timeout=300)  # fmt: skip
    assert proc.returncode == 2
    out = proc.stdout + proc.stderr
    assert "policy=sac: the env's actions are discrete" in out and "Traceback" not in out
    assert not run_dir.exists()


@pytest.mark.parametrize(
    ("env", "algo", "expected"),
    [  # rl-baselines3-zoo hyperparams/sac.yml and td3.yml (eec15dc), SB3's defaults elsewhere
        (
            "hopper",
            "sac",
            {"lr": 3e-4, "learning_starts": 10_000, "gamma": 0.99, "sizes": [256, 256]},
        ),
        (
            "pendulum",
            "sac",
            {"lr": 1e-3, "learning_starts": 100, "gamma": 0.99, "sizes": [256, 256]},
        ),
        (
            "half_cheetah",
            "td3",
            {"lr": 1e-3, "learning_starts": 10_000, "gamma": 0.99, "sizes": [400, 300]},
        ),
        (
            "pendulum",
            "td3",
            {"lr": 1e-3, "learning_starts": 10_000, "gamma": 0.98, "sizes": [400, 300]},
        ),
    ],
)
def test_the_rl_zoo_presets_per_task(env, algo, expected):
    c = to_root_config(compose([f"env={env}", f"+experiment={algo}"]))
    a = c.algorithm
    assert (a.name, c.policy.name, c.env.num_envs, c.env.normalize_observations) == (
        algo,
        algo,
        1,
        False,
    )
    got = {"lr": a.lr, "learning_starts": a.learning_starts, "gamma": a.gamma,
           "sizes": c.policy.actor.hidden_sizes}  # fmt: skip
    assert got == expected


def test_a_task_without_an_off_policy_preset_is_refused_in_one_line(tmp_path):
    proc = run_train(["env=swimmer", "+experiment=td3", f"hydra.run.dir={tmp_path / 'run'}"],
                     cwd=tmp_path, check=False, timeout=300)  # fmt: skip
    assert proc.returncode == 2 and not (tmp_path / "run").exists()
    assert (
        "+experiment=td3 has no preset for env=swimmer (no conf/td3_zoo/swimmer.yaml)"
        in proc.stderr
    )


@pytest.mark.parametrize(
    ("old", "new", "message"),
    [
        ('"name": "ppo"', '"name": "sac"', "algorithm.name='sac': choose from ['ppo', 'grpo']"),
        (
            '"name": "actor_critic"',
            '"name": "td3"',
            "policy.name='td3': choose from ['actor_critic', 'actor_only']",
        ),
    ],
)
def test_the_users_json_files_keep_their_ppo_and_grpo_names(tmp_path, old, new, message):
    from conftest import REPO

    text = (REPO / "examples/json/cart_pole/train_config.json").read_text()
    assert old in text
    path = tmp_path / "train.json"
    path.write_text(text.replace(old, new))
    proc = run_train(["--config-json", str(path), f"hydra.run.dir={tmp_path / 'run'}"],
                     cwd=REPO, check=False, timeout=300)  # fmt: skip
    assert proc.returncode == 2 and message in proc.stderr and "Traceback" not in proc.stderr
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("algorithm", ["sac", "td3"])
def test_distributed_off_policy_is_refused_in_one_line_on_every_rank_before_a_run_dir(
    tmp_path, algorithm
):
    """torchrun with two ranks: a rank's precheck refuses (exit 2, one line naming the algorithm
    and the fix), before Hydra creates a run dir or an env is built."""
    import os
    import subprocess
    import sys

    from conftest import REPO, Children

    env = {**os.environ, "PYTHONPATH": str(REPO / "src"), "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2",
           str(REPO / "train.py"), "--distributed", "env=pendulum", f"algorithm={algorithm}",
           "trainer.total_frames=64"]  # fmt: skip
    with Children() as children:  # torchrun's group (its ranks too) killed however this ends
        proc = children.popen(cmd, cwd=tmp_path, env=env, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True)  # fmt: skip
        stdout, stderr = proc.communicate(timeout=300)
    out = stdout + stderr
    line = f"config error: --distributed: algorithm={algorithm} learns from one process's replay"
    # the first rank to refuse ends the job: torchrun may stop the other before it prints
    lines = [x for x in out.splitlines() if "--distributed: algorithm=" in x]
    assert proc.returncode != 0 and 1 <= len(lines) <= 2, out[-3000:]
    assert all(x.startswith(line) for x in lines)
    assert "src/rlexp/" not in out and "[rlexp." not in out  # no rlexp traceback, no run's log
    assert "exitcode  : 2" in stderr  # torchrun's summary of the rank that refused
    assert not (tmp_path / "outputs").exists() and not list(tmp_path.glob("MUJOCO_LOG.TXT"))
