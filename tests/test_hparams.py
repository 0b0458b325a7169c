"""TensorBoard's HParams dashboard for sweeps: each job's hyperparameters and final metrics, read
back through TensorBoard's own HParams plugin (what ``tensorboard --logdir <sweep dir>`` serves)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from conftest import SWEEP_TINY, compose, run_train

#: conftest.SWEEP_TINY (an eval after each batch), one checkpoint at the end.
TINY = [
    o if not o.startswith("trainer.save_every=") else "trainer.save_every=512" for o in SWEEP_TINY
]
METRICS = {
    "eval/episode_return",
    "eval/success_rate",
    "train/episode_return",
    "train/episode_length",
    "best/eval_episode_return",
}


def dashboard(logdir: Path) -> tuple[object, dict[str, object]]:
    """The HParams plugin's answers for ``logdir``: the experiment (columns) and each run's
    session group (its hyperparameter values, metric values and status), by run name."""
    from tensorboard import context
    from tensorboard.backend.event_processing import plugin_event_multiplexer
    from tensorboard.backend.event_processing.data_provider import MultiplexerDataProvider
    from tensorboard.plugins import base_plugin
    from tensorboard.plugins.hparams import (
        api_pb2,
        backend_context,
        get_experiment,
        list_session_groups,
    )

    mux = plugin_event_multiplexer.EventMultiplexer()
    mux.AddRunsFromDirectory(str(logdir))
    mux.Reload()
    provider = MultiplexerDataProvider(mux, str(logdir))
    plugin = backend_context.Context(
        base_plugin.TBContext(logdir=str(logdir), multiplexer=mux, data_provider=provider)
    )
    ctx = context.RequestContext()
    experiment = get_experiment.Handler(ctx, plugin, "", api_pb2.GetExperimentRequest()).run()
    request = api_pb2.ListSessionGroupsRequest(
        slice_size=100, allowed_statuses=list(api_pb2.Status.values())
    )
    groups = list_session_groups.Handler(ctx, plugin, "", request).run().session_groups
    return experiment, {g.name: g for g in groups}


def hparam(group: object, key: str) -> object:
    value = group.hparams[key]
    return getattr(value, value.WhichOneof("kind"))


def metrics(group: object) -> dict[str, float]:
    return {m.name.tag: m.value for m in group.metric_values}


@pytest.fixture(scope="module")
def sweep(tmp_path_factory) -> Path:
    """``python train.py -m algorithm.clip_epsilon=0.1,0.2`` on tiny budgets (2 jobs, eval on)."""
    root = tmp_path_factory.mktemp("hparams")
    run_train(
        ["-m", *TINY, "algorithm.clip_epsilon=0.1,0.2", f"hydra.sweep.dir={root / 'sweep'}"],
        cwd=root,
    )
    return root / "sweep"


def test_a_sweep_is_one_hparams_session_per_job_with_its_own_values(sweep):
    experiment, groups = dashboard(sweep)
    # One run per job, in the job's own tensorboard/ dir (no add_hparams sub-run).
    assert sorted(groups) == ["0/tensorboard", "1/tensorboard"]
    assert {m.name.tag for m in experiment.metric_infos} == METRICS
    columns = {h.name for h in experiment.hparam_infos}
    for key in (
        "seed",
        "env.name",
        "algorithm.clip_epsilon",
        "algorithm.lr",
        "policy.actor.hidden_sizes",
        "policy.actor.activation",
        "trainer.total_frames",
        "trainer.frames_per_batch",
        "hooks",
        "overrides",
    ):
        assert key in columns, f"{key} is not a column; have {sorted(columns)}"
    assert not [c for c in columns if c.startswith("logger.")]
    for job, clip in (("0", 0.1), ("1", 0.2)):
        group = groups[f"{job}/tensorboard"]
        assert hparam(group, "algorithm.clip_epsilon") == pytest.approx(clip)
        assert f"algorithm.clip_epsilon={clip}" in hparam(group, "overrides")
        assert hparam(group, "env.name") == "InvertedPendulum-v5"
        assert hparam(group, "seed") == 0
        assert hparam(group, "trainer.total_frames") == 512
        assert hparam(group, "policy.actor.hidden_sizes") == "[64, 64]"
        assert hparam(group, "algorithm.normalize_advantage") is True
        assert [s.status for s in group.sessions] == [1]  # STATUS_SUCCESS: status.json finished


def test_the_metrics_are_each_jobs_final_values_and_best_eval(sweep):
    _, groups = dashboard(sweep)
    for job in ("0", "1"):
        rows = [
            json.loads(line) for line in (sweep / job / "metrics.jsonl").read_text().splitlines()
        ]
        final = json.loads((sweep / job / "status.json").read_text())["final_eval"]
        evals = [r["eval/episode_return"] for r in rows if "eval/episode_return" in r]
        train = [r for r in rows if "train/episode_return" in r][-1]
        got = metrics(groups[f"{job}/tensorboard"])
        # InvertedPendulum defines no success: its column is declared and stays empty
        assert set(got) == METRICS - {"eval/success_rate"} and "eval/success_rate" not in final
        assert got["eval/episode_return"] == pytest.approx(final["eval/episode_return"])
        assert got["train/episode_return"] == pytest.approx(train["train/episode_return"])
        assert got["train/episode_length"] == pytest.approx(train["train/episode_length"])
        assert len(evals) == 2 and got["best/eval_episode_return"] == pytest.approx(max(evals))


def test_hparams_of_lists_term_tables_by_name_and_gives_overridden_keys_a_column():
    from rlexp.config.validate import to_dict, to_root_config
    from rlexp.run.metrics import hparams_of

    overrides = ["env=push_cube", "env.native.rewards.success_bonus.weight=5", "hooks=[lr_anneal]"]
    config = to_dict(to_root_config(compose(overrides)))
    table = hparams_of(config, overrides)
    assert table["env.native.task"] == "push_cube"
    assert table["env.native.rewards"] == (
        "reaching_reward, goal_distance_reward, action_penalty, success_bonus"
    )
    assert table["env.native.rewards.success_bonus.weight"] == 5.0
    assert table["hooks"] == "lr_anneal"
    assert table["events.train"] == ""
    assert table["overrides"] == " ".join(overrides)
    assert not [k for k in table if k.startswith(("env.native.events.", "logger."))]
    assert all(isinstance(v, (bool, int, float, str)) for v in table.values())
    assert "algorithm.clip_value" not in table  # None: no value to show


def test_a_resumed_run_keeps_its_best_and_an_unfinished_one_has_no_end_status(tmp_path):
    from rlexp.run.metrics import TensorBoardBackend

    config = {"seed": 3, "algorithm": {"clip_epsilon": 0.3}}
    first = TensorBoardBackend(tmp_path, config)
    first.log({"eval/episode_return": 5.0}, 100)
    first.log({"eval/episode_return": 3.0}, 200)
    first.close()  # no status.json: as a run killed mid-way, or interrupted (resumed later)
    _, groups = dashboard(tmp_path)
    assert [s.status for s in groups["tensorboard"].sessions] == [0]  # STATUS_UNKNOWN
    assert hparam(groups["tensorboard"], "algorithm.clip_epsilon") == pytest.approx(0.3)

    second = TensorBoardBackend(tmp_path, config)  # the resume: a new event file, same dir
    second.log({"train/episode_return": 1.0}, 300)
    second.log({"eval/episode_return": 4.0}, 400)
    (tmp_path / "status.json").write_text(json.dumps({"state": "finished", "global_step": 400}))
    second.close()
    _, groups = dashboard(tmp_path)
    got = metrics(groups["tensorboard"])
    assert got["best/eval_episode_return"] == 5.0 and got["eval/episode_return"] == 4.0
    assert hparam(groups["tensorboard"], "seed") == 3

    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    newest = EventAccumulator(str(sorted((tmp_path / "tensorboard").glob("events.*"))[-1]))
    newest.Reload()  # the best goes on in the resumed run's own file: a continuous curve
    best = newest.Scalars("best/eval_episode_return")
    assert [(e.step, e.value) for e in best] == [(300, 5.0)]


def test_the_carried_best_is_read_with_tensorboards_loader_up_to_a_torn_record(tmp_path):
    """A crash mid-write leaves a torn last record: the best before it is the one carried over."""
    from rlexp.run.metrics import BEST_EVAL_RETURN, TensorBoardBackend, _last_logged

    first = TensorBoardBackend(tmp_path, {"seed": 1})
    first.log({"eval/episode_return": 5.0}, 100)
    first.log({"eval/episode_return": 7.5}, 200)
    first.close()
    (path,) = sorted((tmp_path / "tensorboard").glob("events.*"))
    assert _last_logged([path], BEST_EVAL_RETURN) == 7.5
    path.write_bytes(path.read_bytes()[:-5])  # the 7.5 record, torn
    assert _last_logged([path], BEST_EVAL_RETURN) == 5.0
