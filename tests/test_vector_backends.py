"""The vectorised CPU backends of #31: ``env.backend=envpool`` steps as raw EnvPool does (final and
reset observations, terminated vs truncated, rewards), reseeds to repeat eval rounds and restarts on
resume; ``env.backend=gymnasium_async`` gives the in-process backend's rollouts value for value
(Box, Dict / MultiDiscrete, Discrete envs), resumes them exactly where the env offers state, reports
a dead worker in one line and never leaves a worker behind; both train, stop on Ctrl-C, resume,
evaluate and export through ``train.py`` / ``rlexp``."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from test_resume import _kill_after_checkpoint

from conftest import REPO, compose, rlexp_cli, run_train
from rlexp.checkpoints.files import latest_checkpoint, load_checkpoint, step_checkpoints

envpool = pytest.importorskip("envpool")
TESTS = Path(__file__).resolve().parent


def _rollout(env, actions: list[torch.Tensor], obs: torch.Tensor | None = None):
    """What the lean collector sees, from ``obs`` (None: a full reset): the observation acted on,
    then each step's entries; and the observation to act on next."""
    seen = []
    obs = env.reset()["observation"] if obs is None else obs
    for action in actions:
        nxt = env.step_tensors(action)
        seen += [obs.clone(), *(nxt[k].clone() for k in sorted(nxt))]
        obs = env.autoreset_observation(nxt)
    return seen, obs


def _actions(env, steps: int, seed: int = 0) -> list[torch.Tensor]:
    """Random actions for ``env``: Box ones 30 % beyond the box (so clipping matters), categorical
    ones uniform over each component's values."""
    gen = torch.Generator().manual_seed(seed)
    shape = env.action_spec.shape
    coding = env.action_coding
    if coding.categorical:
        nvec = torch.tensor(coding.nvec)
        return [(torch.rand(shape, generator=gen) * nvec).long() for _ in range(steps)]
    return [torch.rand(shape, generator=gen) * 2.6 - 1.3 for _ in range(steps)]


# -- envpool ---------------------------------------------------------------------------------------
def test_envpool_steps_as_raw_envpool_across_terminations_and_truncations():
    """Hopper-v5 x3 with a 23-step limit: each copy against a raw single-env pool of its own seed
    (EnvPool seeds env i with seed + i), fed the actions clipped by hand to Hopper's box [-1, 1];
    a raw pool resets at the step after a done (reward 0): that observation is the adapter's reset
    one, handed out by autoreset_observation."""
    from rlexp.envs.envpool_env import EnvPoolEnv

    n, seed, limit = 3, 11, 23
    env = EnvPoolEnv("Hopper-v5", n, seed, limit, {}, num_threads=2)
    assert env.obs_dim == 11 and env.act_dim == 3 and env._pool.config["num_threads"] == 2
    actions = _actions(env, 70)
    env.set_seed(seed)
    obs = env.reset()["observation"]
    steps = []
    for action in actions:
        nxt = env.step_tensors(action)
        assert nxt["observation"].dtype == torch.float32 and nxt["reward"].shape == (n, 1)
        steps.append((obs.clone(), {k: v.clone() for k, v in nxt.items()}))
        obs = env.autoreset_observation(nxt)
    env.close()
    ends = {"terminated": 0, "truncated": 0}
    for k in range(n):
        raw = envpool.make_gymnasium(
            "Hopper-v5", num_envs=1, seed=seed + k, max_episode_steps=limit
        )
        o, _ = raw.reset()
        for t, action in enumerate(actions):
            acted_on, nxt = steps[t]
            assert torch.equal(acted_on[k], torch.from_numpy(o[0].astype(np.float32))), (k, t)
            clipped = np.clip(action[k : k + 1].numpy().astype(np.float64), -1.0, 1.0)
            o, r, term, trunc, _ = raw.step(clipped)
            assert torch.equal(nxt["observation"][k], torch.from_numpy(o[0].astype(np.float32)))
            assert nxt["reward"][k, 0].item() == np.float32(r[0]), (k, t)
            assert (nxt["terminated"][k, 0].item(), nxt["truncated"][k, 0].item()) == (
                bool(term[0]),
                bool(trunc[0]),
            ), (k, t)
            assert nxt["done"][k, 0].item() == bool(term[0] or trunc[0])
            if term[0] or trunc[0]:
                ends["terminated" if term[0] else "truncated"] += 1
                o, r, term, trunc, _ = raw.step(np.zeros((1, 3)))  # EnvPool's own reset step
                assert r[0] == 0.0 and not term[0] and not trunc[0]
        raw.close()
    assert ends["terminated"] > 0 and ends["truncated"] > 0, ends  # both kinds of episode end seen


def test_envpool_set_seed_repeats_eval_rounds_and_a_resume_restarts_seeded():
    from rlexp.envs.envpool_env import EnvPoolEnv

    env = EnvPoolEnv("HalfCheetah-v5", 2, 3, 9, {}, num_threads=1)
    actions = _actions(env, 20)

    def round_(seed: int) -> torch.Tensor:
        env.set_seed(seed)
        return torch.cat([x.reshape(-1).float() for x in _rollout(env, actions)[0]])

    first = round_(7)
    assert torch.equal(round_(7), first)  # the eval loop's set_seed + reset: the same round
    assert not torch.equal(round_(8), first)
    sd = env.env_state()
    assert sd["kind"] == "restart" and sd["steps"] == 60 and sd["seed"] == 8
    env.load_env_state(sd)
    want = (8 + 1_000_003 * 60) % 2**31  # seed + 1,000,003 x steps per copy
    assert env.resume_mode == f"restarted (new episodes seeded {want}: EnvPool offers no env state)"
    raw_reset, _ = envpool.make_gymnasium("HalfCheetah-v5", num_envs=2, seed=want).reset()
    assert torch.equal(env.reset()["observation"], torch.from_numpy(raw_reset.astype(np.float32)))
    env.close()


def test_envpool_threads_are_the_config_bounded_by_cpus_and_envs(monkeypatch):
    from rlexp.envs import envpool_env

    monkeypatch.setattr(envpool_env, "available_cpus", lambda: 3)
    pick = envpool_env.pool_threads
    assert (pick(0, 8), pick(0, 2), pick(2, 8), pick(5, 8), pick(5, 1)) == (3, 2, 2, 3, 1)


def test_a_missing_envpool_extra_is_one_line_naming_it(monkeypatch):
    from rlexp import extras
    from rlexp.config.validate import ConfigError, to_root_config
    from rlexp.launch.checks import check_buildable

    installed = extras._installed
    monkeypatch.setattr(extras, "_installed", lambda m: m != "envpool" and installed(m))
    config = to_root_config(compose(["env=hopper", "env.backend=envpool"]))
    with pytest.raises(ConfigError) as err:
        check_buildable(config)
    msg = str(err.value)
    assert "\n" not in msg and msg.startswith(
        "env.backend=envpool needs rlexp's optional 'envpool'"
    )
    assert "envpool is not installed" in msg


@pytest.mark.parametrize(
    ("overrides", "words"),
    [
        (["env.backend=envpool", "env.name=HalfCheeta-v5"], "did you mean 'HalfCheetah-v5'?"),
        (["env.backend=envpool", "env.name=toy_envs:DictGoal-v0"], "not a module:EnvId env"),
        (["env.backend=envpool", "+env.kwargs.reset_noise=0.2"], "env.kwargs.reset_noise is not"),
        (["env.backend=gymnasium_async", "env.name=Hoper-v5"], "did you mean 'Hopper-v5'?"),
        (
            ["env.backend=gymnasium_async", "events=domain_randomization"],
            "(env.backend=gymnasium_async) exposes no MuJoCo model to the training process",
        ),
        (["env.backend=envpool", "events=eval_video"], "env.backend=envpool does not render"),
    ],
)
def test_bad_names_and_what_cannot_run_are_one_line_at_the_config_check(overrides, words):
    from rlexp.config.validate import ConfigError, to_root_config
    from rlexp.launch.checks import check_buildable

    config = to_root_config(compose(["env=hopper", *overrides]))
    with pytest.raises(ConfigError) as err:
        check_buildable(config)
    assert "\n" not in str(err.value) and words in str(err.value), str(err.value)


# -- gymnasium_async -------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("env_id", "limit", "kind"),
    [
        ("Hopper-v5", 13, "mujoco"),  # Box; terminations and time-limit truncations
        ("toy_envs:DictGoal-v0", 7, "state"),  # Dict observations, MultiDiscrete, get_state
        ("toy_envs:NoStateWalk-v0", 5, "restart"),  # Discrete(3, start=-1), no state
    ],
)
def test_async_rollouts_and_resume_equal_the_in_process_backend(env_id, limit, kind):
    """The reference is the in-process GymnasiumEnv with the same seed and actions: the same
    rollouts value for value; a fresh async env loaded with a mid-run env_state continues as the
    uninterrupted in-process env (mujoco / state) or restarts as the in-process env restarts."""
    from rlexp.envs.gym import GymnasiumEnv
    from rlexp.envs.gym_async import AsyncGymnasiumEnv

    n = 3
    ours, ref = AsyncGymnasiumEnv(env_id, n, limit), GymnasiumEnv(env_id, n, limit)
    try:
        assert ours.state_kind == ref.state_kind == kind
        assert ours.obs_layout.record() == ref.obs_layout.record()
        assert ours.action_coding == ref.action_coding
        actions = _actions(ref, 40)
        ours.set_seed(5), ref.set_seed(5)
        (got, _), (want, ref_obs) = _rollout(ours, actions[:25]), _rollout(ref, actions[:25])
        assert all(torch.equal(a, b) for a, b in zip(got, want, strict=True))
        assert sum(int(t.sum()) for t in want[1::6]) >= 3  # (done: the entry after the obs)
        saved = ours.env_state()
        assert saved["kind"] == kind
    finally:
        ours.close()
    resumed, other = AsyncGymnasiumEnv(env_id, n, limit), GymnasiumEnv(env_id, n, limit)
    try:
        for env in (resumed, other):  # a resumed run: built and seeded anew, then the state
            env.set_seed(5)
            env.load_env_state(saved)
        assert resumed.resume_mode == other.resume_mode
        assert resumed.resume_mode.startswith("restarted" if kind == "restart" else "restored")
        got, want = _rollout(resumed, actions[25:])[0], _rollout(other, actions[25:])[0]
        assert all(torch.equal(a, b) for a, b in zip(got, want, strict=True))
        if kind != "restart":  # the episodes continue exactly as if never interrupted
            want = _rollout(ref, actions[25:], ref_obs)[0]
            assert all(torch.equal(a, b) for a, b in zip(got, want, strict=True))
    finally:
        for env in (resumed, other, ref):
            env.close()


def test_a_dead_worker_is_one_error_and_every_worker_is_closed():
    from rlexp.envs.gym_async import AsyncGymnasiumEnv, WorkerError

    env = AsyncGymnasiumEnv("CartPole-v1", 3)
    env.reset()
    pids = [p.pid for p in env._vec.processes]
    os.kill(pids[1], signal.SIGKILL)
    with pytest.raises(WorkerError) as err:
        for _ in range(3):
            env.step_tensors(torch.zeros(3, 1, dtype=torch.int64))
    msg = str(err.value)
    assert "\n" not in msg and msg.startswith(
        "env.name='CartPole-v1' (env.backend=gymnasium_async)"
    )
    assert f"worker 1 (pid {pids[1]}) died: killed by SIGKILL; all workers are closed" in msg
    assert not any(p.is_alive() for p in env._vec.processes)
    env.close()  # closing again after the failure: no error, no wait


WORKERS_OF_A_KILLED_RUN = """
import time
if __name__ == "__main__":  # (each worker imports this module: torch only in the main process)
    from rlexp.envs.gym_async import AsyncGymnasiumEnv
    env = AsyncGymnasiumEnv("CartPole-v1", 2)
    print(*[p.pid for p in env._vec.processes], flush=True)
    time.sleep(120)
"""


def test_workers_exit_when_the_training_process_is_killed(tmp_path, children):
    """SIGKILL gives the training process no chance to close them: each worker sees its pipe
    close and exits (the forkserver's workers hold no other worker's pipe, as fork's would)."""
    script = tmp_path / "run.py"
    script.write_text(WORKERS_OF_A_KILLED_RUN)
    env = {**os.environ, "PYTHONPATH": str(REPO / "src")}
    proc = children.popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True, env=env)
    pids = [int(p) for p in proc.stdout.readline().split()]
    assert len(pids) == 2 and all(_running(p) for p in pids)
    proc.kill()
    proc.wait(timeout=30)
    deadline = time.time() + 20
    while time.time() < deadline and any(_running(p) for p in pids):
        time.sleep(0.1)
    assert not any(_running(p) for p in pids)


def _running(pid: int) -> bool:
    """``pid`` exists and is not a zombie."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return False


def _session(sid: int) -> list[int]:
    """The live processes of session ``sid`` (a run started by ``Children`` leads its own)."""
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if fields[0] != "Z" and int(fields[3]) == sid:
            found.append(int(stat.parent.name))
    return found


# -- end to end through train.py -------------------------------------------------------------------
#: Hopper x2, 256-step rollouts, a checkpoint and a 2-episode eval every 512 steps, 2048 steps.
RUN = [
    "env=hopper",
    "env.num_envs=2",
    "env.num_eval_envs=2",
    "trainer.total_frames=2048",
    "trainer.frames_per_batch=256",
    "trainer.save_every=512",
    "trainer.eval_every=512",
    "trainer.eval_episodes=2",
    "trainer.eval_async=false",
    "algorithm.num_epochs=1",
    "trainer.progress=false",
    "seed=13",
]


def _ctrl_c_and_resume(tmp_path: Path, backend: str) -> tuple[Path, int, dict, dict]:
    """Train on ``backend``; Ctrl-C (SIGINT to the run's process group) once the step-512
    checkpoint is there: exit 130 with a checkpoint, no process of the run left; resume to the end.
    The run dir, the step it stopped at, its final status, the checkpoint the stop wrote."""
    run_dir = tmp_path / backend
    args = [*RUN, f"env.backend={backend}", f"hydra.run.dir={run_dir}"]
    sid = _kill_after_checkpoint(args, tmp_path, run_dir / "checkpoints", 512, sig=signal.SIGINT)
    deadline = time.time() + 20
    while time.time() < deadline and _session(sid):
        time.sleep(0.1)
    assert not _session(sid), f"processes of the stopped run still run: {_session(sid)}"
    stopped = max(int(p.stem.rsplit("_", 1)[1]) for p in step_checkpoints(run_dir / "checkpoints"))
    # The stop itself checkpointed, envs included: not a worker killed by the Ctrl-C too (a second
    # interrupt, no checkpoint), leaving the resume to the periodic checkpoint before it.
    stop = json.loads((run_dir / "status.json").read_text())
    newest = latest_checkpoint(run_dir / "checkpoints")
    assert (stop["state"], stop["reason"]) == ("interrupted", "SIGINT received"), stop
    assert stop["global_step"] == stopped and newest.name.endswith(f"_{stopped:09d}.pt"), stop
    stop_ckpt = load_checkpoint(newest)
    run_train(args, cwd=tmp_path)
    status = json.loads((run_dir / "status.json").read_text())
    assert status["state"] == "finished" and status["global_step"] == 2048
    return run_dir, stopped, status, stop_ckpt


def _eval_and_export(run_dir: Path) -> dict:
    """``rlexp eval`` twice (the same numbers: every round starts from the same seeded episodes)
    and ``rlexp export``; the export's metadata."""
    evals = [rlexp_cli("eval", run_dir, "--episodes", "2") for _ in range(2)]
    assert all(code == 0 and "mean return" in out for code, out, _ in evals), evals
    assert evals[0][1] == evals[1][1]
    code, out, err = rlexp_cli("export", run_dir, "--format", "torchscript")
    assert code == 0, err
    return json.loads(next((run_dir / "exported").glob("*.pt.json")).read_text())


def test_async_backend_trains_stops_on_ctrl_c_and_resumes_as_the_in_process_run(tmp_path):
    """Interrupted and resumed on gymnasium_async, the run ends bit-identical to an uninterrupted
    run of the in-process backend (the same rollouts, an exact MuJoCo resume)."""
    reference = tmp_path / "reference"
    run_train([*RUN, "env.backend=gymnasium", f"hydra.run.dir={reference}"], cwd=tmp_path)
    run_dir, stopped, status, stop_ckpt = _ctrl_c_and_resume(tmp_path, "gymnasium_async")
    assert 512 <= stopped < 2048 and status["env_resume"] == "restored (MuJoCo state)"
    # The stop checkpoint read the workers' envs: they were not hit by the Ctrl-C (own group).
    assert (
        stop_ckpt["envs"]["train"]["kind"] == "mujoco"
        and len(stop_ckpt["envs"]["train"]["copies"]) == 2
    )
    a = load_checkpoint(latest_checkpoint(reference / "checkpoints"))
    b = load_checkpoint(latest_checkpoint(run_dir / "checkpoints"))
    assert a["global_step"] == b["global_step"] == 2048
    for key, value in a["policy"].items():
        assert torch.equal(value, b["policy"][key]), f"policy.{key} differs"
    assert a["last_eval"] == b["last_eval"] and a["windows"]["returns"] == b["windows"]["returns"]
    meta = _eval_and_export(run_dir)
    assert meta["observation_dim"] == 11 and meta["action_space"]["low"] == [-1.0] * 3


def test_envpool_backend_trains_stops_on_ctrl_c_resumes_with_new_episodes_and_exports(tmp_path):
    run_dir, stopped, status, _ = _ctrl_c_and_resume(tmp_path, "envpool")
    seed = (13 + 1_000_003 * (stopped // 2)) % 2**31  # seed + 1,000,003 x steps per env copy
    assert status["env_resume"] == (
        f"restarted (new episodes seeded {seed}: EnvPool offers no env state)"
    )
    rows = [json.loads(x) for x in (run_dir / "metrics.jsonl").read_text().splitlines()]
    assert sorted(r["step"] for r in rows if "eval/episode_return" in r) == [512, 1024, 1536, 2048]
    meta = _eval_and_export(run_dir)
    assert meta["observation_dim"] == 11 and meta["action_space"]["high"] == [1.0] * 3


def test_the_eval_worker_evaluates_an_async_run_in_process():
    """``trainer.eval_async``'s worker is a daemonic process, which may not start workers: it
    builds the in-process backend, whose episodes are the same value for value."""
    from rlexp.config.schema import EnvConfig, PolicyConfig
    from rlexp.envs.gym import GymnasiumEnv
    from rlexp.training.eval_worker import EvalSetup

    cfg = EnvConfig(name="Hopper-v5", backend="gymnasium_async", num_eval_envs=2)
    env, _ = EvalSetup(cfg, PolicyConfig(), seed=3, episodes=2).build()
    assert type(env) is GymnasiumEnv and env.num_envs == 2
    env.close()


def test_a_local_sweep_job_starts_async_workers(tmp_path):
    """A ``hydra/launcher=local`` job runs in a joblib worker, whose default start method (loky)
    a forkserver child does not know: the workers start all the same."""
    sweep = tmp_path / "sweep"
    run = [a for a in RUN if not a.startswith(("trainer.total_frames=", "seed="))]
    args = ["hydra/launcher=local", "env.backend=gymnasium_async", "trainer.total_frames=256"]
    run_train(["-m", *run, *args, "seed=1", f"hydra.sweep.dir={sweep}"], cwd=tmp_path)
    status = json.loads((sweep / "0" / "status.json").read_text())
    assert status["state"] == "finished" and status["global_step"] == 256
