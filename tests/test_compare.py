"""``rlexp compare``: config differences, scores, IQM difference and probability of improvement."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import mannwhitneyu
from test_runs import make_run, rlexp

from conftest import run_train
from rlexp.analysis import compare
from rlexp.analysis.report import iqm


def curve(final: float, steps: int = 4) -> list[dict]:
    """An eval history rising linearly to ``final`` at step 100 * steps."""
    return [
        {"step": 100 * k, "eval/episode_return": final * k / steps} for k in range(1, steps + 1)
    ]


def sweep(root: Path, finals: list[float], algo: str = "ppo", lr: float = 0.0003) -> Path:
    for seed, final in enumerate(finals):
        run = make_run(
            root / str(seed),
            algo=algo,
            seed=seed,
            final=final,
            metrics=curve(final),
            overrides=[f"algorithm={algo}", f"seed={seed}"],
        )
        cfg = (run / "config.yaml").read_text().replace("lr: 0.0003", f"lr: {lr}")
        (run / "config.yaml").write_text(cfg)
    return root


def test_probability_of_improvement_by_hand():
    # x=3: beats 1, ties 3 (a half), loses to 5; x=4: beats 1 and 3 -> (1 + .5 + 0 + 1 + 1 + 0) / 6
    assert compare.probability_of_improvement([3, 4], [1, 3, 5]) == pytest.approx(3.5 / 6)
    assert compare.probability_of_improvement([1, 2, 3], [2, 2]) == pytest.approx(0.5)
    assert compare.probability_of_improvement([2], [2]) == 0.5
    rng = np.random.default_rng(1)
    xs, ys = rng.integers(0, 4, (50, 5)).astype(float), rng.integers(0, 4, (50, 3)).astype(float)
    by_ranks = compare._poi_rows(xs, ys)  # the bootstrap's vectorised form, ties included
    direct = [compare.probability_of_improvement(x, y) for x, y in zip(xs, ys, strict=True)]
    assert by_ranks == pytest.approx(direct)
    assert direct[0] == pytest.approx(mannwhitneyu(xs[0], ys[0]).statistic / 15)


def test_two_sweeps_iqm_difference_and_probability_of_improvement(tmp_path, monkeypatch):
    sweep(tmp_path / "a", [1.0, 2.0, 3.0, 4.0])
    sweep(tmp_path / "b", [0.0, 0.0, 1.0, 1.0])
    monkeypatch.chdir(tmp_path)
    out = rlexp("compare", "a", "b", "--threshold", "0.5", "--json", cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    res = json.loads(out.stdout)
    assert [g["group"] for g in res["groups"]] == ["a", "b"]
    # IQM of 4 values: the mean of the middle two -> 2.5 and 0.5
    assert [g["iqm"] for g in res["groups"]] == [2.5, 0.5]
    (pair,) = res["comparisons"]
    assert pair["iqm_difference"] == pytest.approx(2.0)
    # a=1 vs b: beats 0, 0, ties 1, 1 -> 3 of 4; a=2,3,4 beat all four -> (3 + 12) / 16
    assert pair["probability_of_improvement"] == pytest.approx(15 / 16)
    low, high = pair["probability_of_improvement_ci"]
    assert 0 <= low <= 15 / 16 <= high <= 1
    low, high = pair["iqm_difference_ci"]
    assert 0.0 <= low <= 2.0 <= high <= 4.0  # resampled IQMs: a in [1, 4], b in [0, 1]
    # the same seeds and configs in both dirs: only the seed differs between runs
    assert set(res["differences"]) == {"seed"}
    # steps to 0.5: final 1 reaches 0.5 at step 200 (0.25, 0.5, ...), final 0 never
    by_label = {r["label"]: r for r in res["runs"]}
    assert (
        by_label["a/0"]["steps_to_threshold"] == 200
        and by_label["b/0"]["steps_to_threshold"] is None
    )
    assert by_label["a/3"]["final"] == 4.0 and by_label["a/3"]["best"] == 4.0


def test_group_by_within_one_sweep_and_config_differences(tmp_path):
    sweep(tmp_path / "s" / "ppo", [5.0, 6.0], algo="ppo")
    sweep(tmp_path / "s" / "grpo", [1.0, 2.0], algo="grpo", lr=0.001)
    out = rlexp("compare", "s", "--group-by", "algorithm.name", "--json", cwd=tmp_path)
    res = json.loads(out.stdout)
    assert sorted(g["group"] for g in res["groups"]) == [
        "algorithm.name=grpo",
        "algorithm.name=ppo",
    ]
    assert set(res["differences"]) == {"algorithm.name", "algorithm.lr", "seed"}
    assert res["differences"]["algorithm.lr"]["grpo/0"] == 0.001
    (pair,) = res["comparisons"]
    assert abs(pair["probability_of_improvement"] - 0.5) == 0.5  # one side wins every pair
    # default grouping: the config less the seed, labelled by the overrides that differ
    res = json.loads(rlexp("compare", "s", "--json", cwd=tmp_path).stdout)
    assert sorted(g["group"] for g in res["groups"]) == ["algorithm=grpo", "algorithm=ppo"]
    table = rlexp("compare", "s", cwd=tmp_path).stdout
    assert "Config keys that differ (3)" in table and "P(first > second)" in table
    assert (
        "algorithm=grpo  vs  algorithm=ppo" in table or "algorithm=ppo  vs  algorithm=grpo" in table
    )


def test_one_configuration_and_bad_input(tmp_path):
    sweep(tmp_path / "a", [1.0, 2.0])
    out = rlexp("compare", "a", cwd=tmp_path)
    assert out.returncode == 0 and "One configuration: no comparison" in out.stdout
    for args, message in [
        (["nowhere"], "nowhere: no such dir"),
        (["a", "--group-by", "algorithm.nme"], "did you mean 'algorithm.name'?"),
        (["a", "--threshold", "x"], "is not VALUE or METRIC=VALUE"),
    ]:
        out = rlexp("compare", *args, cwd=tmp_path)
        assert out.returncode == 2 and message in out.stderr and len(out.stderr.splitlines()) == 1
    (tmp_path / "empty").mkdir()
    out = rlexp("compare", "empty", cwd=tmp_path)
    assert out.returncode == 2 and "empty: no run dir there" in out.stderr


def test_iqm_band_stays_inside_the_data_and_the_plot_is_written(tmp_path):
    curves = [[(0, 0.0), (10, v), (20, 2 * v)] for v in (1.0, 2.0, 3.0, 50.0)]
    curves.append([(0, 0.0), (10, 4.0)])  # a shorter run: only where it has data
    steps, centre, low, high = compare.iqm_band(curves)
    assert list(steps) == [0, 10, 20]
    ys = np.array([[0, 1, 2], [0, 2, 4], [0, 3, 6], [0, 50, 100]], float)
    assert centre[2] == pytest.approx(iqm(ys[:, 2]))
    assert centre[1] == pytest.approx(iqm(np.array([1, 2, 3, 50, 4.0])))
    assert np.all(low <= centre) and np.all(centre <= high)
    assert low[2] >= 2.0 and high[2] <= 100.0  # never beyond the runs' values (a std band would)
    sweep(tmp_path / "a", [1.0, 2.0, 3.0])
    sweep(tmp_path / "b", [2.0, 3.0, 4.0])
    out = rlexp("compare", "a", "b", "--plot", "c.png", "--threshold", "2", cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    assert (tmp_path / "c.png").read_bytes()[:4] == b"\x89PNG" and "curves: c.png" in out.stdout


def test_two_real_runs(tmp_path):
    """Two tiny real runs: their differing keys, and scores equal to their own final eval."""
    for seed in (1, 2):
        run_train(
            [
                "env=inverted_pendulum",
                "trainer.total_frames=512",
                "trainer.frames_per_batch=256",
                "trainer.eval_every=256",
                "trainer.eval_episodes=2",
                "algorithm.num_epochs=1",
                f"seed={seed}",
                f"hydra.run.dir=runs/{seed}",
            ],
            cwd=tmp_path,
        )
    out = rlexp("compare", "runs/1", "runs/2", "--json", cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    res = json.loads(out.stdout)
    assert set(res["differences"]) == {"seed"}
    for row in res["runs"]:
        status = json.loads((tmp_path / row["path"] / "status.json").read_text())
        assert row["final"] == status["final_eval"]["eval/episode_return"]
        assert row["status"] == "finished" and row["step"] == 512 and row["git"]
    text = rlexp("compare", "runs/1", "runs/2", cwd=tmp_path).stdout
    assert "seed" in text and "no comparison between configurations" in text.lower()
