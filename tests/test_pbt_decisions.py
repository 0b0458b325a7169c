"""PBT's decisions at their boundaries (rlexp.pbt.population, the ``pbt`` hook): explore clips to
both bounds, the decision generator is keyed by generation, and a ready point is the first
checkpoint *past* each multiple of ``ready_every`` (never every checkpoint, never the last one, never
twice across a resume). Values hand-computed; the hook driven point by point, no training."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from conftest import TINY, compose

LR = {"low": 1e-4, "high": 2e-3, "log": True}
CLIP = {"low": 0.05, "high": 0.25}


def _cfg(**kw):
    from rlexp.pbt.config import PBTConfig

    params = {"hyperparameters": {"lr": LR, "clip_epsilon": CLIP}, **kw}
    return PBTConfig.from_params(params)


# -- explore: both bounds, at and across them ------------------------------------------------------
@pytest.mark.parametrize(
    ("factor", "lr", "clip", "want_lr", "want_clip"),
    [
        (0.5, 3e-4, 0.2, 1.5e-4, 0.1),  # inside: the product itself
        (0.5, 2e-4, 0.1, 1e-4, 0.05),  # onto the lower bounds exactly
        (0.5, 1.5e-4, 0.08, 1e-4, 0.05),  # across the lower bounds: clipped up to them
        (0.5, 1e-4, 0.05, 1e-4, 0.05),  # at the lower bounds: stays there
        (1.5, 1e-3, 0.1, 1.5e-3, 0.15),  # inside
        (1.5, 1.5e-3, 0.2, 2e-3, 0.25),  # across the upper bounds: clipped down to them
        (1.5, 2e-3, 0.25, 2e-3, 0.25),  # at the upper bounds: stays there
    ],
)
def test_explore_clips_a_perturbation_to_both_bounds(factor, lr, clip, want_lr, want_clip):
    from rlexp.pbt.population import explore

    cfg = _cfg(perturb_factors=[factor], resample_probability=0.0)
    new, how = explore({"lr": lr, "clip_epsilon": clip, "entropy_coeff": -7.0}, cfg,
                       np.random.default_rng(0))  # fmt: skip
    assert new["lr"] == pytest.approx(want_lr, rel=1e-12)
    assert new["clip_epsilon"] == pytest.approx(want_clip, rel=1e-12)
    assert new["entropy_coeff"] == -7.0  # not tuned: left as it is, even out of any range
    assert how == {"lr": f"x{factor:g}", "clip_epsilon": f"x{factor:g}"}


def test_a_resample_is_drawn_within_the_bounds_log_uniformly_for_log_ones():
    from rlexp.pbt.population import explore

    cfg = _cfg(resample_probability=1.0)
    rng = np.random.default_rng(1)
    lrs, clips = [], []
    for _ in range(2000):
        new, how = explore({"lr": 5.0, "clip_epsilon": -3.0}, cfg, rng)  # far outside: ignored
        assert how == {"lr": "resampled", "clip_epsilon": "resampled"}
        lrs.append(new["lr"])
        clips.append(new["clip_epsilon"])
    assert 1e-4 <= min(lrs) and max(lrs) <= 2e-3 and 0.05 <= min(clips) and max(clips) <= 0.25
    # log-uniform on [1e-4, 2e-3]: the median is sqrt(1e-4 * 2e-3) = 4.47e-4 (uniform: 1.05e-3)
    assert np.median(lrs) == pytest.approx(math.sqrt(1e-4 * 2e-3), rel=0.1)
    assert np.median(clips) == pytest.approx(0.15, abs=0.01)  # uniform: the middle


# -- the hook, point by point ----------------------------------------------------------------------
def _hook(**kw):
    from rlexp.hooks.pbt import PopulationBasedTraining

    params = {"population_size": 2, "hyperparameters": {"lr": LR, "clip_epsilon": CLIP}, **kw}
    return PopulationBasedTraining(**params)


HPS = {"lr": 3e-4, "clip_epsilon": 0.2, "entropy_coeff": 0.0}


def _at(hook, run_dir: Path, point: str, step: int, total: int, checkpoint=None, **kw):
    """Fire ``point`` at ``step``; the decisions it took."""
    from rlexp.hooks.base import HookControl, HookState

    state = HookState(point=point, global_step=step, iteration=step // 250, total_steps=total,
                      run_dir=run_dir, metrics={"train/episode_return": kw.pop("score", 1.0)},
                      hyperparameters=kw.pop("hps", HPS), checkpoint=checkpoint, **kw)  # fmt: skip
    control = HookControl(HPS)
    hook(state, control)
    return control.decisions


def _ready_steps(run_dir: Path) -> list[int]:
    path = run_dir / "pbt" / "ready.jsonl"
    if not path.exists():
        return []
    return [json.loads(x)["step"] for x in path.read_text().splitlines()]


def _life(hook, run_dir: Path, steps, total: int) -> None:
    """The checkpoints a member writes at ``steps``, the hook fired after each (its log first)."""
    for step in steps:
        ckpt = run_dir / "checkpoints" / f"m_step_{step:09d}.pt"
        ckpt.parent.mkdir(parents=True, exist_ok=True)
        ckpt.write_bytes(b"checkpoint")
        _at(hook, run_dir, "log", step, total)
        _at(hook, run_dir, "checkpoint", step, total, checkpoint=ckpt)


@pytest.mark.parametrize(
    ("save_every", "total", "want"),
    [
        (250, 3000, [1000, 2000]),  # at each multiple exactly; not at the end (step == total)
        (250, 3250, [1000, 2000, 3000]),  # the last multiple before the end is one
        (300, 3300, [1200, 2100, 3000]),  # the first checkpoint past each multiple
        (1000, 3001, [1000, 2000, 3000]),  # save_every == ready_every: every checkpoint
        (700, 4000, [1400, 2100, 3500]),  # 2800 is in generation 2 like 2100: not one
    ],
)
def test_a_ready_point_is_the_first_checkpoint_past_each_multiple(tmp_path, save_every, total,
                                                                   want):  # fmt: skip
    run = tmp_path / "sweep" / "0"
    hook = _hook(ready_every=1000)
    _at(hook, run, "train_start", 0, total)
    _life(hook, run, range(save_every, total + 1, save_every), total)
    assert _ready_steps(run) == want
    gens = [
        json.loads(x)["generation"] for x in (run / "pbt" / "ready.jsonl").read_text().splitlines()
    ]
    assert gens == [s // 1000 for s in want]


def test_a_resume_at_a_ready_point_decides_it_once_and_a_later_one_not_again(tmp_path):
    run = tmp_path / "sweep" / "0"
    total = 3000
    # Life 1: checkpoints 250..750, then the one at 1000 is written and the member is killed
    # before the hook fires there: its checkpoint holds the hook's state of step 750.
    first = _hook(ready_every=1000)
    _at(first, run, "train_start", 0, total)
    _life(first, run, [250, 500, 750], total)
    saved = first.state_dict()
    (run / "checkpoints" / "m_step_000001000.pt").write_bytes(b"checkpoint")
    assert _ready_steps(run) == []
    # Life 2 resumes at 1000: that ready point is decided first, once; 1250..1750 are not.
    second = _hook(ready_every=1000)
    second.load_state_dict(saved)
    _at(second, run, "train_start", 1000, total, resumed=True)
    assert _ready_steps(run) == [1000]
    _life(second, run, [1250, 1500], total)
    assert _ready_steps(run) == [1000]
    saved = second.state_dict()  # the checkpoint of 1500: the 1000 decision is in it
    # Life 3 resumes at 1500 (past the ready point, decided): nothing at start, next one at 2000.
    third = _hook(ready_every=1000)
    third.load_state_dict(saved)
    _at(third, run, "train_start", 1500, total, resumed=True)
    assert _ready_steps(run) == [1000]
    _life(third, run, [1750, 2000, 2250], total)
    assert _ready_steps(run) == [1000, 2000]


# -- the decision generator: keyed by (seed, member, generation) -----------------------------------
@pytest.fixture(scope="module")
def snapshots(tmp_path_factory):
    """Real checkpoints of one tiny run at steps 256 .. 1024 (what a sibling's snapshots are)."""
    from rlexp.config.validate import to_dict, to_root_config
    from rlexp.run.metrics import MetricLogger
    from rlexp.training.build import build

    root = tmp_path_factory.mktemp("snap")
    config = to_root_config(compose([*TINY, "trainer.eval_every=0", "algorithm.num_epochs=1"]))
    trainer = build(config, root / "run", "cpu", 1024).trainer(MetricLogger([]), to_dict(config),
                                                              {})  # fmt: skip
    try:
        trainer.train(1024)
    finally:
        trainer.close()
    found = {int(p.stem.rsplit("_", 1)[1]): p for p in (root / "run" / "checkpoints").glob("*.pt")}
    assert sorted(found) == [256, 512, 768, 1024]
    return found


def _population_run(sweep: Path, snapshots, gens, seed=0, member="0"):
    """Member ``member`` (score 1) beside member 'x' (score 9, a snapshot at each ready point) at
    ready points 256 * gens: the values it explored to, per generation."""
    from rlexp.pbt.population import Ready, publish, ready_name

    me = sweep / member
    other = sweep / ("1" if member == "0" else "0")
    hook = _hook(ready_every=256, resample_probability=1.0, seed=seed, mode="async")
    _at(hook, me, "train_start", 0, 4096)
    out = {}
    for gen in gens:
        step = 256 * gen
        publish(other, snapshots[step], Ready("x", step, gen, 9.0, ready_name(step), HPS), keep=8)
        own = me / "checkpoints" / f"m_step_{step:09d}.pt"
        own.parent.mkdir(parents=True, exist_ok=True)
        own.write_bytes(snapshots[step].read_bytes())
        _at(hook, me, "log", step, 4096, score=1.0)
        decisions = _at(hook, me, "checkpoint", step, 4096, checkpoint=own)
        assert decisions.load is not None, f"no exploit at generation {gen}"
        out[gen] = dict(decisions.set)
    return out


def test_each_generation_draws_afresh_and_the_same_seeds_draw_the_same(tmp_path, snapshots):
    a = _population_run(tmp_path / "a", snapshots, [1, 2, 3, 4])
    # Resampled (probability 1) at each ready point: four generations, four different draws
    for name in ("lr", "clip_epsilon"):
        values = [a[g][name] for g in (1, 2, 3, 4)]
        assert len(set(values)) == 4, (name, values)
        assert all(CLIP["low"] <= a[g]["clip_epsilon"] <= CLIP["high"] for g in a)
    # The same (seed, member, generation): the same draws, whatever generations came before
    assert _population_run(tmp_path / "b", snapshots, [3])[3] == a[3]
    assert _population_run(tmp_path / "c", snapshots, [1, 2, 3, 4]) == a
    # Another seed, or another member at the same generation: other draws
    other_seed = _population_run(tmp_path / "d", snapshots, [2], seed=5)[2]
    assert other_seed != a[2]
    other_member = _population_run(tmp_path / "e", snapshots, [2], member="1")[2]
    assert other_member != a[2]


def test_the_decision_generator_is_seeded_by_seed_member_and_generation():
    from rlexp.pbt.population import decision_rng

    draws = {
        key: decision_rng(*key).random(4).tolist()
        for key in [(0, "0", 1), (0, "0", 2), (0, "1", 1), (1, "0", 1)]
    }
    assert len({tuple(v) for v in draws.values()}) == 4
    assert decision_rng(0, "0", 2).random(4).tolist() == draws[(0, "0", 2)]


def test_explore_perturbs_the_copied_values_not_the_members_own(tmp_path, snapshots):
    """The source's checkpoint holds PPO's lr 3e-4 and clip 0.2; the member's own are 1e-3 and 0.1:
    x0.5 of the copied values is lr 1.5e-4, clip 0.1 (of its own: 5e-4 and 0.05)."""
    from rlexp.pbt.population import Ready, publish, ready_name

    me, other = tmp_path / "sweep" / "0", tmp_path / "sweep" / "1"
    own_hps = {"lr": 1e-3, "clip_epsilon": 0.1, "entropy_coeff": 0.005}
    hook = _hook(ready_every=256, perturb_factors=[0.5], resample_probability=0.0)
    _at(hook, me, "train_start", 0, 4096, hps=own_hps)
    publish(other, snapshots[512], Ready("1", 512, 2, 9.0, ready_name(512), HPS), keep=2)
    ckpt = me / "checkpoints" / "m_step_000000512.pt"
    ckpt.parent.mkdir(parents=True)
    ckpt.write_bytes(snapshots[512].read_bytes())
    _at(hook, me, "log", 512, 4096, hps=own_hps)
    decisions = _at(hook, me, "checkpoint", 512, 4096, checkpoint=ckpt, hps=own_hps)
    assert decisions.load is not None
    assert decisions.set == pytest.approx({"lr": 1.5e-4, "clip_epsilon": 0.1})
    [rec] = [json.loads(x) for x in (me / "pbt" / "lineage.jsonl").read_text().splitlines()][1:]
    assert rec["old"] == {"lr": 1e-3, "clip_epsilon": 0.1}
    assert rec["copied"] == pytest.approx({"lr": 3e-4, "clip_epsilon": 0.2})
    assert rec["explore"] == {"lr": "x0.5", "clip_epsilon": "x0.5"}
