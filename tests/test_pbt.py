"""Population Based Training (rlexp.pbt, the ``pbt`` hook, conf/sweep/pbt.yaml).

Unit tests: explore, the quantile rule, the choice of a source, snapshots out of pruning's reach,
a dead member dropped after the sync timeout, exploit's full-state copy (in process). End to end
(``python train.py -m +sweep=pbt`` on InvertedPendulum, 2 members side by side through the joblib
launcher): the sync mode's history is the same for the same seeds; a member killed after an
exploit resumes with its own hyperparameters (Ray #62173); pruning keeps what siblings copy; the
config errors. On the real SLURM cluster (marked ``slurm``): a population as an array.
"""

from __future__ import annotations

import hashlib
import json
import logging
import time
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from test_slurm import cluster  # noqa: F401 (the fixture: a cluster that answers)

from conftest import REPO, TINY, compose, rlexp_cli, run_train

#: A population of 2 on InvertedPendulum: 16 iterations of 256 steps, a ready point every 1024.
#: keep_last=3 (not the default): the sources live in pbt/, out of checkpoints/' pruning.
POP = [
    "+sweep=pbt",
    "env=inverted_pendulum",
    "seed=0,1",
    "hooks.pbt.params.population_size=2",
    "hooks.pbt.params.ready_every=1024",
    "hooks.pbt.params.perturb_factors=[0.5,1.5]",
    "hooks.pbt.params.resample_probability=0.4",
    "hooks.pbt.params.hyperparameters={lr:{low:1e-4,high:2e-3,log:true},clip_epsilon:{low:0.05,high:0.25}}",
    "trainer.frames_per_batch=256",
    "trainer.eval_every=0",
    "trainer.keep_last=3",
    "algorithm.num_epochs=1",
    "logger=none",
]
#: Where every member starts (PPO's defaults; Hydra merges the override's ranges into the yaml's, so
#: entropy_coeff is tuned too, from 0: only a resample moves it).
CONFIG_HPS = {"lr": 3e-4, "entropy_coeff": 0.0, "clip_epsilon": 0.2}


def lineage(job: Path) -> list[dict]:
    return [json.loads(x) for x in (job / "pbt" / "lineage.jsonl").read_text().splitlines()]


def ready(job: Path) -> list[dict]:
    rows = [json.loads(x) for x in (job / "pbt" / "ready.jsonl").read_text().splitlines()]
    return [{k: v for k, v in r.items() if k != "time"} for r in rows]


def exploits(sweep: Path) -> list[dict]:
    return [r for job in ("0", "1") for r in lineage(sweep / job) if r["event"] == "exploit"]


def ckpt_hps(job: Path, step: int) -> dict[str, float]:
    path = next((job / "checkpoints").glob(f"*_step_{step:09d}.pt"))
    return torch.load(path, weights_only=True)["algorithm"]["hyperparameters"]


# -- explore and select ------------------------------------------------------------------------------
def _cfg(**kw):
    from rlexp.pbt.config import PBTConfig

    params = {
        "hyperparameters": {
            "lr": {"low": 1e-4, "high": 2e-3, "log": True},
            "clip_epsilon": {"low": 0.05, "high": 0.25},
        },
        "perturb_factors": [0.5, 1.5],
        "resample_probability": 0.4,
        **kw,
    }
    return PBTConfig.from_params(params)


def test_explore_changes_only_the_tuned_hyperparameters_within_their_bounds():
    from rlexp.pbt.population import explore

    cfg = _cfg()
    values = {"lr": 1.9e-3, "clip_epsilon": 0.2, "entropy_coeff": 0.007, "max_grad_norm": 0.5}
    rng = np.random.default_rng(3)
    seen = set()
    for _ in range(300):
        new, how = explore(values, cfg, rng)
        assert new["entropy_coeff"] == 0.007 and new["max_grad_norm"] == 0.5  # not tuned
        assert 1e-4 <= new["lr"] <= 2e-3 and 0.05 <= new["clip_epsilon"] <= 0.25
        for name in ("lr", "clip_epsilon"):
            seen.add(how[name])
            if how[name] == "x0.5":
                assert new[name] == values[name] * 0.5
            if how[name] == "x1.5":  # 1.9e-3 * 1.5 and 0.2 * 1.5 are past the bounds: clipped
                assert new[name] == {"lr": 2e-3, "clip_epsilon": 0.25}[name]
    assert seen == {"x0.5", "x1.5", "resampled"}


def test_quantiles_follow_rays_rule():
    from rlexp.pbt.population import quantiles

    names = [str(i) for i in range(10)]
    assert quantiles(names[:4], 0.25) == (["0"], ["3"])
    assert quantiles(names[:2], 0.25) == (["0"], ["1"])
    assert quantiles(names[:1], 0.5) == ([], [])
    assert quantiles(names, 0.3) == (["0", "1", "2"], ["7", "8", "9"])
    assert quantiles(names[:5], 0.5) == (["0", "1"], ["3", "4"])  # ceil(2.5) = 3, at most 5 // 2


def test_a_source_is_a_better_top_member_with_a_snapshot():
    from rlexp.pbt.population import Ready, choose_source

    cfg = _cfg(quantile=0.25)

    def rec(name, score):
        return Ready(name, 1024, 1, score, "ready_step_000001024.pt", {})

    rng = np.random.default_rng(0)
    others = {n: (Path(n), rec(n, s)) for n, s in (("a", 5.0), ("b", 9.0), ("c", None))}
    assert choose_source(rec("me", 1.0), others, cfg, rng)[1].member == "b"
    assert choose_source(rec("me", 6.0), others, cfg, rng) is None  # not in the bottom
    assert choose_source(rec("me", None), others, cfg, rng) is None  # no score yet
    # Nobody better than the bottom member: nothing copied (never the worst)
    tied = {n: (Path(n), rec(n, 1.0)) for n in ("a", "b", "d")}
    assert choose_source(rec("me", 1.0), tied, cfg, rng) is None
    assert choose_source(rec("me", 8.5), others, _cfg(min_improvement=1.0), rng) is None


# -- snapshots and pruning ---------------------------------------------------------------------------
def test_pruning_never_removes_a_source_in_use(tmp_path):
    from rlexp.checkpoints.files import prune_checkpoints
    from rlexp.pbt.population import Ready, publish, read_ready, ready_name, take

    source = tmp_path / "sweep" / "0"
    ckpts = source / "checkpoints"
    ckpts.mkdir(parents=True)
    digests = {}
    for gen in (1, 2, 3, 4):
        step = 1000 * gen
        path = ckpts / f"x_step_{step:09d}.pt"
        path.write_bytes(f"state at {step}".encode() * 100)
        digests[step] = hashlib.sha256(path.read_bytes()).hexdigest()
        publish(source, path, Ready("0", step, gen, float(gen), ready_name(step), {}), keep=2)
        prune_checkpoints(ckpts, keep_last=1, newest=path)
        if gen == 2:  # a sibling takes generation 2's snapshot
            incoming = tmp_path / "sweep" / "1" / "pbt" / "incoming.pt"
            incoming.parent.mkdir(parents=True)
            assert take(source, read_ready(source)[-1], incoming)
    # The source pruned its step-2000 checkpoint and snapshot; the taken bytes are intact.
    assert sorted(p.name for p in ckpts.iterdir()) == ["x_step_000004000.pt"]
    assert sorted(p.name for p in (source / "pbt").glob("ready_step_*")) == [
        "ready_step_000003000.pt",
        "ready_step_000004000.pt",
    ]
    assert hashlib.sha256(incoming.read_bytes()).hexdigest() == digests[2000]
    assert [r.step for r in read_ready(source)] == [1000, 2000, 3000, 4000]
    # A record whose snapshot is gone is not taken (the hook then tries the member's newest).
    assert not take(source, read_ready(source)[0], tmp_path / "other.pt")


def test_a_dead_member_is_dropped_after_the_sync_timeout(tmp_path, caplog, monkeypatch):
    import types

    import rlexp.hooks.pbt as pbt_hook
    from rlexp.hooks.base import HookControl, HookState
    from rlexp.hooks.pbt import PopulationBasedTraining
    from rlexp.pbt import population
    from rlexp.pbt.population import Ready, publish, ready_name

    sweep = tmp_path / "sweep"
    me, dead = sweep / "0", sweep / "1"
    (me / "checkpoints").mkdir(parents=True)
    (dead / "checkpoints").mkdir(parents=True)
    old = dead / "checkpoints" / "x_step_000000512.pt"
    old.write_bytes(b"x")
    publish(dead, old, Ready("1", 512, 1, 3.0, ready_name(512), {"lr": 3e-4}), keep=2)
    ckpt = me / "checkpoints" / "x_step_000001024.pt"
    ckpt.write_bytes(b"y")
    hook = PopulationBasedTraining(
        population_size=3, ready_every=512, mode="sync", sync_timeout_s=1.5,
        hyperparameters={"lr": {"low": 1e-4, "high": 1e-3}},
    )  # fmt: skip
    state = HookState(
        point="checkpoint", global_step=1024, iteration=4, total_steps=4096, run_dir=me,
        metrics={"train/episode_return": 1.0}, hyperparameters={"lr": 3e-4}, checkpoint=ckpt,
    )  # fmt: skip
    control = HookControl({"lr": 3e-4})
    # A fake clock that each poll's sleep moves on: the bound is checked on the clock the hook
    # reads, not on how fast this machine runs (no wall-clock assertion).
    clock = {"now": 50.0}
    sleeps: list[float] = []

    def sleep(s: float) -> None:
        sleeps.append(s)
        clock["now"] += s

    now = types.SimpleNamespace(monotonic=lambda: clock["now"], sleep=sleep, time=time.time)
    monkeypatch.setattr(population, "time", now)
    monkeypatch.setattr(pbt_hook, "time", now)
    with caplog.at_level(logging.INFO, logger="rlexp.hooks.pbt"):
        hook(state, control)
    # 0.2 s polls until 1.5 s have passed: given up at the first poll at or past the bound
    assert set(sleeps) == {0.2} and 1.5 <= clock["now"] - 50.0 < 1.7 + 1e-9, sleeps
    line = next(r.getMessage() for r in caplog.records if "dropped" in r.getMessage())
    assert line.startswith("[pbt] generation 2 (step 1024): dropped 1 (at step 512), a member ")
    assert "never seen after waiting 2 s (hooks.pbt.params.sync_timeout_s=1.5)" in line
    assert line.endswith("going on with 1 of 3 members")
    assert control.decisions.empty()  # alone: nothing to copy
    assert [r["step"] for r in ready(me)] == [1024] and hook.last_ready == 1024


# -- exploit: the full state, in process ---------------------------------------------------------------
def _trainer(run_dir: Path, seed: int):
    from rlexp.config.validate import to_dict, to_root_config
    from rlexp.run.metrics import MetricLogger
    from rlexp.training.build import build

    config = to_root_config(compose([*TINY, f"seed={seed}", "trainer.eval_every=0",
                                     "algorithm.num_epochs=1", "+hooks.s.func=stop_at",
                                     "+hooks.s.params.threshold=1e9"]))  # fmt: skip
    run_dir.mkdir(parents=True)
    objects = build(config, run_dir, "cpu", 1024)
    return objects.trainer(MetricLogger([]), to_dict(config), {})


def test_exploit_copies_the_full_training_state_then_the_member_diverges(tmp_path):
    from rlexp.checkpoints.files import save_checkpoint

    source, member = _trainer(tmp_path / "0", seed=7), _trainer(tmp_path / "1", seed=8)
    try:
        source.train(512)
        member.train(256)
        member.algorithm.set_hyperparameter("clip_epsilon", 0.13)
        path = save_checkpoint(tmp_path / "src.pt", source.state_dict())
        returns_before = member.algorithm.reward_normalizer.returns.clone()
        member.hooks.control.load_state(path)
        member.hooks.control.set("lr", 7e-4)  # explore, applied after the load
        member._apply_hook_decisions()
        src = source.policy.state_dict()
        for key, value in member.policy.state_dict().items():  # weights and obs normaliser
            assert torch.equal(value, src[key]), key
        opt, src_opt = (
            member.algorithm.optimizer.state_dict(),
            source.algorithm.optimizer.state_dict(),
        )
        for i, st in src_opt["state"].items():
            assert torch.equal(opt["state"][i]["exp_avg"], st["exp_avg"])
        rn, src_rn = member.algorithm.reward_normalizer, source.algorithm.reward_normalizer
        assert torch.equal(rn.var, src_rn.var) and torch.equal(rn.count, src_rn.count)
        # Its own: step, updates (schedules follow them), running returns of its own envs.
        assert member.global_step == 256 and member.algorithm.iteration == 1
        assert torch.equal(rn.returns, returns_before)
        # The source's hyperparameters (0.2, not the member's 0.13), then the explored lr.
        assert member.algorithm.hyperparameters()["clip_epsilon"] == 0.2
        assert member.algorithm.hyperparameters()["lr"] == 7e-4
        member.train(512)
        assert member.global_step == 512
        after = member.policy.state_dict()
        assert any(not torch.equal(after[k], src[k]) for k in src)  # diverged by its own updates
    finally:
        source.close()
        member.close()


# -- end to end ----------------------------------------------------------------------------------------
def _sweep(tmp_path: Path, name: str, extra: list[str], **kw):
    sweep = tmp_path / name
    proc = run_train(["-m", *POP, *extra, f"hydra.sweep.dir={sweep}"], tmp_path, timeout=400, **kw)
    return sweep, proc


def test_sync_population_on_joblib_is_the_same_for_the_same_seeds(tmp_path):
    sync = ["hooks.pbt.params.mode=sync", "trainer.total_frames=4096"]
    a, proc = _sweep(tmp_path, "a", sync)
    b, _ = _sweep(tmp_path, "b", sync)
    out = proc.stdout + proc.stderr
    assert "PBT population of 2: hydra.launcher.n_jobs 1 -> 2" not in out  # local: n_jobs=2 already
    assert f"sweep {a}: 2 of 2 jobs finished" in out
    for job in ("0", "1"):
        assert lineage(a / job) == lineage(b / job)
        assert ready(a / job) == ready(b / job)
        assert [r["step"] for r in ready(a / job)] == [1024, 2048, 3072]
    done = exploits(a)
    assert done, "no member exploited: the test shows nothing"
    for rec in done:
        # a sibling's snapshot of the same generation, copied then explored within bounds
        assert rec["source_step"] == rec["step"] and rec["source_score"] > rec["score"]
        assert 1e-4 <= rec["new"]["lr"] <= 2e-3 and 0.05 <= rec["new"]["clip_epsilon"] <= 0.25
        assert set(rec["new"]) == set(CONFIG_HPS) and 0 <= rec["new"]["entropy_coeff"] <= 0.01
        source = ready(a / rec["source"])
        copied = next(r for r in source if r["step"] == rec["source_step"])
        assert rec["copied"] == {k: copied["hyperparameters"][k] for k in rec["copied"]}
        job = a / rec["member"]
        next_step = rec["step"] + 1024
        if next_step < 4096:  # the next checkpoint holds the explored values, not the copied ones
            assert {k: ckpt_hps(job, next_step)[k] for k in rec["new"]} == rec["new"]
    # What the last exploit loaded is the source's checkpoint of that step; the member's
    # parameters at its final checkpoint differ from it (its own updates since).
    rec = done[-1]
    snap = torch.load(a / rec["member"] / "pbt" / "incoming.pt", weights_only=True)
    assert snap["global_step"] == rec["source_step"]
    final = torch.load(next((a / rec["member"] / "checkpoints").glob("*_step_000004096.pt")),
                       weights_only=True)  # fmt: skip
    assert any(not torch.equal(final["policy"][k], v) for k, v in snap["policy"].items())


def test_async_population_keeps_sources_past_pruning_and_reports(tmp_path):
    sweep, proc = _sweep(
        tmp_path,
        "s",
        ["trainer.total_frames=4096", "trainer.keep_last=1", "hooks.pbt.params.keep_ready=2"],
    )
    out = proc.stdout + proc.stderr
    assert "snapshot is gone" not in out and "cannot be used" not in out
    for job in ("0", "1"):
        assert len(list((sweep / job / "checkpoints").glob("*_step_*.pt"))) == 1
        assert len(list((sweep / job / "pbt").glob("ready_step_*.pt"))) == 2
        assert lineage(sweep / job)[0] == {
            "event": "start", "step": 0, "member": job, "hyperparameters": CONFIG_HPS,
        }  # fmt: skip
    # rlexp report: the best member (highest final score), its lineage and schedule, the figure
    code, md, err = rlexp_cli("report", sweep, "--no-plot")
    assert code == 0, err
    best = max(("0", "1"), key=lambda j: (ready(sweep / j)[-1]["score"], j))
    assert "## Population Based Training" in md and "2 members, " in md
    assert f"Best member: **{best}** " in md
    current = {}
    for job in ("0", "1"):  # what each member's lineage last set
        recs = lineage(sweep / job)
        current[job] = recs[-1].get("new", recs[-1].get("hyperparameters"))
    code, out, _ = rlexp_cli("runs", sweep)
    assert code == 0 and "PBT members' current hyperparameters:" in out
    for job in ("0", "1"):
        shown = ", ".join(f"{k}={v:.4g}" for k, v in current[job].items())
        assert f"{job}: {shown}" in out
    # rlexp pbt export: the member's own schedule, each value from the step it was set
    target = tmp_path / "conf" / "hooks" / "replay.yaml"
    assert rlexp_cli("pbt", "export", sweep, "--member", "1", "-o", target)[0] == 0
    exported = yaml.safe_load(target.read_text())
    for name in CONFIG_HPS:
        points = [[0, CONFIG_HPS[name]]]
        for rec in lineage(sweep / "1")[1:]:
            if rec["new"][name] != points[-1][1]:
                points.append([rec["step"], rec["new"][name]])
        assert exported[f"pbt_{name}"] == {"func": "piecewise",
                                           "params": {"name": name, "points": points}}  # fmt: skip
    assert rlexp_cli("pbt", "export", sweep, "--member", "9")[0] == 2


def test_piecewise_replays_a_schedule_by_env_step():
    from rlexp.hooks.base import HookControl, HookState, check_hook
    from rlexp.hooks.builtin import Piecewise

    hook = Piecewise("clip_epsilon", [[0, 0.25], [1000, 0.1], [3000, 0.3]])
    for step, current, expect in ((0, 0.2, 0.25), (999, 0.25, None), (1000, 0.25, 0.1),
                                  (2999, 0.1, None), (5000, 0.1, 0.3)):  # fmt: skip
        control = HookControl({"clip_epsilon": current})
        state = HookState("rollout_end", step, 0, 8000, Path("."),
                          hyperparameters={"clip_epsilon": current})  # fmt: skip
        hook(state, control)
        assert control.decisions.set == ({} if expect is None else {"clip_epsilon": expect})
    with pytest.raises(ValueError, match=r"hooks.r.params.points\[1\]\[0\]=0 must be above"):
        check_hook("piecewise", {"name": "lr", "points": [[5, 1e-4], [0, 2e-4]]}, "hooks.r")


def test_config_errors_are_one_line_with_exit_2(tmp_path):
    cases = [
        (["-m", *POP, "hydra/launcher=basic"],
         "config error: hydra/launcher=basic (hydra._internal.core_plugins.basic_launcher."
         "BasicLauncher) runs a sweep's jobs one after another; a PBT population (hooks.pbt.params "
         "in conf/sweep/pbt.yaml) needs its 2 members side by side"),
        (["-m", *POP, "seed=0,1,2"],
         "config error: hooks.pbt.params.population_size=2 (conf/sweep/pbt.yaml) but the sweep "
         "launches 3 jobs"),
        (["-m", *POP, "+hooks.pbt.params.hyperparameters.kl_coeff={low:0,high:1}"],
         "config error: hooks.pbt.params.hyperparameters.kl_coeff is not a mutable hyperparameter "
         "of algorithm=ppo"),
        (["-m", *POP, "hooks.pbt.params.quantile=0.7"],
         "config error: hooks.pbt.params.quantile=0.7 must be a finite number"),
        ([p for p in POP if p != "seed=0,1"],
         "config error: hooks.pbt: Population Based Training runs a population as a sweep: add -m"),
    ]  # fmt: skip
    for args, start in cases:
        proc = run_train(args, tmp_path, check=False, timeout=120)
        lines = proc.stderr.strip().splitlines()
        assert proc.returncode == 2 and len(lines) == 1, (args, proc.stderr)
        assert lines[0].startswith(start), (lines[0], start)
    assert not (tmp_path / "multirun").exists()


def test_killed_member_resumes_with_its_own_hyperparameters(tmp_path, children):
    """Ray #62173: a member killed after an exploit resumes with the explored values and its
    lineage, not the sweep's initial values; the same command continues the population."""
    import os
    import signal
    import sys

    from rlexp.checkpoints.files import latest_good_checkpoint

    sweep = tmp_path / "k"
    args = ["-m", *POP, "hooks.pbt.params.mode=sync", "trainer.total_frames=16384",
            "trainer.keep_last=0", f"hydra.sweep.dir={sweep}"]  # fmt: skip
    env = {"PYTHONPATH": str(REPO / "src")}
    proc = children.train(args, tmp_path, tmp_path / "first.txt", env_extra=env)

    def exploited_and_saved() -> tuple[str, dict] | None:
        for job in ("0", "1"):
            try:
                recs = [r for r in lineage(sweep / job) if r["event"] == "exploit"]
            except (OSError, ValueError):
                continue
            saved = sorted((sweep / job / "checkpoints").glob("*_step_*.pt"))
            if recs and saved and int(saved[-1].stem.rsplit("_", 1)[1]) > recs[-1]["step"]:
                return job, recs[-1]
        return None

    deadline = time.monotonic() + 300
    found = None
    while found is None and proc.poll() is None and time.monotonic() < deadline:
        found = exploited_and_saved()
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)  # the whole sweep: no checkpoint at a safe point
    proc.wait(30)
    assert found is not None, (tmp_path / "first.txt").read_text()[-3000:]
    job, _ = found
    ckpt = latest_good_checkpoint(sweep / job / "checkpoints")
    resume_step = int(ckpt["global_step"])
    assert resume_step < 16384, "the member finished before the kill"
    held = {k: ckpt["algorithm"]["hyperparameters"][k] for k in CONFIG_HPS}
    before = [r for r in lineage(sweep / job) if r["step"] < resume_step]  # in the checkpoint
    kept = [r for r in before if r["event"] == "exploit"]
    assert held == kept[-1]["new"] != CONFIG_HPS  # what the member resumes from: its explored ones
    run = subprocess_run(sys.executable, args, tmp_path)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    log = (sweep / job / "train.log").read_text()
    assert f"[resume] continuing from {ckpt['path']} at step {resume_step}" in log
    # The checkpoint was written at a ready point, before its decision: the resumed member takes
    # that decision first, from the values it resumed with ("old"); the next checkpoint holds what
    # it decided. The lineage is the checkpoint's, then what followed.
    at = [r for r in lineage(sweep / job) if r["step"] == resume_step]
    then = at[-1]["new"] if at else held
    if at:
        assert at[-1]["old"] == held
    assert {k: ckpt_hps(sweep / job, resume_step + 1024)[k] for k in CONFIG_HPS} == then
    assert [r for r in lineage(sweep / job) if r["step"] < resume_step] == before
    for name in ("0", "1"):
        status = json.loads((sweep / name / "status.json").read_text())
        assert (status["state"], status["global_step"]) == ("finished", 16384)


def subprocess_run(python: str, args: list[str], cwd: Path):
    import os
    import subprocess

    env = {**os.environ, "PYTHONPATH": str(REPO / "src")}
    return subprocess.run([python, str(REPO / "train.py"), *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=400)  # fmt: skip


@pytest.mark.slurm
def test_sync_population_on_the_slurm_cluster(cluster, tmp_path, children):  # noqa: F811
    """The members as SLURM array tasks, side by side on the test cluster: each generation has
    both members' ready points, and the decisions are the joblib launcher's (same seeds)."""
    from test_slurm import SLURM, finish, sweep

    args = [*POP, "hooks.pbt.params.mode=sync", "trainer.total_frames=3072"]
    slurm = tmp_path / "slurm"
    out = finish(sweep(children, [*SLURM, *args, f"hydra.sweep.dir={slurm}"], tmp_path), 600)
    assert "Submitit 'slurm' sweep output dir" in out
    local, _ = _sweep(tmp_path, "local", args[len(POP) :])  # the joblib launcher's history
    for job in ("0", "1"):
        status = json.loads((slurm / job / "status.json").read_text())
        assert (status["state"], status["global_step"]) == ("finished", 3072)
        assert [r["step"] for r in ready(slurm / job)] == [1024, 2048]
        assert lineage(slurm / job) == lineage(local / job)


@pytest.mark.parametrize("state", ["failed", "stopped_early", "finished"])
def test_sync_does_not_wait_for_a_member_that_has_ended(tmp_path, monkeypatch, state):
    """A member whose status.json says it is not training (a SIGKILLed job the local launcher
    recorded ``failed``, one a hook stopped, one finished) is dropped at once, named with its
    state; a running or an interrupted member behind (it may be resumed) is still waited for until
    the bound (#43 item 4, PBT)."""
    import types

    from rlexp.pbt import population
    from rlexp.pbt.population import Ready, publish, ready_name

    sweep = tmp_path / "sweep"
    for name in ("0", "1", "2", "3"):
        (sweep / name / "checkpoints").mkdir(parents=True)

    def ready(name: str, step: int, generation: int) -> None:
        ckpt = sweep / name / "checkpoints" / f"x_step_{step:09d}.pt"
        ckpt.write_bytes(b"x")
        publish(
            sweep / name, ckpt, Ready(name, step, generation, 1.0, ready_name(step), {}), keep=2
        )

    def status(name: str, value: str) -> None:
        (sweep / name / "status.json").write_text(json.dumps({"state": value, "global_step": 512}))

    ready("1", 1024, 2)  # reached generation 2
    ready("2", 512, 1)  # behind, at generation 1, and ended
    status("2", state)
    ready("3", 512, 1)  # behind, at generation 1, interrupted: a requeued member comes back
    status("3", "interrupted")
    clock = {"now": 0.0}
    sleeps: list[float] = []

    def sleep(s: float) -> None:
        sleeps.append(s)
        clock["now"] += s

    monkeypatch.setattr(
        population, "time", types.SimpleNamespace(monotonic=lambda: clock["now"], sleep=sleep)
    )
    names = ["0", "1", "2", "3"]
    # member 3 may come back: waited for until the bound (0.2 s polls up to 2 s), member 2 never waited for
    reached, dropped = population.wait_for_generation(sweep / "0", names, 2, timeout_s=2.0)
    assert sorted(reached) == ["1"] and dropped == [f"2 ({state})", "3 (at step 512)"], dropped
    assert set(sleeps) == {0.2} and 2.0 <= sum(sleeps) < 2.2 + 1e-9, sleeps
    # member 3 reaches the point: nothing left to wait for, no poll at all
    sleeps.clear()
    ready("3", 1024, 2)
    reached, dropped = population.wait_for_generation(sweep / "0", names, 2, timeout_s=600.0)
    assert sorted(reached) == ["1", "3"] and dropped == [f"2 ({state})"] and sleeps == [], sleeps
