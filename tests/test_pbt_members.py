"""A PBT population is exactly its own members, and one bad PBT file costs one warning.

Members are the sweep's jobs (``multirun.yaml``: its ``hydra.sweep.subdir``, ``population_size``
jobs), known by their dirs: a stray in the sweep dir (an earlier sweep's job copied in, a symlinked
run, a run of another env) is never a source, async or sync, and is named once; a real member's
snapshot that does not fit (another env, other policy shapes) is skipped like an unreadable one.
One bad value in a member's ``lineage.jsonl`` / ``ready.jsonl`` leaves that member (or line) out of
``rlexp runs``, ``report`` and ``pbt export`` with one warning, and ``pbt export`` never writes a
hooks file ``train.py`` would refuse. Sweep dirs are laid out by hand (no training but three tiny
checkpoints).
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path

import pytest
import yaml

from conftest import TINY, compose, rlexp_cli

HPS = {"lr": 3e-4, "clip_epsilon": 0.2, "entropy_coeff": 0.0}
PARAMS = {
    "population_size": 2,
    "ready_every": 256,
    "hyperparameters": {"lr": {"low": 1e-4, "high": 2e-3, "log": True},
                        "clip_epsilon": {"low": 0.05, "high": 0.25}},
}  # fmt: skip


@pytest.fixture(scope="module")
def snaps(tmp_path_factory):
    """Checkpoints at step 256 of three tiny runs: the population's own kind, another env
    (Pendulum), the same env with another policy width."""
    from rlexp.config.validate import to_dict, to_root_config
    from rlexp.run.metrics import MetricLogger
    from rlexp.training.build import build

    root = tmp_path_factory.mktemp("snaps")
    out = {}
    for name, extra in (("own", []), ("other_env", ["env=pendulum"]),
                        ("other_width", ["policy.actor.hidden_sizes=[16]"])):  # fmt: skip
        config = to_root_config(
            compose([*TINY, *extra, "trainer.eval_every=0", "algorithm.num_epochs=1"])
        )
        trainer = build(config, root / name, "cpu", 256).trainer(
            MetricLogger([]), to_dict(config), {}
        )
        try:
            trainer.train(256)
        finally:
            trainer.close()
        out[name] = next((root / name / "checkpoints").glob("*_step_000000256.pt"))
    return out


def _multirun(sweep: Path, subdir: str = "${hydra.job.num}", size: int = 2) -> None:
    sweep.mkdir(parents=True, exist_ok=True)
    doc = {"hydra": {"sweep": {"dir": str(sweep), "subdir": subdir}},
           "hooks": {"pbt": {"func": "pbt", "params": {**PARAMS, "population_size": size}}}}  # fmt: skip
    (sweep / "multirun.yaml").write_text(yaml.safe_dump(doc))


def _publish(run: Path, snapshot: Path, score: float, claims: str | None = None, step=256):
    from rlexp.pbt.population import Ready, publish, ready_name

    rec = Ready(claims or run.name, step, step // 256, score, ready_name(step), HPS)
    publish(run, snapshot, rec, keep=2)


def _hook(**kw):
    from rlexp.hooks.pbt import PopulationBasedTraining

    return PopulationBasedTraining(**{**PARAMS, **kw})


def _decide(hook, me: Path, snapshot: Path, score: float = 1.0, step: int = 256):
    """Member ``me`` at its ready point ``step`` (its own checkpoint a copy of ``snapshot``)."""
    from rlexp.hooks.base import HookControl, HookState

    own = me / "checkpoints" / f"m_step_{step:09d}.pt"
    own.parent.mkdir(parents=True, exist_ok=True)
    if not own.exists():
        os.link(snapshot, own)

    def at(point, **kw):
        control = HookControl(HPS)
        hook(HookState(point=point, global_step=step if point != "train_start" else 0,
                       iteration=1, total_steps=4096, run_dir=me, hyperparameters=HPS,
                       metrics={"train/episode_return": score}, **kw), control)  # fmt: skip
        return control.decisions

    if not hook.lineage:
        at("train_start")
    at("log")
    return at("checkpoint", checkpoint=own)


def _exploits(run: Path) -> list[dict]:
    rows = [json.loads(x) for x in (run / "pbt" / "lineage.jsonl").read_text().splitlines()]
    return [r for r in rows if r["event"] == "exploit"]


def _strays(sweep: Path, snaps) -> None:
    """An earlier sweep's job copied in (claiming to be member 1), a job number past the
    population, a symlink to a run elsewhere, a run of another env: all far better than anyone."""
    _publish(sweep / "old", snaps["own"], 100.0, claims="1")
    _publish(sweep / "2", snaps["own"], 200.0)
    elsewhere = sweep.parent / "elsewhere" / "run"
    _publish(elsewhere, snaps["own"], 300.0)
    (sweep / "linked").symlink_to(elsewhere, target_is_directory=True)
    _publish(sweep / "pend", snaps["other_env"], 400.0)


# -- who the members are -----------------------------------------------------------------------
def test_members_are_the_sweeps_jobs_named_by_its_subdir(tmp_path):
    from rlexp.pbt.population import job_names, scan

    a = tmp_path / "a"
    _multirun(a, size=3)
    assert job_names(a, 3) == ["0", "1", "2"]
    b = tmp_path / "b"
    _multirun(b, subdir="member_${hydra.job.num}")
    assert job_names(b, 2) == ["member_0", "member_1"]
    assert job_names(tmp_path / "none", 2) == ["0", "1"]  # no multirun.yaml: Hydra's default
    for name in ("member_0", "member_1", "0", "old"):
        (b / name).mkdir()
    (b / "member_x").symlink_to(b / "member_0")
    (b / "report.md").write_text("a file, not a job")
    members, strays = scan(b, ["member_0", "member_1"])
    assert members == {"member_0": b / "member_0", "member_1": b / "member_1"}
    assert strays == {"0": "not one of the sweep's jobs", "member_x": "a symlink, not a job's "
                      "own dir", "old": "not one of the sweep's jobs"}  # fmt: skip


def test_async_a_stray_is_never_a_source_and_is_named_once(tmp_path, snaps, caplog):
    sweep = tmp_path / "sweep"
    _multirun(sweep)
    _strays(sweep, snaps)
    _publish(sweep / "1", snaps["own"], 5.0)
    hook = _hook()
    with caplog.at_level(logging.WARNING):
        decisions = _decide(hook, sweep / "0", snaps["own"])
        _decide(hook, sweep / "0", snaps["own"], step=512)  # the next ready point: no new warning
    assert decisions.load is not None
    [rec] = _exploits(sweep / "0")[:1]
    assert (rec["source"], rec["source_score"]) == ("1", 5.0)
    named = [r.getMessage() for r in caplog.records if "ignored in the sweep dir" in r.getMessage()]
    assert len(named) == 1, named
    for stray in ("old", "2", "linked", "pend"):
        assert f"{stray} (" in named[0]
    assert "linked (a symlink" in named[0] and "0 (" not in named[0] and "1 (" not in named[0]


def test_sync_waits_for_its_member_not_a_stray_at_the_same_generation(tmp_path, snaps):
    sweep = tmp_path / "sweep"
    _multirun(sweep)
    _strays(sweep, snaps)
    # Member 1 not there yet: the strays at generation 1 must not stand in for it
    decisions = _decide(_hook(mode="sync", sync_timeout_s=1.0), sweep / "0", snaps["own"])
    assert decisions.load is None and not _exploits(sweep / "0")
    # With member 1 there, the source is member 1 (named by its dir, whatever its file claims)
    sweep2 = tmp_path / "sweep2"
    _multirun(sweep2)
    _strays(sweep2, snaps)
    _publish(sweep2 / "1", snaps["own"], 5.0, claims="9")
    decisions = _decide(_hook(mode="sync", sync_timeout_s=30.0), sweep2 / "0", snaps["own"])
    assert decisions.load is not None
    assert [(r["source"], r["source_score"]) for r in _exploits(sweep2 / "0")] == [("1", 5.0)]


@pytest.mark.parametrize("kind", ["other_env", "other_width"])
def test_a_members_snapshot_that_does_not_fit_is_skipped(tmp_path, snaps, kind, caplog):
    sweep = tmp_path / "sweep"
    _multirun(sweep)
    _publish(sweep / "1", snaps[kind], 5.0)
    with caplog.at_level(logging.WARNING):
        decisions = _decide(_hook(), sweep / "0", snaps["own"])
    assert decisions.load is None and not _exploits(sweep / "0")  # kept its own state
    line = next(r.getMessage() for r in caplog.records if "does not fit" in r.getMessage())
    want = "env.name=" if kind == "other_env" else "policy"
    assert line.startswith("[pbt] member 1's snapshot does not fit this member (") and want in line


# -- one bad value in one member's files ---------------------------------------------------------
def _member(sweep: Path, name: str, lineage: list, final: float, ready: list | None = None):
    run = sweep / name
    (run / "pbt").mkdir(parents=True)
    (run / "status.json").write_text(
        json.dumps(
            {"state": "finished", "global_step": 2048, "final_eval": {"eval/episode_return": final}}
        )
    )
    (run / "config.yaml").write_text("algorithm:\n  name: ppo\nenv:\n  name: Pendulum-v1\n")
    (run / ".hydra").mkdir()
    (run / ".hydra" / "overrides.yaml").write_text(f"- seed={name}\n")
    lines = [x if isinstance(x, str) else json.dumps(x) for x in lineage]
    (run / "pbt" / "lineage.jsonl").write_text("".join(x + "\n" for x in lines))
    if ready is not None:
        (run / "pbt" / "ready.jsonl").write_text("".join(x + "\n" for x in ready))
    return run


START = {"event": "start", "step": 0, "member": "0", "hyperparameters": HPS}


def _exploit(step: int, new: dict, **kw) -> dict:
    return {"event": "exploit", "step": step, "generation": int(step) // 1024, "member": "0",
            "score": 1.0, "source": "1", "source_step": step, "source_score": 2.0, "old": HPS,
            "copied": HPS, "new": new, "explore": {"lr": "x1.2"}, **kw}  # fmt: skip


GOOD = [START, _exploit(1024, {**HPS, "lr": 3.6e-4}), _exploit(2048, {**HPS, "lr": 1e-05})]
BAD = {
    "a string": [START, _exploit(1024, {**HPS, "lr": "abc"})],
    "a list": [START, _exploit(1024, [1, 2])],
    "inf": [START, '{"event": "exploit", "step": 1024, "new": {"lr": Infinity}}'],
    "a negative rate": [START, _exploit(1024, {**HPS, "lr": -0.5})],
    "a string step": [START, _exploit("1024", {**HPS, "lr": 4e-4})],
    "a step back": [START, _exploit(2048, HPS), _exploit(1024, HPS)],
    "a null score": [START, _exploit(1024, HPS, score=None)],
    "not JSON": [START, '{"event": "exploit", "step": 1024, "new": {"lr": 3e-4'],
}


@pytest.mark.parametrize("bad", list(BAD))
def test_one_bad_lineage_value_costs_its_member_not_the_sweep(tmp_path, bad, caplog):
    sweep = tmp_path / "sweep"
    _multirun(sweep)
    _member(sweep, "0", GOOD, 10.0)
    _member(sweep, "1", BAD[bad], 99.0)  # the best by its final score
    with caplog.at_level(logging.WARNING):
        code, out, err = rlexp_cli("runs", sweep)
    assert code == 0, err
    assert "0: lr=1e-05, clip_epsilon=0.2, entropy_coeff=0" in out and "\n1: " not in out
    assert any("lineage.jsonl line 2:" in r.getMessage() or "line 3:" in r.getMessage()
               for r in caplog.records if r.levelno == logging.WARNING)  # fmt: skip
    code, md, err = rlexp_cli("report", sweep, "--no-plot")
    assert code == 0, err
    assert "1 members, 2 exploits in all" in md and "Best member: **0**" in md
    # export: the damaged member is refused in one line; the best readable one is exported
    target = tmp_path / "conf" / "hooks" / "best.yaml"
    code, _, err = rlexp_cli("pbt", "export", sweep, "--member", "1", "-o", target)
    assert code == 2 and not target.exists()
    assert err.startswith("rlexp pbt export: member 1 in ") and "lineage.jsonl line " in err
    assert len(err.strip().splitlines()) == 1
    assert rlexp_cli("pbt", "export", sweep, "-o", target)[0] == 0
    assert yaml.safe_load(target.read_text())["pbt_lr"]["params"]["points"] == [
        [0, 3e-4], [1024, 3.6e-4], [2048, 1e-05]]  # fmt: skip


def test_an_export_is_one_train_py_accepts_or_nothing(tmp_path):
    from rlexp.hooks.base import check_hook
    from rlexp.pbt.lineage import export_schedule, read_member

    sweep = tmp_path / "sweep"
    _multirun(sweep)
    good = read_member(_member(sweep, "0", GOOD, 1.0))
    exported = yaml.safe_load(export_schedule(good))
    for name, hook in exported.items():
        check_hook(hook["func"], hook["params"], f"hooks.{name}")  # what train.py checks
    assert exported["pbt_clip_epsilon"]["params"]["points"] == [[0, 0.2]]
    # A dir name with a line break stays inside the file's comment
    weird = read_member(_member(sweep, "x\nevil: 1", GOOD, 1.0))
    assert set(yaml.safe_load(export_schedule(weird))) == set(exported)
    # A name the member's algorithm (ppo) cannot set: refused, one line naming it
    odd = read_member(_member(sweep, "1", [START, _exploit(1024, {**HPS, "kl_coeff": 0.1})], 1.0))
    with pytest.raises(ValueError, match=r"sets 'kl_coeff', not a mutable hyperparameter"):
        export_schedule(odd)
    # Two records at one step (a ready point decided again): one point, the later value
    twice = [START, _exploit(1024, {**HPS, "lr": 4e-4}), _exploit(1024, {**HPS, "lr": 5e-4})]
    pts = yaml.safe_load(export_schedule(read_member(_member(sweep, "2", twice, 1.0))))
    assert pts["pbt_lr"]["params"]["points"] == [[0, 3e-4], [1024, 5e-4]]


def test_a_bad_ready_line_is_left_out_not_the_member(tmp_path, caplog):
    from rlexp.pbt.population import read_ready

    good = {"member": "0", "step": 256, "generation": 1, "score": 2.5,
            "checkpoint": "ready_step_000000256.pt", "hyperparameters": HPS, "time": 1.0}  # fmt: skip
    lines = [
        json.dumps(good),
        json.dumps({**good, "step": "512", "checkpoint": "ready_step_000000512.pt"}),
        json.dumps({**good, "step": 768, "score": "high", "checkpoint": "ready_step_000000768.pt"}),
        json.dumps({**good, "step": 1024, "hyperparameters": {"lr": [1]}}),
        json.dumps({**good, "step": 1280, "checkpoint": "ready_step_000000256.pt"}),
        '{"member": "0", "step": 1e999}',
        json.dumps(
            {
                **good,
                "member": "9",
                "step": 1536,
                "generation": 6,
                "checkpoint": "ready_step_000001536.pt",
                "score": None,
            }
        ),  # fmt: skip
    ]
    sweep = tmp_path / "sweep"
    run = _member(sweep, "0", GOOD, 1.0, ready=lines)
    problems: list[str] = []
    recs = read_ready(run, problems)
    assert [(r.member, r.step, r.score) for r in recs] == [("0", 256, 2.5), ("0", 1536, None)]
    assert [p.split(":")[0] for p in problems] == [f"pbt/ready.jsonl line {i}" for i in range(2, 7)]
    assert rlexp_cli("report", sweep, "--no-plot")[0] == 0


@pytest.mark.parametrize(
    ("subdir", "ok"),
    [("${hydra.job.num}", True), ("member_${hydra.job.num}", True), ("${hydra.job.override_dirname}", False),
     ("${hydra.job.num}/x", False), ("m${hydra.job.num}_${now:%H}", False), ("fixed", False)],
)  # fmt: skip
def test_a_pbt_sweep_names_its_job_dirs_by_job_number(subdir, ok):
    from rlexp.pbt.config import check_pbt_subdir

    hooks = {"pbt": {"func": "pbt", "params": PARAMS}}
    check_pbt_subdir(subdir, {"other": {"func": "stop_at"}})  # no PBT: anything goes
    if ok:
        check_pbt_subdir(subdir, hooks)
        return
    with pytest.raises(ValueError) as err:
        check_pbt_subdir(subdir, hooks)
    assert str(err.value).startswith(f"hydra.sweep.subdir={subdir}: a PBT population ")
    assert "\n" not in str(err.value)
