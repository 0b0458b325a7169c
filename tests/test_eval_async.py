"""Evaluation off the critical path (issue #18, ``trainer.eval_async``): a worker process evaluates
policy snapshots while training goes on, and a run ends with exactly what an in-process run ends
with: the same eval rows, best.pt and checkpoints; a round in flight at a stop is evaluated first on
resume; at most one round is in flight; ``auto`` is decided once; ``eval_every=0`` evaluates
nothing; ``eval/success_rate`` exists only for tasks that define success."""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from conftest import CONF_DIR, REPO, compose
from rlexp.checkpoints.files import load_checkpoint, step_checkpoints
from rlexp.config.validate import ConfigError, to_root_config

#: Six iterations of 256 steps, an eval round after each (3 episodes on 2 copies: uneven quotas), a
#: checkpoint every second one: rounds whose checkpoint waits for them, and rounds without.
RUN = [
    "env=inverted_pendulum",
    "trainer.total_frames=1536",
    "trainer.frames_per_batch=256",
    "trainer.eval_every=256",
    "trainer.eval_episodes=3",
    "env.num_eval_envs=2",
    "trainer.save_every=512",
    "trainer.keep_last=0",
    "algorithm.num_epochs=1",
    "logger=none",
    "logger.jsonl=true",
    "trainer.progress=false",
]


def _config(*extra: str):
    return to_root_config(compose([*RUN, *extra]))


def _train(config, run_dir: Path) -> None:
    from rlexp.app import train

    threads = torch.get_num_threads()
    try:
        train(config, run_dir)
    finally:
        torch.set_num_threads(threads)


def _eval_rows(run_dir: Path) -> list[dict]:
    rows = [json.loads(x) for x in (run_dir / "metrics.jsonl").read_text().splitlines()]
    return [
        {k: v for k, v in r.items() if k == "step" or k.startswith("eval/")}
        for r in rows
        if "eval/episode_return" in r
    ]


def _same(a, b, where: str) -> None:
    """Equal through dicts, lists and tensors; the config's trainer.eval_async may differ, and
    ``path`` (where load_checkpoint read the file from)."""
    if isinstance(a, dict):
        skip = {"path"} if "/" not in where else set()
        skip |= {"eval_async"} if where.endswith("/config/trainer") else set()
        assert set(a) - skip == set(b) - skip, where
        for k in set(a) - skip:
            _same(a[k], b[k], f"{where}/{k}")
    elif isinstance(a, list | tuple):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            _same(x, y, f"{where}[{i}]")
    elif isinstance(a, torch.Tensor):
        assert isinstance(b, torch.Tensor) and torch.equal(a, b), where
    else:
        assert a == b, where


def _assert_same_run(sync_dir: Path, async_dir: Path) -> None:
    rows = _eval_rows(sync_dir)
    assert [r["step"] for r in rows] == [256, 512, 768, 1024, 1280, 1536]
    assert len({r["eval/episode_return"] for r in rows}) > 1, "every round alike: vacuous"
    assert _eval_rows(async_dir) == rows
    a_best, b_best = (load_checkpoint(d / "checkpoints" / "best.pt") for d in (sync_dir, async_dir))
    _same(a_best, b_best, "best.pt")
    assert a_best["global_step"] == max(rows, key=lambda r: r["eval/episode_return"])["step"]
    a_ckpts, b_ckpts = (step_checkpoints(d / "checkpoints") for d in (sync_dir, async_dir))
    assert [p.name for p in a_ckpts] == [p.name for p in b_ckpts] and len(a_ckpts) == 3
    for a, b in zip(a_ckpts, b_ckpts, strict=True):
        _same(load_checkpoint(a), load_checkpoint(b), a.name)
    for d in (sync_dir, async_dir):
        assert json.loads((d / "status.json").read_text())["final_eval"] == {
            k: v for k, v in rows[-1].items() if k != "step"
        }


@pytest.fixture(scope="module")
def sync_run(tmp_path_factory) -> Path:
    run_dir = tmp_path_factory.mktemp("sync") / "run"
    _train(_config("trainer.eval_async=false"), run_dir)
    return run_dir


# -- (a) the same run, sync and async: identical eval rows, best.pt, checkpoints -------------------
def test_async_evaluation_gives_exactly_the_sync_runs_results(sync_run, tmp_path, monkeypatch):
    from rlexp.training.eval_worker import EvalWorker

    calls: list[tuple[str, int]] = []
    real_submit, real_result = EvalWorker.submit, EvalWorker.result

    def submit(self, round_):
        calls.append(("submit", round_.step))
        return real_submit(self, round_)

    def result(self):
        done, metrics = real_result(self)
        calls.append(("result", done.step))
        return done, metrics

    monkeypatch.setattr(EvalWorker, "submit", submit)
    monkeypatch.setattr(EvalWorker, "result", result)
    run_dir = tmp_path / "run"
    _train(_config("trainer.eval_async=true"), run_dir)
    _assert_same_run(sync_run, run_dir)
    # (c) at most one round in flight: every result before the next submit, none left over.
    steps = [256, 512, 768, 1024, 1280, 1536]
    assert calls == [(kind, s) for s in steps for kind in ("submit", "result")]
    assert "eval/success_rate" not in _eval_rows(run_dir)[0], "InvertedPendulum has no success"


def test_a_recurrent_run_s_async_rounds_are_its_sync_rounds(tmp_path):
    """An LSTM policy (#48): the worker builds the recurrent policy, carries and resets its state
    as in-process rounds do; eval rows, best.pt and checkpoints equal."""
    memory = [
        *(x for x in RUN if not x.startswith("env=")),
        "env=hopper",  # real-valued returns: rounds differ
        "env.max_episode_steps=60",
        "env.num_eval_envs=2",
        "policy.memory.type=lstm",
        "policy.memory.hidden_size=16",
        "policy.memory.num_layers=2",
        "algorithm.sequence_length=16",
        "trainer.total_frames=768",
        "trainer.save_every=768",
    ]
    sync_dir, async_dir = tmp_path / "sync", tmp_path / "async"
    for run_dir, mode in ((sync_dir, "false"), (async_dir, "true")):
        _train(to_root_config(compose([*memory, f"trainer.eval_async={mode}"])), run_dir)
    rows = _eval_rows(sync_dir)
    assert [r["step"] for r in rows] == [256, 512, 768]
    assert len({r["eval/episode_return"] for r in rows}) > 1, "every round alike: vacuous"
    assert _eval_rows(async_dir) == rows
    for name in ("best.pt", "Hopper-v5_ppo_step_000000768.pt"):
        a, b = (load_checkpoint(d / "checkpoints" / name) for d in (sync_dir, async_dir))
        assert "actor_core.rnn.weight_hh_l1" in a["policy"]
        _same(a, b, name)


# -- (b) a stop while a round is in flight: the resume evaluates it first ---------------------------
def test_a_round_in_flight_at_a_stop_is_evaluated_first_on_resume(sync_run, tmp_path, monkeypatch):
    from rlexp.app import RunEnded
    from rlexp.training.trainer import Trainer

    real_evaluate = Trainer.evaluate

    def evaluate_then_stop(self):  # the stop arrives while the round of step 1024 is out
        real_evaluate(self)
        if self.global_step == 1024:
            self.request_stop("stop injected by the test")

    monkeypatch.setattr(Trainer, "evaluate", evaluate_then_stop)
    run_dir = tmp_path / "run"
    with pytest.raises(RunEnded):
        _train(_config("trainer.eval_async=true"), run_dir)
    stopped = load_checkpoint(run_dir / "checkpoints" / "InvertedPendulum-v5_ppo_step_000001024.pt")
    pending = stopped["eval_in_flight"]
    assert pending["step"] == 1024 and pending["save"], "the round and its checkpoint are pending"
    assert stopped["last_eval"] == {k: v for k, v in _eval_rows(sync_run)[2].items() if k != "step"}
    assert [r["step"] for r in _eval_rows(run_dir)] == [256, 512, 768]
    monkeypatch.setattr(Trainer, "evaluate", real_evaluate)

    _train(_config("trainer.eval_async=true"), run_dir)
    _assert_same_run(sync_run, run_dir)  # checkpoint 1024 rewritten once its round came in


def test_a_sync_resume_evaluates_an_async_runs_round_in_flight_in_process(
    sync_run, tmp_path, monkeypatch
):
    """The resumed run may decide eval_async differently (another machine, auto): the pending
    round then runs in-process, on a copy of the policy with the snapshot's weights."""
    from rlexp.app import RunEnded
    from rlexp.training.trainer import Trainer

    real_evaluate = Trainer.evaluate

    def evaluate_then_stop(self):
        real_evaluate(self)
        if self.global_step == 768:
            self.request_stop("stop injected by the test")

    monkeypatch.setattr(Trainer, "evaluate", evaluate_then_stop)
    run_dir = tmp_path / "run"
    with pytest.raises(RunEnded):
        _train(_config("trainer.eval_async=true"), run_dir)
    monkeypatch.setattr(Trainer, "evaluate", real_evaluate)
    _train(_config("trainer.eval_async=false"), run_dir)
    assert _eval_rows(run_dir) == _eval_rows(sync_run)
    _same(
        load_checkpoint(run_dir / "checkpoints" / "best.pt"),
        load_checkpoint(sync_run / "checkpoints" / "best.pt"),
        "best.pt",
    )


def test_a_hook_stopping_on_eval_metrics_still_stops_one_iteration_later(tmp_path):
    """stop_at on eval/episode_return (reached at the first round): in sync mode the run stops at
    the round's step; async, the round's result arrives after the next update, so one iteration
    later, and the round of that step is taken in before the final checkpoint."""
    stop = ["+hooks.stop.func=stop_at", "+hooks.stop.params.threshold=-1e9"]
    ends = {}
    for mode in ("false", "true"):
        run_dir = tmp_path / mode
        _train(_config(*stop, f"trainer.eval_async={mode}"), run_dir)
        status = json.loads((run_dir / "status.json").read_text())
        assert status["state"] == "stopped_early", status
        assert "eval/episode_return=" in status["reason"] and "at step 256" in status["reason"]
        ends[mode] = (status["global_step"], [r["step"] for r in _eval_rows(run_dir)])
    assert ends == {"false": (256, [256]), "true": (512, [256, 512])}


def test_sigterm_with_a_round_in_flight_exits_promptly_and_leaves_no_worker(tmp_path, children):
    run_dir = tmp_path / "run"
    args = [*RUN, "trainer.total_frames=100000000", "trainer.eval_async=true",
            "trainer.save_every=0", f"hydra.run.dir={run_dir}"]  # fmt: skip
    console = tmp_path / "console.txt"
    proc = children.train(args, tmp_path, console)  # its group (the worker too) killed on teardown
    deadline = time.time() + 180
    while "[eval] step=" not in console.read_text() and time.time() < deadline:
        assert proc.poll() is None, console.read_text()
        time.sleep(0.05)
    text = console.read_text()
    worker = int(text.split("eval worker started (pid ")[1].split(")")[0])
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(timeout=60) == 128 + signal.SIGTERM, console.read_text()
    ended = time.time()
    while time.time() < ended + 5 and _alive(worker):
        time.sleep(0.05)
    assert not _alive(worker), "the eval worker outlived the run"
    ckpt = load_checkpoint(step_checkpoints(run_dir / "checkpoints")[-1])
    assert ckpt["eval_in_flight"]["step"] == ckpt["global_step"], "eval every iteration: in flight"
    status = json.loads((run_dir / "status.json").read_text())
    assert status["state"] == "interrupted" and "SIGTERM" in status["reason"]


def _alive(pid: int) -> bool:
    """Running (a zombie waiting for its parent to reap it counts as gone)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


def test_the_worker_dies_with_a_killed_training_process(tmp_path, children):
    """SIGKILL leaves no chance to clean up: the worker follows its parent (PR_SET_PDEATHSIG)."""
    code = (
        "import os, sys, time\n"
        f"sys.path.insert(0, {str(REPO / 'tests')!r})\n"
        "from conftest import compose\n"
        "from rlexp.config.validate import to_root_config\n"
        "from rlexp.training.eval_worker import EvalSetup, EvalWorker\n"
        f"c = to_root_config(compose({RUN!r}))\n"
        "w = EvalWorker(EvalSetup(c.env, c.policy, 1, 1))\n"
        "w.start()\n"
        "print(w.pid, flush=True)\n"
        "time.sleep(600)\n"
    )
    env = {**os.environ, "PYTHONPATH": str(REPO / "src")}
    proc = children.popen(  # the worker is in its group: killed on teardown if it outlived it
        [sys.executable, "-c", code], env=env, stdout=subprocess.PIPE, text=True
    )
    worker = int(proc.stdout.readline())
    time.sleep(1.0)  # the worker is importing or building its env
    proc.kill()
    proc.wait(timeout=30)
    # A worker killed mid-import follows its parent once its imports (torch) are done: seconds on
    # an idle machine, more on a loaded one; an orphan would live on for good.
    deadline = time.time() + 60
    while time.time() < deadline and _alive(worker):
        time.sleep(0.05)
    assert not _alive(worker), "the eval worker outlived its killed parent"


# -- (c) at most one in flight ----------------------------------------------------------------------
def test_a_second_submit_while_a_round_is_in_flight_is_refused():
    from rlexp.training.eval_worker import EvalRound, EvalWorker

    worker = EvalWorker(None)  # type: ignore[arg-type]
    worker.in_flight = EvalRound(256, {})
    with pytest.raises(RuntimeError, match="step 256 is still in flight"):
        worker.submit(EvalRound(512, {}))


# -- (d) eval_every=0: no evaluation at all ---------------------------------------------------------
def test_eval_every_0_builds_no_eval_env_starts_no_worker_and_logs_no_eval(tmp_path, monkeypatch):
    import rlexp.envs.factory as factory
    from rlexp.training.build import build
    from rlexp.training.eval_worker import EvalWorker

    config = _config("trainer.eval_every=0", "trainer.eval_async=true")
    built: list[int] = []
    real_make_env = factory.make_env

    def make_env(cfg, num_envs, seed, *a, **kw):
        built.append(num_envs)
        return real_make_env(cfg, num_envs, seed, *a, **kw)

    monkeypatch.setattr(factory, "make_env", make_env)
    assert build(config, tmp_path / "b", "cpu", 1536).eval_env is None
    assert built == [1], "only the training env"
    monkeypatch.setattr(EvalWorker, "start", lambda self: pytest.fail("a worker was started"))
    run_dir = tmp_path / "run"
    _train(config, run_dir)
    rows = [json.loads(x) for x in (run_dir / "metrics.jsonl").read_text().splitlines()]
    assert rows and not [k for r in rows for k in r if k.startswith("eval/")]
    assert json.loads((run_dir / "status.json").read_text())["final_eval"] == {}
    assert not (run_dir / "checkpoints" / "best.pt").exists()


# -- (e) auto -----------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("overrides", "cpus", "jobs", "on", "why"),
    [
        ([], 2, 1, True, "a spare core: 2 CPUs, 1 job(s) x (1 rank(s) x 1 thread(s) + 1"),
        ([], 1, 1, False, "no spare core"),
        ([], 4, 2, True, "= 4 <= 4"),
        ([], 3, 2, False, "no spare core"),
        (["trainer.torch_threads=2"], 2, 1, False, "no spare core"),
        (["trainer.eval_every=200000"], 8, 1, False, "5 eval rounds in the budget"),
        (["trainer.eval_every=0"], 8, 1, False, "no evaluation"),
        (["trainer.eval_episodes=0", "trainer.eval_async=true"], 8, 1, False, "no evaluation"),
        (["trainer.eval_async=false"], 8, 1, False, "trainer.eval_async=false"),
        (["trainer.eval_async=true"], 1, 1, True, "trainer.eval_async=true"),
        (["events=eval_video"], 8, 1, False, "events.eval (record_video)"),
        (["hooks=early_stop"], 8, 1, False, "hooks.early_stop act on eval results"),
        (["env=push_cube"], 2, 1, False, "no spare core"),  # the physics pool has the cores
    ],
)
def test_auto_is_on_with_a_spare_core_and_nothing_acting_on_eval_results(
    overrides, cpus, jobs, on, why
):
    from rlexp.training.eval_worker import decide_eval_async

    config = to_root_config(compose(overrides))  # HalfCheetah, 1M steps, eval every 50k: 20 rounds
    total = config.trainer.total_frames
    got, reason = decide_eval_async(config, total, cpus, jobs)
    assert (got, why in reason) == (on, True), reason


def test_the_launchers_jobs_count_and_the_choice_is_logged_once(tmp_path, caplog):
    from rlexp.training.eval_worker import launcher_jobs

    assert [launcher_jobs(n, 8) for n in (None, 2, -1, -2, "x", True)] == [1, 2, 8, 7, 1, 1]
    with caplog.at_level("INFO"):
        _train(_config("trainer.total_frames=256"), tmp_path / "run")
    lines = [r.getMessage() for r in caplog.records if "trainer.eval_async" in r.getMessage()]
    assert lines == ["[eval] trainer.eval_async=auto -> off: 1 eval rounds in the budget (< 10: "
                     "the worker's start-up would not pay off)"]  # fmt: skip


def test_eval_async_true_with_eval_events_is_a_config_error_naming_the_key():
    from rlexp.launch.precheck import precheck

    with pytest.raises(
        ConfigError, match=r"^trainer.eval_async=true: events.eval \(record_video\)"
    ):
        precheck(["events=eval_video", "trainer.eval_async=true"], CONF_DIR)
    with pytest.raises(ConfigError, match="trainer.eval_async='sometimes' must be auto, true or"):
        precheck(["trainer.eval_async=sometimes"], CONF_DIR)
    with pytest.raises(ConfigError, match="trainer.best_metric=eval/success_rate: InvertedPend"):
        precheck(["env=inverted_pendulum", "trainer.best_metric=eval/success_rate"], CONF_DIR)


# -- success only where the task defines it --------------------------------------------------------
@pytest.mark.parametrize(
    ("name", "has_success"), [("hopper", False), ("cart_pole", True), ("push_cube", True)]
)
def test_success_rate_only_for_tasks_that_define_success(name, has_success):
    from rlexp.envs.factory import make_env
    from rlexp.policies.actor_critic import make_policy
    from rlexp.training.evaluation import eval_line, run_episodes

    config = to_root_config(compose([f"env={name}", "env.max_episode_steps=20"]))
    env = make_env(config.env, 2, seed=1)
    policy = make_policy(
        config.policy,
        env.observation_spec["observation"].shape[-1],
        env.action_spec.shape[-1],
        env.action_spec,
    ).sampling_policy(deterministic=True)
    for lean in (True, False):
        env.set_seed(1)
        metrics = run_episodes(env, policy, 3, lean=lean)
        assert ("eval/success_rate" in metrics) == has_success, (lean, metrics)
    assert ("success=" in eval_line(20, metrics, 3)) == has_success
    if env.__class__.__name__ == "NativeEnv":  # a native task without a success rule reports 0s
        env.task_spec = dataclasses.replace(env.task_spec, success=None, terminated=None)
        env.set_seed(1)
        assert "eval/success_rate" not in run_episodes(env, policy, 3)
