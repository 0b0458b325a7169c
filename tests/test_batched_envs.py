"""Batched torch envs (#31): ``env.backend=vecenv`` (rsl_rl's VecEnv contract) and
``env.backend=torchrl`` (a TorchRL EnvBase factory), named ``package.module:callable``.

The adapters' values against numbers worked out by hand (the true final observation or rsl_rl's
stand-in, terminated vs truncated, the autoreset), end to end through ``train.py`` for each contract
(train, Ctrl-C, resume: bit-identical where the env has state, new seeded episodes where it has
none; ``rlexp eval``; ``rlexp export`` acting as the checkpoint), and every refusal in one line
naming the env. The env is ``tests/batched_toy.py``.
"""

from __future__ import annotations

import json
import os
import re
import signal
import time
from pathlib import Path

import pytest
import torch

from conftest import REPO, compose, rlexp_cli, run_train
from rlexp.checkpoints.files import latest_checkpoint, load_checkpoint, step_checkpoints

TESTS = Path(__file__).resolve().parent
#: batched_toy.py importable and allowed in the training process
ENV_VARS = {
    "PYTHONPATH": f"{REPO / 'src'}{os.pathsep}{TESTS}",
    "RLEXP_ENV_MODULES": "batched_toy",
}
BASE = [
    "env=hopper",
    "env.num_envs=4",
    "env.num_eval_envs=2",
    "trainer.frames_per_batch=128",
    "trainer.eval_every=1024",
    "trainer.eval_episodes=2",
    "trainer.save_every=256",
    "trainer.total_frames=8192",
    "algorithm.num_epochs=1",
    "trainer.progress=false",
    "logger=none",
    "logger.jsonl=true",
]
VECENV = [
    *BASE,
    "env.backend=vecenv",
    "env.name=batched_toy:make_vecenv",
    "+env.kwargs.obs_format=dict",  # rsl_rl 3.x's observation groups
    "+env.kwargs.critic=false",  # "policy" only: the export below probes the 7 policy values
    "seed=5",
]
TORCHRL = [*BASE, "env.backend=torchrl", "env.name=batched_toy:make_torchrl_env", "seed=6"]


@pytest.fixture
def allowed(monkeypatch):
    """In this process, as the subprocesses have it: RLEXP_ENV_MODULES=batched_toy."""
    monkeypatch.setenv("RLEXP_ENV_MODULES", "batched_toy")


# -- the adapters, against hand-computed numbers -----------------------------------------------------
#: Three envs: 0 keeps going, 1 reaches its 19-step limit, 2 leaves the arena (|x| > 2).
POS = [[0.5, -0.25], [0.0, 1.0], [1.9, 0.0]]
VEL = [[0.1, 0.0], [0.0, -0.5], [1.0, 0.0]]
GOAL = [[1.0, 1.0], [-1.0, 0.5], [0.0, 0.0]]
LENGTH = [3, 18, 7]
ACTION = [[1.0, 1.0], [0.5, -4.0], [2.0, 0.0]]  # rows 1 and 2 outside the box [-1, 1] x [-2, 2]


def _by_hand(action: list[list[float]]) -> dict[str, torch.Tensor]:
    """One step of the toy's physics, written out: damping 0.25, dt 0.2, force (3, 1.5), mass 1.3,
    arena 2, 19 steps; the observation [pos, vel, goal - pos, length / 19]."""
    pos, vel, goal = (torch.tensor(x) for x in (POS, VEL, GOAL))
    a = torch.tensor(action)
    vel2 = 0.75 * vel + 0.2 * torch.tensor([3.0, 1.5]) * a / 1.3
    pos2 = pos + 0.2 * vel2
    length = torch.tensor(LENGTH, dtype=torch.float32)
    before = torch.cat([pos, vel, goal - pos, (length / 19).unsqueeze(-1)], -1)
    final = torch.cat([pos2, vel2, goal - pos2, ((length + 1) / 19).unsqueeze(-1)], -1)
    reward = -(goal - pos2).norm(dim=-1) - 0.01 * a.pow(2).sum(-1)
    return {"before": before, "final": final, "reward": reward.unsqueeze(-1)}


@pytest.mark.parametrize("final_obs", [True, False], ids=["final_observation", "rsl_rl_stand_in"])
def test_vecenv_step_against_hand_computed_values(final_obs):
    from batched_toy import ToyVecEnv

    from rlexp.envs.vecenv import VecEnvAdapter

    env = VecEnvAdapter(ToyVecEnv(3, seed=0, final_obs=final_obs), "batched_toy:make_vecenv")
    env.reset()
    saved = env.env_state()  # the restore path puts the hand-made state in
    saved["state"].update(
        pos=torch.tensor(POS), vel=torch.tensor(VEL), goal=torch.tensor(GOAL),
        length=torch.tensor(LENGTH),
    )  # fmt: skip
    want = _by_hand([[1.0, 1.0], [0.5, -2.0], [1.0, 0.0]])  # clipped to the env's Box
    saved["obs"] = want["before"]
    env.load_env_state(saved)
    assert env.resume_mode == "restored (the env's get_state)"
    torch.testing.assert_close(env.reset()["observation"], want["before"])
    nxt = env.step_action(torch.tensor(ACTION))
    assert nxt["done"].reshape(-1).tolist() == [False, True, True]
    assert nxt["truncated"].reshape(-1).tolist() == [False, True, False]  # the time-out
    assert nxt["terminated"].reshape(-1).tolist() == [False, False, True]  # out of the arena
    torch.testing.assert_close(nxt["reward"], want["reward"])
    # "next": finished rows hold the true final observation, or (without one) rsl_rl's stand-in,
    # the observation the policy acted on (GAE then bootstraps the time-out from V(s_t))
    finished = want["final"] if final_obs else want["before"]
    torch.testing.assert_close(nxt["observation"][0], want["final"][0])
    torch.testing.assert_close(nxt["observation"][1:], finished[1:])
    after = env.autoreset_observation(nxt)  # what the policy acts on next: reset rows 1 and 2
    torch.testing.assert_close(after[0], want["final"][0])
    assert (after[1:, 2:4] == 0).all() and (after[1:, 6] == 0).all()  # at rest, phase 0
    assert (after[1:, :2].abs() <= 1).all() and not torch.equal(after[1:], want["final"][1:])


@pytest.mark.parametrize("obs_format", ["tensor", "tuple", "dict"])
def test_vecenv_observation_forms_give_the_same_run(obs_format):
    """A tensor, rsl_rl 2.x's (obs, extras) and rsl_rl 3.x's groups ("policy") are one contract:
    the policy's observation first in the vector (the dict's "critic" group, 2x it, after it)."""
    from batched_toy import ToyVecEnv

    from rlexp.envs.vecenv import VecEnvAdapter

    env = VecEnvAdapter(ToyVecEnv(2, seed=1, obs_format=obs_format), "toy")
    ref = VecEnvAdapter(ToyVecEnv(2, seed=1), "toy")
    assert env.obs_layout.parts[0].key == ("policy" if obs_format == "dict" else "")
    wide = 14 if obs_format == "dict" else 7
    assert env.obs_dim == wide

    def same(a, b):
        torch.testing.assert_close(a[:, :7], b, rtol=0, atol=0)
        if wide == 14:
            torch.testing.assert_close(a[:, 7:], 2 * b, rtol=0, atol=0)

    same(env.reset()["observation"], ref.reset()["observation"])
    for _ in range(25):  # past a time-out
        a, b = env.step_action(torch.ones(2, 2)), ref.step_action(torch.ones(2, 2))
        same(a["observation"], b["observation"])
        assert all((a[k] == b[k]).all() for k in ("reward", "done", "terminated", "truncated"))


def test_torchrl_step_against_hand_computed_values():
    """TorchRL's step_and_maybe_reset: the true final observation in "next", the reset one next;
    entries flattened depth-first, sorted ([phase, position, task/to_goal, velocity]); the
    unbounded actions reach the env unclipped."""
    from batched_toy import ToyTorchRLEnv

    from rlexp.envs.torchrl_env import TorchRLAdapter

    raw = ToyTorchRLEnv(3, seed=0)
    env = TorchRLAdapter(raw, "batched_toy:make_torchrl_env")
    assert [p.key for p in env.obs_layout.parts] == [
        "phase",
        "position",
        "task/to_goal",
        "velocity",
    ]
    assert (
        torch.isinf(env.action_spec.space.low).all()
        and torch.isinf(env.action_spec.space.high).all()
    )
    env.reset()
    p = raw.physics
    p.pos, p.vel, p.goal = torch.tensor(POS), torch.tensor(VEL), torch.tensor(GOAL)
    p.length = torch.tensor(LENGTH)
    want = _by_hand(ACTION)
    order = [6, 0, 1, 4, 5, 2, 3]  # [pos, vel, goal - pos, phase] -> the layout's order
    nxt = env.step_action(torch.tensor(ACTION))
    assert nxt["done"].reshape(-1).tolist() == [False, True, True]
    assert nxt["truncated"].reshape(-1).tolist() == [False, True, False]
    assert nxt["terminated"].reshape(-1).tolist() == [False, False, True]
    torch.testing.assert_close(nxt["reward"], want["reward"])
    torch.testing.assert_close(nxt["observation"], want["final"][:, order])
    after = env.autoreset_observation(nxt)
    torch.testing.assert_close(after[0], want["final"][0, order])
    assert (after[1:, 0] == 0).all() and (after[1:, 5:] == 0).all()  # phase 0, at rest


def test_the_chunked_eval_loop_equals_torchrl_s_loop(monkeypatch):
    """What an eval round runs on a GPU env (rewards and done flags read back every DEVICE_CHUNK
    steps, none per step), here on the CPU: TorchRL's step-by-step loop's episodes and numbers."""
    from batched_toy import ToyVecEnv

    from rlexp.config.schema import EnvConfig, PolicyConfig
    from rlexp.envs.vecenv import VecEnvAdapter
    from rlexp.policies.actor_critic import policy_for_env
    from rlexp.training import evaluation

    def env_and_policy():
        env = VecEnvAdapter(ToyVecEnv(3, seed=2), "toy")
        torch.manual_seed(0)
        policy = policy_for_env(PolicyConfig(), EnvConfig(normalize_observations=False), env)
        env.set_seed(7)
        return env, policy.sampling_policy(deterministic=True)

    monkeypatch.setattr(evaluation, "DEVICE_CHUNK", 5)  # chunk ends fall inside episodes
    env, policy = env_and_policy()
    tally = evaluation.EpisodeTally(3, 7)
    obs = env.reset()["observation"]
    with torch.no_grad():  # (as run_episodes runs it)
        act, ended = evaluation._actor(policy)
        evaluation._device_loop(env, act, ended, obs, tally, torch.device("cpu"), None)
    reference = evaluation.run_episodes(*env_and_policy(), 7, lean=False)
    assert tally.metrics() == reference and reference["eval/episodes"] == 7


def test_torchrl_action_specs_become_rlexp_actions():
    from torchrl.data import Binary, Bounded, Categorical, MultiCategorical, OneHot

    from rlexp.envs.torchrl_env import _action

    coding, shape, one_hot = _action(OneHot(5, shape=(4, 5)), 1, "w")
    assert (coding.kind, coding.nvec, shape, one_hot) == ("discrete", (5,), (4, 5), 5)
    coding, shape, one_hot = _action(Categorical(3, shape=(4,)), 1, "w")
    assert (coding.kind, coding.nvec, coding.dim, shape, one_hot) == ("discrete", (3,), 1, (4,), 0)
    coding, *_ = _action(MultiCategorical(nvec=[2, 7], shape=(4, 2)), 1, "w")
    assert (coding.kind, coding.nvec) == ("multi_discrete", (2, 7))
    coding, *_ = _action(Binary(3, shape=(4, 3)), 1, "w")
    assert (coding.kind, coding.nvec) == ("multi_binary", (2, 2, 2))
    low, high = torch.tensor([-1.0, -3.0]), torch.tensor([2.0, 0.5])
    coding, *_ = _action(Bounded(low.expand(4, 2), high.expand(4, 2), shape=(4, 2)), 1, "w")
    assert (coding.low, coding.high) == ((-1.0, -3.0), (2.0, 0.5))


# -- end to end through train.py ---------------------------------------------------------------------
def _interrupt_after_first_checkpoint(children, args: list[str], cwd: Path, run_dir: Path) -> None:
    """``train.py args`` in the background, Ctrl-C (SIGINT) once its first checkpoint exists: the
    run checkpoints at the end of that iteration and exits 130."""
    proc = children.train(args, cwd, cwd / "interrupted.txt", env_extra=ENV_VARS)
    deadline = time.time() + 120
    while (
        time.time() < deadline
        and proc.poll() is None
        and not step_checkpoints(run_dir / "checkpoints")
    ):
        time.sleep(0.02)
    proc.send_signal(signal.SIGINT)
    assert proc.wait(timeout=120) == 128 + signal.SIGINT, (cwd / "interrupted.txt").read_text()
    status = json.loads((run_dir / "status.json").read_text())
    assert status["state"] == "interrupted" and status["global_step"] < 8192


def _eval_line(*args) -> tuple[float, float]:
    code, out, err = rlexp_cli("eval", *args, "--episodes", "3")
    assert code == 0, err
    found = re.search(r"mean return (-?[\d.]+) \+- ([\d.]+) over 3 episodes", out)
    assert found, out
    return float(found.group(1)), float(found.group(2))


def _export_acts_as_the_policy(
    run_dir: Path, low: list[float], high: list[float], eval_tolerance: float = 0.0
) -> None:
    """The TorchScript file's actions on a probe batch are the checkpoint's deterministic ones,
    clipped to the env's bounds (the file's own); its eval equals the checkpoint's (within
    ``eval_tolerance``: a GPU policy and the CPU file differ in the last bits)."""
    from torchrl.data import Unbounded

    from rlexp.checkpoints.files import select_checkpoint
    from rlexp.config.schema import PolicyConfig
    from rlexp.policies.actor_critic import make_policy

    code, out, err = rlexp_cli("export", run_dir, "--format", "torchscript")
    assert code == 0, err
    ckpt, _ = select_checkpoint(run_dir, None)
    policy = make_policy(PolicyConfig(), 7, 2, Unbounded(shape=(2,)))
    policy.load_state_dict(ckpt["policy"])
    probe = torch.randn(256, 7, generator=torch.Generator().manual_seed(0)) * 20
    with torch.no_grad():
        mean = policy.sampling_policy(deterministic=True).sample(probe)[-2]
    want = torch.clamp(mean, torch.tensor(low), torch.tensor(high))
    exported = run_dir / "exported" / (Path(ckpt["path"]).stem + ".pt")
    got = torch.jit.load(str(exported))(probe)
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-5)
    meta = json.loads(Path(f"{exported}.json").read_text())
    shown = [None if abs(v) == float("inf") else v for v in low]
    assert meta["action_low"] == shown and meta["actions_clamped"] is True
    assert _eval_line(exported) == pytest.approx(_eval_line(ckpt["path"]), abs=eval_tolerance)
    module = torch.jit.load(str(exported))  # the bounds the file clips to are the env's
    assert module.action_low.tolist() == low and module.action_high.tolist() == high


def test_vecenv_trains_resumes_exactly_after_ctrl_c_evaluates_and_exports(
    tmp_path, children, allowed
):
    """The VecEnv has get_state/set_state: interrupted and resumed, the run ends bit-identical to
    the one that was never interrupted."""
    from rlexp.app import train
    from rlexp.config.validate import to_root_config

    train(to_root_config(compose(VECENV)), tmp_path / "whole")
    broken = tmp_path / "broken"
    args = [*VECENV, f"hydra.run.dir={broken}"]
    _interrupt_after_first_checkpoint(children, args, tmp_path, broken)
    proc = run_train(args, cwd=tmp_path, env_extra=ENV_VARS)
    assert "[resume] training envs: restored (the env's get_state)" in proc.stdout + proc.stderr
    a = load_checkpoint(latest_checkpoint(tmp_path / "whole" / "checkpoints"))
    b = load_checkpoint(latest_checkpoint(broken / "checkpoints"))
    assert a["global_step"] == b["global_step"] == 8192 and a["envs"]["train"]["kind"] == "state"
    for key, value in a["policy"].items():
        assert torch.equal(value, b["policy"][key]), f"policy.{key} differs after the resume"
    assert a["windows"]["returns"] == b["windows"]["returns"] and a["windows"]["returns"]
    assert (a["windows"]["running_return"] == b["windows"]["running_return"]).all()
    assert a["last_eval"] == b["last_eval"] and a["last_eval"]
    assert a["observation_layout"]["parts"][0]["key"] == "policy"
    _export_acts_as_the_policy(broken, [-1.0, -2.0], [1.0, 2.0])


def test_torchrl_env_trains_restarts_after_ctrl_c_evaluates_and_exports(
    tmp_path, children, allowed
):
    """The TorchRL env has no state: the resume starts new episodes, seeded from the checkpoint
    (seed + 1,000,003 x steps taken); its unbounded actions are exported unclipped."""
    run_dir = tmp_path / "run"
    args = [*TORCHRL, f"hydra.run.dir={run_dir}"]
    _interrupt_after_first_checkpoint(children, args, tmp_path, run_dir)
    stopped = load_checkpoint(latest_checkpoint(run_dir / "checkpoints"))
    assert stopped["envs"]["train"]["kind"] == "restart"
    steps = stopped["envs"]["train"]["steps"]
    assert steps * 4 == stopped["global_step"]  # the adapter counts steps of all 4 copies at once
    run_train(args, cwd=tmp_path, env_extra=ENV_VARS)
    status = json.loads((run_dir / "status.json").read_text())
    assert status["state"] == "finished" and status["global_step"] == 8192
    seed = (6 + 1_000_003 * steps) % 2**31
    assert status["env_resume"].startswith(f"restarted (new episodes seeded {seed}:"), status
    inf = float("inf")
    _export_acts_as_the_policy(run_dir, [-inf, -inf], [inf, inf])


# -- refusals: one line naming the env -----------------------------------------------------------
def _config_error(overrides: list[str]) -> str:
    from rlexp.config.validate import ConfigError, to_root_config
    from rlexp.launch.checks import check_buildable

    with pytest.raises(ConfigError) as err:
        check_buildable(to_root_config(compose(["env=hopper", *overrides])))
    msg = str(err.value)
    assert "\n" not in msg, msg
    return msg


VEC = ["env.backend=vecenv", "env.name=batched_toy:make_vecenv"]


@pytest.mark.parametrize(
    ("overrides", "words"),
    [
        (["env.backend=vecenv", "env.name=toy_vec"], "is not a registered env factory"),
        (["env.backend=vecenv", "env.name=batched_toy.missing:make"], "could not be imported"),
        (["env.backend=vecenv", "env.name=batched_toy:nothing"], "has no attribute 'nothing'"),
        (["env.backend=vecenv", "env.name=batched_toy:NOT_CALLABLE"], "not a callable"),
        (
            [*VEC, "+env.kwargs.bad=obs_shape"],
            "step()'s observation has shape [1, 6], expected [1, 7]",
        ),
        ([*VEC, "+env.kwargs.bad=obs_dtype"], "observation has dtype torch.int64, expected one of"),
        ([*VEC, "+env.kwargs.bad=device"], "is on meta, but the env says it lives on cpu"),
        (
            [*VEC, "+env.kwargs.bad=reward_shape"],
            "rewards has shape [1, 2], expected [1] or [1, 1]",
        ),
        ([*VEC, "+env.kwargs.speed=2"], "env.kwargs.speed is not a parameter of the callable"),
        ([*VEC, "+env.kwargs.seed=2"], "env.kwargs.seed is set by rlexp"),
        ([*VEC, "env.max_episode_steps=50"], "keeps its own time limit"),
        (
            ["env.backend=vecenv", "env.name=batched_toy:make_vecenv_of_three", "env.num_envs=4"],
            "builds 3 envs (the callable takes no num_envs parameter: its own count) but "
            "env.num_envs=4",
        ),
        (
            ["env.backend=vecenv", "env.name=batched_toy:make_torchrl_env"],
            "use env.backend=torchrl",
        ),
        (["env.backend=torchrl", "env.name=batched_toy:make_vecenv"], "use env.backend=vecenv"),
    ],
)
def test_what_cannot_run_is_one_line_at_the_config_check(overrides, words, allowed):
    msg = _config_error(overrides)
    name = next(o for o in overrides if o.startswith("env.name=")).split("=", 1)[1]
    assert words in msg and f"env.name={name!r}" in msg, msg


def test_a_module_outside_the_allowlist_names_the_three_ways_to_allow_it(tmp_path):
    """Not allowed (no RLEXP_ENV_MODULES): one line, exit 2, before the run dir exists."""
    run_dir = tmp_path / "r"
    env = {**ENV_VARS, "RLEXP_ENV_MODULES": None}
    proc = run_train([*VECENV, f"hydra.run.dir={run_dir}"], tmp_path, check=False, env_extra=env)
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr
    assert "env.name='batched_toy:make_vecenv'" in lines[0] and "is not allowed" in lines[0]
    for way in (
        "RLEXP_ENV_MODULES=batched_toy",
        "allow_env_module('batched_toy')",
        "register_env_factory",
    ):
        assert way in lines[0], lines[0]
    assert not run_dir.exists()


def test_a_registered_name_and_a_plugin_s_allowed_module(monkeypatch):
    """What a plugin does: register a name, or allow its package (no shell variable needed)."""
    from batched_toy import make_vecenv

    from rlexp.config.validate import to_root_config
    from rlexp.envs import batched
    from rlexp.launch.checks import check_buildable

    monkeypatch.delenv("RLEXP_ENV_MODULES", raising=False)
    monkeypatch.setattr(batched, "ENV_FACTORIES", {})
    monkeypatch.setattr(batched, "_ALLOWED_MODULES", list(batched._ALLOWED_MODULES))
    batched.register_env_factory("toy_vec", make_vecenv)
    check_buildable(
        to_root_config(compose(["env=hopper", "env.backend=vecenv", "env.name=toy_vec"]))
    )
    assert "did you mean 'toy_vec'" in _config_error(["env.backend=vecenv", "env.name=toy_ve"])
    batched.allow_env_module("batched_toy")
    check_buildable(to_root_config(compose(["env=hopper", *VEC])))


def test_auto_device_is_the_env_s_gpu_or_the_cpu_for_a_small_mlp(monkeypatch):
    from rlexp.config.schema import MLPConfig, PolicyConfig
    from rlexp.runtime.devices import auto_device

    small = PolicyConfig()  # 64x64
    wide = PolicyConfig(critic=MLPConfig(hidden_sizes=[512, 512]))
    assert auto_device(torch.device("cpu"), small, None)[0] == "cpu"  # no CUDA here, or...
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)  # ... as on a GPU machine
    device, why = auto_device(torch.device("cpu"), small, None)
    assert device == "cpu" and "small MLP (widest layer 64 <= 256)" in why
    assert auto_device(torch.device("cpu"), wide, None)[0] == "cuda"
    assert auto_device(torch.device("cuda:1"), small, None)[0] == "cuda:1"
    assert auto_device(torch.device("cpu"), small, 3)[0] == "cuda:3"  # distributed on nccl
