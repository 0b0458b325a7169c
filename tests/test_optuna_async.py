"""Asynchronous Optuna trials, pruning and seeds inside the search (#50 items 1, 2, 4).

In process (fast): the trial loop with a stand-in launcher on a virtual clock (no barrier: a slow
trial does not delay the next trial's start on the other worker; the batch mode keeps its barrier),
the ``optuna_prune`` hook against each pruner family on a journal study (the step a trial is pruned
at, worked out by hand from the pruner's rule, or for hyperband, whose brackets hash the trial
number, from Optuna itself run on the same values), ``trial_seeds`` (jobs, seeds, the mean / IQM),
and the one-line refusals. Real ``python train.py -m`` sweeps on the local launcher: pruning
(status ``pruned``, the study PRUNED with its intermediate values), no barrier from the trials'
own recorded times, and an asynchronous study killed mid-trial and run again.
"""

from __future__ import annotations

import heapq
import json
import os
import signal
import time
from pathlib import Path

import optuna
import pytest
from hydra.core.utils import JobReturn, JobStatus
from omegaconf import OmegaConf
from optuna.trial import TrialState

from conftest import SWEEP_TINY, Children, journal_order, run_train
from rlexp.hooks.base import HookControl, HookState
from rlexp.hooks.optuna_prune import OptunaPrune
from rlexp.launch.optuna_sweeper import EXIT_REFUSED, OptunaSweep, check_spec

optuna.logging.set_verbosity(optuna.logging.WARNING)

# -- the trial loop on a virtual clock --------------------------------------------------------------


class ClockLauncher:
    """Hydra's launcher interface plus rlexp's ``launch_stream``, on a virtual clock: job ``j``
    lasts ``durations[j]`` time units and returns ``x`` (or None for a job in ``fail``); records
    each job's start and end time and its overrides."""

    def __init__(self, durations: dict[int, float], fail: tuple[int, ...] = ()) -> None:
        self.durations, self.fail = durations, fail
        self.start: dict[int, float] = {}
        self.end: dict[int, float] = {}
        self.overrides: dict[int, list[str]] = {}
        self.now = 0.0

    def _return(self, job: int, overrides) -> JobReturn:
        values = dict(o.split("=", 1) for o in overrides)
        value = None if job in self.fail else float(values.get("x", 0.0))
        return JobReturn(status=JobStatus.COMPLETED, _return_value=value)

    def launch_stream(self, n_jobs, take, done) -> None:
        running: list[tuple[float, int, list[str]]] = []
        more = True
        while more or running:
            while more and len(running) < n_jobs:
                item = take()
                if item is None or item == "wait":
                    more = item is not None
                    break
                job, overrides = item
                self.start[job], self.overrides[job] = self.now, list(overrides)
                heapq.heappush(running, (self.now + self.durations.get(job, 1.0), job, overrides))
            if not running:
                continue
            end, job, overrides = heapq.heappop(running)
            self.now = self.end[job] = end
            done(job, self._return(job, overrides))

    def launch(self, job_overrides, initial_job_idx):
        """A batch: all start now and come back together, once the slowest ended."""
        returns = []
        jobs = [initial_job_idx + i for i in range(len(job_overrides))]
        for job, overrides in zip(jobs, job_overrides, strict=True):
            self.start[job], self.overrides[job] = self.now, list(overrides)
            returns.append(self._return(job, overrides))
        self.now += max(self.durations.get(j, 1.0) for j in jobs)
        for job in jobs:
            self.end[job] = self.now
        return returns


def sweep_once(sweep_dir: Path, launcher, config_seed: int = 0, **cfg) -> OptunaSweep:
    sweep_dir.mkdir(parents=True, exist_ok=True)
    config = {
        "sampler": {"_target_": "optuna.samplers.RandomSampler", "seed": 3},
        "direction": "maximize",
        "storage": f"journal://{sweep_dir}/optuna.journal",
        "study_name": None,
        "n_trials": 4,
        "n_jobs": 2,
        "params": {"x": "interval(0, 1)"},
        **cfg,
    }
    sweeper = OptunaSweep(**config)
    root = {"hydra": {"sweep": {"dir": str(sweep_dir)}}, "seed": config_seed}
    sweeper.bind(OmegaConf.create(root), launcher)
    sweeper.sweep([])
    return sweeper


def test_a_slow_trial_does_not_delay_the_next_trials_start_on_the_other_worker(tmp_path):
    # trial 0 lasts 10 time units, the others 1: the other worker runs trials 1, 2 and 3 one
    # after the other while trial 0 trains (starts 0, 1, 2), not after it (the batch's 10)
    launcher = ClockLauncher({0: 10.0})
    sweeper = sweep_once(tmp_path / "async", launcher)
    assert launcher.start == {0: 0.0, 1: 0.0, 2: 1.0, 3: 2.0}
    assert launcher.end == {0: 10.0, 1: 1.0, 2: 2.0, 3: 3.0}
    trials = sweeper.study.get_trials()
    assert [t.state for t in trials] == [TrialState.COMPLETE] * 4
    assert [t.user_attrs["rlexp_job"] for t in trials] == [0, 1, 2, 3]
    # the study's own record (its journal's order): 2 and 3 were asked and told before 0 was told
    created, finished = journal_order(tmp_path / "async")
    assert finished[3] < finished[0]
    assert finished[1] < created[2] < finished[0]
    # each trial's value is its own job's return
    assert [t.value for t in trials] == [float(launcher.overrides[j][0].split("=")[1]) for j in range(4)]  # fmt: skip

    # async_trials=false: the batches of before, the barrier included
    batch = ClockLauncher({0: 10.0})
    sweep_once(tmp_path / "batch", batch, async_trials=False)
    assert batch.start == {0: 0.0, 1: 0.0, 2: 10.0, 3: 10.0}


class StopLauncher(ClockLauncher):
    """Job 1 is interrupted by a stop signal: its status.json says so and it returns None."""

    def __init__(self, sweep_dir: Path) -> None:
        super().__init__({})
        self.sweep_dir = sweep_dir

    def _return(self, job, overrides):
        if job == 1:
            (self.sweep_dir / "1").mkdir(parents=True, exist_ok=True)
            (self.sweep_dir / "1" / "status.json").write_text('{"state": "interrupted"}')
            return JobReturn(status=JobStatus.COMPLETED, _return_value=None)
        return super()._return(job, overrides)


def test_an_interrupted_trial_stays_running_and_is_resumed_not_failed(tmp_path):
    sweep = tmp_path / "s"
    first = sweep_once(sweep, StopLauncher(sweep), n_trials=3)
    states = [t.state for t in first.study.get_trials()]
    assert states == [TrialState.COMPLETE, TrialState.RUNNING, TrialState.COMPLETE]
    (sweep / "1" / "status.json").unlink()  # its re-run finishes
    again = ClockLauncher({})
    second = sweep_once(sweep, again, n_trials=3)
    assert sorted(again.start) == [1]  # the same trial, in place: no FAIL, no retry, no new one
    trials = second.study.get_trials()
    assert [t.state for t in trials] == [TrialState.COMPLETE] * 3
    assert trials[1].params == first.study.get_trials()[1].params


def test_the_failure_rate_stops_asking_asynchronously(tmp_path, caplog):
    # every job fails: after n_jobs (2) trials told, 2 of 2 failed > 0.5: no new trial is asked;
    # the other worker's trial in flight (none here: both were the first two) ends
    launcher = ClockLauncher({}, fail=(0, 1, 2, 3, 4, 5))
    sweeper = sweep_once(tmp_path, launcher, n_trials=6, max_failure_rate=0.5)
    assert sorted(launcher.start) == [0, 1, 2]  # trial 2 started when trial 0 failed (1 of 1)
    assert [t.state for t in sweeper.study.get_trials()] == [TrialState.FAIL] * 3
    assert "stopping the sweep: 2 of 2 trials so far failed" in caplog.text


def test_sweeps_of_two_dirs_share_one_study_without_taking_each_others_trials(tmp_path):
    """One journal, two sweep dirs (2 local workers and 2 SLURM jobs, say): each sweep plans,
    resumes and numbers its own job dirs; the sampler sees every trial."""
    shared = f"journal://{tmp_path}/shared.journal"
    first, second = ClockLauncher({0: 10.0}), ClockLauncher({})
    a = sweep_once(tmp_path / "a", first, storage=shared, study_name="s", n_trials=3)
    b = sweep_once(tmp_path / "b", second, storage=shared, study_name="s", n_trials=2)
    assert sorted(first.start) == [0, 1, 2] and sorted(second.start) == [0, 1]  # own job dirs
    trials = b.study.get_trials()
    assert [t.user_attrs["rlexp_sweep"] for t in trials] == [str((tmp_path / d).resolve()) for d in "aaabb"]  # fmt: skip
    assert [t.user_attrs["rlexp_job"] for t in trials] == [0, 1, 2, 0, 1]
    # the second sweep's sampler continued the shared study: reseeded with seed + 3 trials so far
    from test_optuna_sweeper import draws

    assert trials[3].params["x"] == draws(optuna.samplers.RandomSampler(seed=6), 1)[0]["x"]
    # each dir's results: its own best trial and job
    for sweeper, numbers in ((a, [0, 1, 2]), (b, [3, 4])):
        res = OmegaConf.load(sweeper.sweep_dir / "optimization_results.yaml")
        best = max((trials[n] for n in numbers), key=lambda t: t.value)
        assert (res.best_trial, res.best_job) == (best.number, best.user_attrs["rlexp_job"])
    # the same command again in dir a: nothing to do (b's trials are not a's to resume)
    again = ClockLauncher({})
    sweep_once(tmp_path / "a", again, storage=shared, study_name="s", n_trials=3)
    assert again.start == {}


def test_a_trial_just_asked_by_another_sweep_is_not_failed_as_an_orphan(tmp_path, monkeypatch):
    """A RUNNING trial with no job yet: another sweep of a shared study may have just asked it
    (it records its job a moment later): left alone; one older than ORPHAN_AGE_S was left by a
    killed sweep: told FAIL."""
    from rlexp.launch import optuna_sweeper

    shared = f"journal://{tmp_path}/shared.journal"
    sweep_once(tmp_path / "a", ClockLauncher({}), storage=shared, study_name="s", n_trials=1)
    study = optuna.load_study(study_name="s", storage=optuna.storages.JournalStorage(
        optuna.storages.journal.JournalFileBackend(str(tmp_path / "shared.journal"))))  # fmt: skip
    just_asked = study.ask().number
    sweep_once(tmp_path / "b", ClockLauncher({}), storage=shared, study_name="s", n_trials=1)
    assert study.get_trials()[just_asked].state == TrialState.RUNNING
    monkeypatch.setattr(optuna_sweeper, "ORPHAN_AGE_S", 0.0)
    sweep_once(tmp_path / "b", ClockLauncher({}), storage=shared, study_name="s", n_trials=1)
    assert study.get_trials()[just_asked].state == TrialState.FAIL


# -- trial_seeds --------------------------------------------------------------------------------------


class SeedLauncher(ClockLauncher):
    """Returns ``RETURNS[seed]`` + x (so each seed of a trial scores apart)."""

    RETURNS = {5: 1.0, 6: 2.0, 7: 3.0, 8: 100.0}

    def _return(self, job, overrides):
        values = dict(o.split("=", 1) for o in overrides)
        value = None if job in self.fail else self.RETURNS[int(values["seed"])] + float(values["x"])
        return JobReturn(status=JobStatus.COMPLETED, _return_value=value)


@pytest.mark.parametrize(("how", "expected"), [("mean", 26.5), ("iqm", 2.5)])
def test_a_trial_of_several_seeds_is_their_mean_or_iqm(tmp_path, how, expected):
    launcher = SeedLauncher({})
    sweeper = sweep_once(
        tmp_path, launcher, config_seed=5, n_trials=2, trial_seeds=4, trial_objective=how
    )
    trials = sweeper.study.get_trials()
    # trial 0 is jobs 0-3 with seeds 5-8 (the config's seed, then the next ones), trial 1 jobs 4-7
    # with the same seeds; each job's overrides: the trial's parameters, then its seed
    assert [t.user_attrs["rlexp_jobs"] for t in trials] == [[0, 1, 2, 3], [4, 5, 6, 7]]
    assert [t.user_attrs["rlexp_seeds"] for t in trials] == [[5, 6, 7, 8]] * 2
    assert [t.user_attrs["rlexp_job"] for t in trials] == [0, 4]
    for t in trials:
        x = t.params["x"]
        assert t.user_attrs["rlexp_overrides"] == [f"x={x}"]
        for job, seed in zip(t.user_attrs["rlexp_jobs"], [5, 6, 7, 8], strict=True):
            assert launcher.overrides[job] == [f"x={x}", f"seed={seed}"]
        # seeds return 1, 2, 3, 100 (+ x): mean 26.5, IQM (the middle two of four) 2.5
        assert t.value == pytest.approx(expected + x)
    assert len(launcher.start) == 8


def test_a_trial_with_a_failed_seed_fails_and_is_retried_on_the_same_jobs_and_seeds(tmp_path):
    sweep = tmp_path / "s"
    first = sweep_once(sweep, SeedLauncher({}, fail=(1,)), config_seed=5, n_trials=1, trial_seeds=2)
    assert [t.state for t in first.study.get_trials()] == [TrialState.FAIL]
    again = SeedLauncher({})
    second = sweep_once(sweep, again, config_seed=5, n_trials=1, trial_seeds=2)
    retry = second.study.get_trials()[1]
    assert retry.state == TrialState.COMPLETE and retry.user_attrs["rlexp_retry_of"] == 0
    assert retry.user_attrs["rlexp_jobs"] == [0, 1] and retry.user_attrs["rlexp_seeds"] == [5, 6]
    assert sorted(again.start) == [0, 1]
    assert retry.value == pytest.approx((1.0 + 2.0) / 2 + retry.params["x"])


# -- the optuna_prune hook and each pruner family -----------------------------------------------------


def eval_state(step: int, value: float) -> HookState:
    return HookState(
        point="eval_end",
        global_step=step,
        iteration=step // 100,
        total_steps=1000,
        run_dir=Path("."),
        eval_metrics={"eval/episode_return": value},
    )


class Study:
    """A journal study the sweeper would hold; ``run`` plays one trial's job through the hook."""

    def __init__(self, tmp_path: Path, pruner: dict) -> None:
        tmp_path.mkdir(parents=True, exist_ok=True)
        self.storage = f"journal://{tmp_path}/optuna.journal"
        self.pruner = pruner
        from hydra.utils import instantiate

        self.study = optuna.create_study(
            study_name="s",
            storage=optuna.storages.JournalStorage(
                optuna.storages.journal.JournalFileBackend(str(tmp_path / "optuna.journal"))
            ),
            pruner=instantiate(pruner),
            direction="maximize",
        )
        self.job = 0

    def run(self, curve: list[tuple[int, float]]) -> int | None:
        """The step the hook stopped the trial at (None: it ran to its end, told COMPLETE)."""
        trial = self.study.ask()
        trial.set_user_attr("rlexp_job", self.job)
        trial.set_user_attr("rlexp_jobs", [self.job])
        hook = OptunaPrune(self.storage, "s", self.job, self.pruner)
        self.job += 1
        for step, value in curve:
            control = HookControl({})
            hook(eval_state(step, value), control)
            if control.decisions.stop is not None:
                assert control.decisions.stop_status == "pruned"
                assert f"pruned by Optuna's {self.pruner['_target_'].rsplit('.', 1)[1]}" in control.decisions.stop  # fmt: skip
                self.study.tell(trial.number, state=TrialState.PRUNED)
                return step
        self.study.tell(trial.number, curve[-1][1])
        return None


P = "optuna.pruners."


def test_median_pruner_prunes_below_the_median_of_the_completed_trials_at_that_step(tmp_path):
    s = Study(tmp_path, {"_target_": P + "MedianPruner", "n_startup_trials": 2})
    assert s.run([(100, 10), (200, 20), (300, 30)]) is None
    assert s.run([(100, 12), (200, 22), (300, 32)]) is None
    # medians: 11 at step 100, 21 at step 200: 15 passes, the best so far (18) at 200 does not
    assert s.run([(100, 15), (200, 18), (300, 40)]) == 200
    pruned = s.study.get_trials()[2]
    assert pruned.state == TrialState.PRUNED
    assert pruned.intermediate_values == {100: 15.0, 200: 18.0}  # kept, up to the stop
    assert pruned.value == 18.0  # Optuna's value of a pruned trial: its last reported one


def test_percentile_pruner_prunes_below_its_percentile(tmp_path):
    s = Study(tmp_path, {"_target_": P + "PercentilePruner", "percentile": 75.0, "n_startup_trials": 3})  # fmt: skip
    for a, b in [(10, 20), (20, 40), (30, 60)]:
        assert s.run([(100, a), (200, b)]) is None
    # maximising, the 75th percentile keeps the top 75%: the bar is the 25th (15, then 30); the
    # median (40 at step 200) would have pruned 35 too
    assert s.run([(100, 16), (200, 35)]) is None
    assert s.run([(100, 16), (200, 29)]) == 200


def test_successive_halving_prunes_outside_the_top_half_of_a_rung(tmp_path):
    s = Study(tmp_path, {"_target_": P + "SuccessiveHalvingPruner", "min_resource": 100, "reduction_factor": 2, "min_early_stopping_rate": 0})  # fmt: skip
    assert s.run([(100, 30), (200, 30), (400, 30)]) is None  # alone at each rung: promoted
    # rung 0 (step 100): 35 is the top of [30, 35]; rung 1 (step 200): 10 is not the top of
    # [30, 10] (the top len // 2 = 1 is promoted)
    assert s.run([(100, 35), (200, 10), (400, 50)]) == 200


def test_threshold_and_patient_pruners(tmp_path):
    threshold = {"_target_": P + "ThresholdPruner", "lower": 5.0}
    s = Study(tmp_path / "t", threshold)
    assert s.run([(100, 7), (200, 6), (300, 4), (400, 9)]) == 300
    # patient (patience 1) prunes only once the best of the last two steps is below the best
    # before them, and the threshold says so: 4 at 200 is below 5, but not yet 2 steps after 7
    s = Study(tmp_path / "p", {"_target_": P + "PatientPruner", "patience": 1, "wrapped_pruner": threshold})  # fmt: skip
    assert s.run([(100, 7), (200, 4), (300, 3), (400, 9)]) == 300
    s = Study(tmp_path / "p2", {"_target_": P + "PatientPruner", "patience": 1, "wrapped_pruner": threshold})  # fmt: skip
    assert s.run([(100, 7), (200, 4), (300, 8), (400, 3)]) is None  # 8 improved on 7


def test_nop_pruner_never_prunes(tmp_path):
    s = Study(tmp_path, {"_target_": P + "NopPruner"})
    assert s.run([(100, 30), (200, 30)]) is None
    assert s.run([(100, -1e9), (200, -1e9)]) is None


def test_hyperband_prunes_as_optuna_does_on_the_same_values(tmp_path):
    cfg = {"_target_": P + "HyperbandPruner", "min_resource": 100, "max_resource": 400, "reduction_factor": 2}  # fmt: skip
    curves = [[(100, v), (200, v), (400, v)] for v in (30, 31, 32, 33, 34, 35)]
    curves += [[(100, 1), (200, 1), (400, 1)]] * 4
    # Optuna alone (no rlexp), a study of the same name, the same trials in the same order
    ref = optuna.create_study(
        study_name="s", pruner=optuna.pruners.HyperbandPruner(100, 400, 2), direction="maximize"
    )
    expected = []
    for curve in curves:
        t = ref.ask()
        stop = None
        for step, value in curve:
            t.report(value, step)
            if t.should_prune():
                stop = step
                break
        expected.append(stop)
        ref.tell(t, state=TrialState.PRUNED) if stop else ref.tell(t, curve[-1][1])
    assert any(expected), expected  # the poor trials are pruned somewhere
    s = Study(tmp_path, cfg)
    assert [s.run(c) for c in curves] == expected


def test_a_trial_of_several_seeds_reports_from_its_first_job_and_every_job_stops(tmp_path):
    threshold = {"_target_": P + "ThresholdPruner", "lower": 5.0}
    s = Study(tmp_path, threshold)
    trial = s.study.ask()
    trial.set_user_attr("rlexp_job", 4)
    trial.set_user_attr("rlexp_jobs", [4, 5])
    first, second = (OptunaPrune(s.storage, "s", job, threshold) for job in (4, 5))
    control = HookControl({})
    second(eval_state(100, 1.0), control)  # the second seed's 1.0 is not reported
    assert control.decisions.stop is None
    assert s.study.get_trials()[0].intermediate_values == {}
    first(eval_state(100, 3.0), control := HookControl({}))  # the first seed's: pruned
    assert control.decisions.stop_status == "pruned"
    assert s.study.get_trials()[0].intermediate_values == {100: 3.0}
    second(eval_state(200, 9.0), control := HookControl({}))  # the second asks: stops too
    assert control.decisions.stop_status == "pruned"


def test_a_study_the_hook_cannot_reach_is_a_warning_and_the_run_goes_on(tmp_path, caplog):
    hook = OptunaPrune(f"journal://{tmp_path}/none.journal", "s", 0, {"_target_": P + "NopPruner"})
    control = HookControl({})
    hook(eval_state(100, 1.0), control)
    assert control.decisions.stop is None
    assert "cannot reach the Optuna study 's'" in caplog.text and "without pruning" in caplog.text


# -- refusals -------------------------------------------------------------------------------------------


def spec_error(job_cfg=None, arguments=(), **sweeper) -> str:
    with pytest.raises(ValueError) as err:
        check_spec(
            {"params": {"x": "interval(0, 1)"}, "direction": "maximize", **sweeper},
            list(arguments),
            job_cfg,
        )
    assert "\n" not in str(err.value)
    return str(err.value)


def test_a_pruner_where_no_intermediate_values_are_possible_is_refused_in_one_line():
    job = OmegaConf.create(
        {
            "trainer": {"eval_every": 256, "eval_episodes": 2, "total_frames": 1024},
            "env": {"num_eval_envs": 1},
        }  # fmt: skip
    )
    check_spec(
        {"pruner": "median", "direction": "maximize"}, [], job
    )  # evaluates during training: accepted
    assert spec_error(job, ["trainer.eval_every=0"], pruner="median") == (
        "hydra.sweeper.pruner=MedianPruner: trainer.eval_every=0, so the trials never evaluate "
        "and report no intermediate values for the pruner to judge; set trainer.eval_every above "
        "0 or hydra.sweeper.pruner=null"
    )
    msg = spec_error(job, ["trainer.eval_every=4096"], pruner="successive_halving")
    assert msg.startswith("hydra.sweeper.pruner=SuccessiveHalvingPruner: trainer.eval_every=4096 >= trainer.total_frames=1024")  # fmt: skip
    no_eval = OmegaConf.merge(job, {"env": {"num_eval_envs": 0}})
    assert "env.num_eval_envs=0" in spec_error(no_eval, pruner="hyperband")
    # nop needs nothing; several objectives cannot be pruned
    check_spec({"pruner": "nop", "direction": "maximize"}, ["trainer.eval_every=0"], job)
    assert "this one has 2 directions" in spec_error(job, pruner="median", direction=["maximize", "minimize"])  # fmt: skip


def test_trial_seeds_refusals():
    assert spec_error(trial_seeds=0) == "hydra.sweeper.trial_seeds=0: a whole number >= 1"
    assert "hydra.sweeper.trial_objective='median': choose from ['mean', 'iqm']" in spec_error(trial_objective="median")  # fmt: skip
    msg = spec_error(arguments=["seed=range(0,10)"], trial_seeds=3)
    assert msg.startswith("hydra.sweeper.trial_seeds=3 gives each trial its own 3 seeds: take seed out")  # fmt: skip


def test_a_pruner_with_an_in_memory_study_is_refused(tmp_path, caplog):
    with pytest.raises(SystemExit) as exit_:
        sweep_once(tmp_path, ClockLauncher({}), storage=None, pruner="median")
    assert exit_.value.code == EXIT_REFUSED
    assert "hydra.sweeper.storage=null: the trials' jobs report to the study" in caplog.text


# -- real sweeps on the local launcher ------------------------------------------------------------------


def study_of(sweep: Path) -> optuna.Study:
    storage = optuna.storages.JournalStorage(
        optuna.storages.journal.JournalFileBackend(str(sweep / "optuna.journal"))
    )
    (name,) = optuna.get_all_study_names(storage)
    return optuna.load_study(study_name=name, storage=storage)


def status(job: Path) -> dict:
    try:
        return json.loads((job / "status.json").read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        return {}


def evals(job: Path) -> dict[int, float]:
    rows = [json.loads(x) for x in (job / "metrics.jsonl").read_text().splitlines()]
    return {r["step"]: r["eval/episode_return"] for r in rows if "eval/episode_return" in r}


def command(sweep: Path, n_trials: int, *extra: str) -> list[str]:
    return [
        "-m",
        "+sweep=ppo_optuna",
        "hydra/launcher=local",
        f"hydra.sweeper.n_trials={n_trials}",
        *SWEEP_TINY,
        "logger=none",
        *extra,
        f"hydra.sweep.dir={sweep}",
    ]


def test_a_real_sweep_prunes_its_trials_status_pruned_and_the_study_holds_pruned(tmp_path):
    """ThresholdPruner(lower=1000): InvertedPendulum's first eval (step 256) is far below, so each
    trial is pruned there: a checkpoint at 256, status pruned, the study PRUNED with that eval as
    its intermediate value (and value)."""
    sweep = tmp_path / "s"
    pruner = "+hydra.sweeper.pruner={_target_:optuna.pruners.ThresholdPruner,lower:1000}"
    proc = run_train(command(sweep, 3, pruner, "trainer.total_frames=1024"), cwd=tmp_path)
    out = proc.stdout + proc.stderr
    trials = study_of(sweep).get_trials()
    assert [t.state for t in trials] == [TrialState.PRUNED] * 3
    for t in trials:
        job = sweep / str(t.user_attrs["rlexp_job"])
        st = status(job)
        assert st["state"] == "pruned" and st["global_step"] == 256
        assert "pruned by Optuna's ThresholdPruner at step 256" in st["reason"]
        assert t.intermediate_values == {256: evals(job)[256]}
        assert t.value == st["final_eval"]["eval/episode_return"] == evals(job)[256]
        assert (job / "checkpoints").is_dir() and list((job / "checkpoints").glob("*256.pt"))
        assert f"trial {t.number} (job {t.user_attrs['rlexp_job']}) pruned" in out
    assert "3 stopped early" in out and "Traceback" not in out


def _seed_for(pattern: list[int]) -> int:
    """A RandomSampler seed whose first draws of ``trainer.total_frames`` are ``pattern``."""
    from optuna.distributions import CategoricalDistribution

    dist = {"trainer.total_frames": CategoricalDistribution([256, 6144])}
    for seed in range(200):
        study = optuna.create_study(sampler=optuna.samplers.RandomSampler(seed=seed))
        if [study.ask(dist).params["trainer.total_frames"] for _ in pattern] == pattern:
            return seed
    raise AssertionError(f"no seed draws {pattern}")


def test_a_real_async_sweep_starts_the_next_trial_while_a_slow_one_trains(tmp_path):
    """Trial 0 trains 6144 env steps, trials 1-2 256: trial 2 starts (is asked) once trial 1 is
    told, before trial 0 is: no batch barrier."""
    seed = _seed_for([6144, 256, 256])
    sweep = tmp_path / "s"
    run_train(
        [
            "-m", "hydra/sweeper=optuna", "hydra/sweeper/sampler=random", "hydra/launcher=local",
            f"hydra.sweeper.sampler.seed={seed}", "hydra.sweeper.n_trials=3",
            *SWEEP_TINY, "logger=none", "trainer.eval_every=2048", "trainer.save_every=2048",
            "trainer.total_frames=choice(256,6144)", f"hydra.sweep.dir={sweep}",
        ],
        cwd=tmp_path,
    )  # fmt: skip
    t0, t1, t2 = study_of(sweep).get_trials()
    assert [t.params["trainer.total_frames"] for t in (t0, t1, t2)] == [6144, 256, 256]
    assert all(t.state == TrialState.COMPLETE for t in (t0, t1, t2))
    # the order the sweep wrote its operations to the journal, not wall-clock datetimes (a VM's
    # clock can step back between two of them): trial 2 asked after trial 1 was told, before 0
    created, finished = journal_order(sweep)
    assert finished[1] < created[2] < finished[0]
    assert status(sweep / "0")["global_step"] == 6144


def test_an_async_study_killed_mid_trial_continues_without_losing_or_doubling_a_trial(tmp_path):
    sweep = tmp_path / "s"
    cmd = command(sweep, 5)
    with Children() as children:  # the sweep's group (its jobs too) killed however this ends
        proc = children.train(cmd, tmp_path, tmp_path / "first.log")
        deadline = time.monotonic() + 240
        while status(sweep / "3").get("state") != "running":
            assert proc.poll() is None, (tmp_path / "first.log").read_text()[-3000:]
            assert time.monotonic() < deadline, "trial 3 never started"
            time.sleep(0.01)
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    before = study_of(sweep).get_trials()
    assert before[3].state == TrialState.RUNNING
    done_before = {t.number: t.value for t in before if t.state == TrialState.COMPLETE}
    assert len(done_before) >= 2  # trial 3 started once two of trials 0-2 had ended (2 workers)
    # asynchronous: trial 2 was asked when the first of trials 0 and 1 ended, not after both
    created, finished = journal_order(sweep)
    late = len(created) + len(finished) + 10**6  # not told before the kill
    assert created[2] < max(finished.get(0, late), finished.get(1, late))
    second = run_train(cmd, cwd=tmp_path)
    after = study_of(sweep).get_trials()
    # every job dir has one trial, told once; the killed trial re-run in place, none asked twice
    assert [t.user_attrs["rlexp_job"] for t in after] == [0, 1, 2, 3, 4]
    assert [t.state for t in after] == [TrialState.COMPLETE] * 5
    assert {n: after[n].value for n in done_before} == done_before
    assert after[3].params == before[3].params
    for t in after:
        st = status(sweep / str(t.user_attrs["rlexp_job"]))
        assert st["state"] == "finished" and t.value == st["final_eval"]["eval/episode_return"]
    assert sorted(p.name for p in sweep.iterdir() if p.is_dir()) == ["0", "1", "2", "3", "4"]
    assert (sweep / "3" / "train.log").read_text().count("run dir: ") == 2
    assert f"sweep {sweep}: 5 of 5 jobs finished" in second.stdout + second.stderr
