"""rlexp's Optuna sweeper on Optuna >= 4 (#30 item 10): Hydra's sweep grammar as Optuna
distributions (against literals), samplers and pruners named in config, the journal, SQLite and
in-memory storages, the sweep loop with a stand-in launcher (in process: fast), and
``hydra/sweeper=optuna`` in a real ``python train.py -m`` that continues its study."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import optuna
import pytest
from hydra.core.utils import JobReturn, JobStatus
from omegaconf import OmegaConf
from optuna.distributions import CategoricalDistribution as Cat
from optuna.distributions import FloatDistribution as Float
from optuna.distributions import IntDistribution as Int

from conftest import CONF_DIR, SWEEP_TINY, run_train
from rlexp.launch import optuna_space, optuna_study
from rlexp.launch.optuna_sweeper import EXIT_REFUSED, OptunaSweep

# -- the search space: Hydra's grammar -> Optuna's distributions -----------------------------------


@pytest.mark.parametrize(
    ("line", "expected"),
    [
        ("x=choice(0.1, 0.2)", Cat([0.1, 0.2])),
        ("x=0.1,0.2", Cat([0.1, 0.2])),
        ("x=choice(a, b, true, 3)", Cat(["a", "b", True, 3])),
        ("x=choice([1,2],[3])", Cat(["[1,2]", "[3]"])),  # as override text
        ("x=range(1, 10)", Int(1, 9)),  # Hydra's range: the end is excluded
        ("x=range(1, 10, 3)", Int(1, 7, step=3)),
        ("x=range(10, 1, -3)", Int(4, 10, step=3)),
        ("x=range(0.5, 2.0, 0.5)", Float(0.5, 1.5, step=0.5)),
        ("x=interval(0, 1)", Float(0.0, 1.0)),
        ("x=tag(log, interval(1e-5, 1e-3))", Float(1e-5, 1e-3, log=True)),
        ("x=tag(int, interval(1, 64))", Int(1, 64)),
        ("x=tag(int, log, interval(1, 1024))", Int(1, 1024, log=True)),
    ],
)
def test_a_sweep_override_becomes_its_optuna_distribution(line, expected):
    dists, fixed = optuna_space.search_space([line])
    assert dists == {"x": expected} and fixed == {}


def test_shuffle_is_a_choice_and_plain_values_are_fixed_as_written():
    dists, fixed = optuna_space.search_space(
        ["x=shuffle(range(1, 4))", "seed=3", "+sweep=ppo_optuna", "y=choice(1, 2)", "y=5"]
    )
    assert list(dists) == ["x"] and sorted(dists["x"].choices) == [1, 2, 3]
    # the command line (later) wins over hydra.sweeper.params (earlier): y is fixed
    assert fixed == {"seed": "seed=3", "+sweep": "+sweep=ppo_optuna", "y": "y=5"}


@pytest.mark.parametrize(
    ("line", "message"),
    [
        ("x=tag(foo, interval(0, 1))", "x=tag(foo, interval(0, 1)): unknown tag(s) ['foo']"),
        ("env=glob(*)", "env=glob(*): Glob cannot be sampled by Optuna; write env=choice(...)"),
        ("x=range(3, 1)", "x=range(3, 1): the range is empty"),
        ("x=choice(1,", "x=choice(1,: no viable alternative at input"),
    ],
)
def test_what_optuna_cannot_sample_is_one_line_naming_the_key(line, message):
    with pytest.raises(optuna_space.SearchSpaceError) as err:
        optuna_space.search_space([line])
    assert message in str(err.value) and "\n" not in str(err.value)


def test_the_deprecated_search_space_dicts_and_the_grid():
    assert optuna_space.from_dict("a", {"type": "float", "low": 1e-4, "high": 1e-2, "log": True}) == Float(1e-4, 1e-2, log=True)  # fmt: skip
    assert optuna_space.from_dict("b", {"type": "int", "low": 2, "high": 8, "step": 2}) == Int(2, 8, step=2)  # fmt: skip
    assert optuna_space.from_dict("c", {"type": "categorical", "choices": ["x", 1]}) == Cat(["x", 1])  # fmt: skip
    with pytest.raises(ValueError, match=r"search_space.d.type='normal': choose from int, float"):
        optuna_space.from_dict("d", {"type": "normal"})
    assert optuna_space.grid_choices("a", Int(1, 7, step=3)) == [1, 4, 7]
    assert optuna_space.grid_choices("b", Float(0.5, 1.5, step=0.5)) == [0.5, 1.0, 1.5]
    assert optuna_space.grid_choices("c", Cat(["p", "q"])) == ["p", "q"]
    with pytest.raises(ValueError, match="c: the grid sampler needs choice"):
        optuna_space.grid_choices("c", Float(0, 1))
    # a trial's overrides: its parameters in the search space's order, then the fixed ones
    params = {"b": 2, "a": 0.5, "z": "q"}
    assert optuna_space.trial_overrides(params, ["a", "b"], {"+s": "+s=x"}) == (
        "a=0.5", "b=2", "z=q", "+s=x",
    )  # fmt: skip


# -- samplers, pruners, directions ------------------------------------------------------------------


def test_samplers_and_pruners_are_named_by_short_names_or_allowlisted_targets():
    leaf = optuna_study.leaf_config
    assert leaf("s", "tpe", optuna_study.SAMPLERS) == {"_target_": "optuna.samplers.TPESampler"}
    grid = {"_target_": "optuna.samplers.GridSampler", "_partial_": True}  # hydra-optuna-sweeper's
    assert leaf("s", grid, optuna_study.SAMPLERS) == {"_target_": "optuna.samplers.GridSampler"}
    with pytest.raises(ValueError, match=r"hydra.sweeper.sampler='tpx' is not known.*did you mean 'tpe'"):  # fmt: skip
        leaf("hydra.sweeper.sampler", "tpx", optuna_study.SAMPLERS)
    evil = {"_target_": "os.system", "command": "true"}
    with pytest.raises(ValueError, match=r"hydra.sweeper.sampler._target_='os.system': must be inside"):  # fmt: skip
        leaf("hydra.sweeper.sampler", evil, optuna_study.SAMPLERS)
    nested = {"_target_": "optuna.samplers.CmaEsSampler", "independent_sampler": evil}
    with pytest.raises(ValueError, match=r"sampler.independent_sampler._target_='os.system'"):
        leaf("sampler", nested, optuna_study.SAMPLERS)
    # a pruner judges one objective's intermediate values (the jobs report them, #50): refused
    # for a multi-objective study only
    optuna_study.check_pruner(leaf("p", "nop", optuna_study.PRUNERS), 2)
    optuna_study.check_pruner(None, 2)
    optuna_study.check_pruner(leaf("p", "median", optuna_study.PRUNERS), 1)
    with pytest.raises(ValueError) as err:
        optuna_study.check_pruner(leaf("p", "median", optuna_study.PRUNERS), 2)
    assert "hydra.sweeper.pruner=optuna.pruners.MedianPruner" in str(err.value)
    assert "this one has 2 directions" in str(err.value)
    assert optuna_study.directions("MAXIMIZE") == ["maximize"]
    assert optuna_study.directions(["maximize", "minimize"]) == ["maximize", "minimize"]
    with pytest.raises(ValueError, match="hydra.sweeper.direction='up'"):
        optuna_study.directions("up")


@pytest.mark.parametrize(
    "override",
    [
        *(f"hydra/sweeper={p.stem}" for p in sorted((CONF_DIR / "hydra/sweeper").glob("*.yaml"))),
        *(
            f"hydra/sweeper/sampler={p.stem}"
            for p in sorted((CONF_DIR / "hydra/sweeper/sampler").glob("*.yaml"))
        ),
    ],
)
def test_every_sweeper_and_sampler_config_composes_and_builds(override):
    """Each file composes into rlexp's sweeper, and its sampler is built by Optuna with the keys
    the file gives (a key Optuna's class lacks would fail here, not in a user's sweep)."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from rlexp.config.schema import register_configs

    register_configs()
    GlobalHydra.instance().clear()
    sweeper_first = [] if override.startswith("hydra/sweeper=") else ["hydra/sweeper=optuna"]
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("config", overrides=[*sweeper_first, override], return_hydra_config=True)
    node = cfg.hydra.sweeper
    assert node._target_ == "hydra_plugins.rlexp_sweeper.optuna_sweeper.RlexpOptunaSweeper"
    assert OmegaConf.to_container(node, resolve=False)["storage"].endswith("/optuna.journal")
    sampler_cfg = optuna_study.leaf_config("s", OmegaConf.to_container(node.sampler), optuna_study.SAMPLERS)  # fmt: skip
    extra = {"search_space": {"x": [1, 2]}} if sampler_cfg["_target_"].endswith("GridSampler") else {}  # fmt: skip
    sampler = optuna_study.build(sampler_cfg, **extra)
    assert isinstance(sampler, optuna.samplers.BaseSampler)
    assert type(sampler).__name__ == sampler_cfg["_target_"].rsplit(".", 1)[1]


# -- the sweep loop, in process, with a stand-in launcher --------------------------------------------


class Launcher:
    """Hydra's launcher interface: each job's value is ``x`` (job dirs are numbered from
    ``initial_job_idx``); ``fail`` lists job numbers that fail (rlexp's task returns None)."""

    def __init__(self, fail: tuple[int, ...] = ()) -> None:
        self.fail = fail
        self.jobs: list[tuple[int, tuple[str, ...]]] = []

    def launch(self, job_overrides, initial_job_idx):
        returns = []
        for i, overrides in enumerate(job_overrides):
            job = initial_job_idx + i
            self.jobs.append((job, tuple(overrides)))
            values = dict(o.split("=", 1) for o in overrides)
            value = None if job in self.fail else float(values.get("x", 0.0))
            returns.append(JobReturn(status=JobStatus.COMPLETED, _return_value=value))
        return returns


PARAMS = {"x": "interval(0, 1)", "y": "choice(a, b, c)"}


def sweep_once(
    sweep_dir: Path, launcher: Launcher, arguments: tuple[str, ...] = (), **cfg
) -> OptunaSweep:
    """One run of rlexp's sweeper over ``sweep_dir`` (the journal default unless ``storage``)."""
    sweep_dir.mkdir(parents=True, exist_ok=True)
    config = {
        "sampler": {"_target_": "optuna.samplers.RandomSampler", "seed": 7},
        "direction": "maximize",
        "storage": f"journal://{sweep_dir}/optuna.journal",
        "study_name": None,
        "n_trials": 3,
        "n_jobs": 2,
        "params": PARAMS,
        **cfg,
    }
    sweeper = OptunaSweep(**config)
    sweeper.bind(OmegaConf.create({"hydra": {"sweep": {"dir": str(sweep_dir)}}}), launcher)
    sweeper.sweep(list(arguments))
    return sweeper


def draws(sampler: optuna.samplers.BaseSampler, n: int) -> list[dict]:
    """What ``sampler`` proposes for PARAMS' space in a fresh in-memory study, ``n`` trials."""
    dists, _ = optuna_space.search_space([f"{k}={v}" for k, v in PARAMS.items()])
    study = optuna.create_study(sampler=sampler, direction="maximize")
    return [study.ask(dists).params for _ in range(n)]


def test_a_seeded_sampler_named_in_config_reaches_the_study(tmp_path):
    first, again = Launcher(), Launcher()
    sweeper = sweep_once(tmp_path / "a", first, ("z=1",), pruner="nop")
    sweep_once(tmp_path / "b", again, ("z=1",), pruner="nop")
    assert isinstance(sweeper.study.sampler, optuna.samplers.RandomSampler)
    assert isinstance(sweeper.study.pruner, optuna.pruners.NopPruner)
    assert first.jobs == again.jobs  # the same seed, the same trials
    proposed = [dict(o.split("=", 1) for o in overrides) for _, overrides in first.jobs]
    expected = draws(optuna.samplers.RandomSampler(seed=7), 3)
    assert [{"x": float(p["x"]), "y": p["y"]} for p in proposed] == expected
    assert [job for job, _ in first.jobs] == [0, 1, 2]
    assert all(overrides[-1] == "z=1" for _, overrides in first.jobs)
    other = Launcher()
    sweep_once(tmp_path / "c", other, ("z=1",), sampler={"_target_": "optuna.samplers.RandomSampler", "seed": 8})  # fmt: skip
    assert other.jobs != first.jobs
    named = sweep_once(tmp_path / "d", Launcher(), sampler="qmc", n_trials=1)
    assert isinstance(named.study.sampler, optuna.samplers.QMCSampler)


def test_a_journal_study_resumes_retries_and_reseeds_in_process(tmp_path):
    sweep = tmp_path / "sweep"
    first = sweep_once(sweep, Launcher(fail=(1,)))
    trials = first.study.get_trials()
    assert [t.state.name for t in trials] == ["COMPLETE", "FAIL", "COMPLETE"]
    assert [t.user_attrs["rlexp_job"] for t in trials] == [0, 1, 2]
    assert (sweep / "optuna.journal").is_file() and not (sweep / "optuna.db").exists()

    # the same sweep again with n_trials=4: job 1 retried with its parameters, one new trial, the
    # sampler reseeded with seed + trials so far (7 + 3): its first draw is RandomSampler(10)'s
    launcher = Launcher()
    second = sweep_once(sweep, launcher, n_trials=4)
    assert [job for job, _ in launcher.jobs] == [1, 3]
    trials = second.study.get_trials()
    assert [t.state.name for t in trials] == [
        "COMPLETE",
        "FAIL",
        "COMPLETE",
        "COMPLETE",
        "COMPLETE",
    ]
    assert trials[3].params == trials[1].params
    x = trials[1].params["x"]  # the retry's record: its job dir, seed (the config's: 0), overrides
    assert trials[3].user_attrs == {"rlexp_job": 1, "rlexp_retry_of": 1, "rlexp_jobs": [1], "rlexp_seeds": [0], "rlexp_overrides": [f"x={x}", f"y={trials[1].params['y']}"], "rlexp_sweep": str(sweep.resolve())}  # fmt: skip
    assert trials[4].params == draws(optuna.samplers.RandomSampler(seed=10), 1)[0]
    results = OmegaConf.load(sweep / "optimization_results.yaml")
    best = max((t for t in trials if t.value is not None), key=lambda t: t.value)
    assert (results.best_value, results.best_trial, results.best_job) == (best.value, best.number, best.user_attrs["rlexp_job"])  # fmt: skip

    # read back as `rlexp report` does, from the journal alone
    table = optuna_study.read_trials(sweep)
    assert [(t["number"], t["job"], t["state"], t["retry_of"]) for t in table] == [
        (0, 0, "COMPLETE", None), (1, 1, "FAIL", None), (2, 2, "COMPLETE", None),
        (3, 1, "COMPLETE", 1), (4, 3, "COMPLETE", None),
    ]  # fmt: skip


def test_sqlite_storage_and_a_pre_journal_optuna_db_are_continued(tmp_path):
    db = tmp_path / "x" / "study.db"
    first = sweep_once(tmp_path / "x", Launcher(), storage=f"sqlite:///{db}", study_name="s")
    assert db.is_file() and len(first.study.trials) == 3
    launcher = Launcher()
    sweep_once(tmp_path / "x", launcher, storage=f"sqlite:///{db}", study_name="s", n_trials=4)
    assert [job for job, _ in launcher.jobs] == [3]
    # a sweep dir whose study an rlexp before the journal kept in optuna.db: the default storage
    # continues it there (no journal is started beside it)
    old = tmp_path / "old"
    old.mkdir()
    study = optuna.create_study(study_name="ppo", storage=f"sqlite:///{old / 'optuna.db'}", direction="maximize")  # fmt: skip
    trial = study.ask({"x": Float(0, 1), "y": Cat(["a", "b", "c"])})
    study._storage.set_trial_system_attr(trial._trial_id, "rlexp_job", 0)  # as optuna 2 stored it
    study.tell(trial, 0.5)
    launcher = Launcher()
    continued = sweep_once(old, launcher, n_trials=2)
    assert [job for job, _ in launcher.jobs] == [1] and not (old / "optuna.journal").exists()
    assert continued.storage == f"sqlite:///{old / 'optuna.db'}"
    assert [t["job"] for t in optuna_study.read_trials(old)] == [0, 1]


def test_the_grid_sampler_walks_its_grid_once(tmp_path):
    launcher = Launcher()
    params = {"x": "choice(0.1, 0.2)", "y": "range(1, 3)"}
    sweeper = sweep_once(tmp_path, launcher, sampler="grid", params=params, n_trials=10)
    assert sweeper.n_trials == 4  # capped at the size of the grid
    seen = {overrides[:2] for _, overrides in launcher.jobs}
    assert seen == {("x=0.1", "y=1"), ("x=0.1", "y=2"), ("x=0.2", "y=1"), ("x=0.2", "y=2")}
    assert [t.state.name for t in sweeper.study.trials] == ["COMPLETE"] * 4


def custom_space(cfg, trial) -> None:
    """A ``custom_search_space`` function: one more parameter, suggested on each trial."""
    trial.suggest_int("w", 1, 3)


def test_custom_search_space_and_an_in_memory_study(tmp_path, caplog):
    launcher = Launcher()
    sweeper = sweep_once(
        tmp_path, launcher, storage=None, custom_search_space=f"{__name__}.custom_space"
    )
    assert "cannot be continued" in caplog.text and not (tmp_path / "optuna.journal").exists()
    assert all(re.fullmatch(r"w=[123]", overrides[2]) for _, overrides in launcher.jobs)
    assert all("w" in t.params for t in sweeper.study.trials)


def test_a_study_of_another_direction_is_refused_in_one_line(tmp_path, caplog):
    sweep_once(tmp_path, Launcher(), n_trials=1)
    with pytest.raises(SystemExit) as exit_:
        sweep_once(tmp_path, Launcher(), direction="minimize")
    assert exit_.value.code == EXIT_REFUSED
    assert "was created to ['maximize'], this sweep asks ['minimize']" in caplog.text


def test_a_bad_sweeper_config_is_refused_before_the_sweep_starts(tmp_path):
    from rlexp.config.validate import ConfigError
    from rlexp.launch.precheck import precheck

    base = ["-m", "hydra/sweeper=optuna", f"hydra.sweep.dir={tmp_path / 's'}", "seed=0"]
    for extra, message in [
        (
            ["hydra.sweeper.pruner=median", "trainer.eval_every=0"],
            "hydra.sweeper.pruner=MedianPruner: trainer.eval_every=0, so the trials never evaluate",
        ),
        (["hydra.sweeper.sampler=tpx"], "did you mean 'tpe'"),
        (["algorithm.lr=tag(lg,interval(1e-4,1e-2))"], "unknown tag(s) ['lg']"),
        (["hydra.sweeper.max_failure_rate=2"], "hydra.sweeper.max_failure_rate=2"),
    ]:
        with pytest.raises(ConfigError, match=re.escape(message)):
            precheck([*base, *extra], CONF_DIR)
    assert not (tmp_path / "s").exists()


# -- hydra/sweeper=optuna in python train.py -m ------------------------------------------------------


def test_hydra_sweeper_optuna_runs_rlexps_sweeper_and_continues_its_journal(tmp_path):
    """The spelling users typed for hydra-optuna-sweeper runs rlexp's sweeper on optuna >= 4; its
    study is the journal in the sweep dir; the same command with n_trials=4 on the parallel local
    launcher keeps the 2 trials and their dirs, and runs 2 new ones together (jobs 2 and 3)."""
    sweep = tmp_path / "sweep"

    def command(n: int, *extra: str) -> list[str]:
        return [
            "-m", "hydra/sweeper=optuna", f"hydra.sweeper.n_trials={n}", "hydra.sweeper.n_jobs=2",
            "hydra.sweeper.sampler.seed=0", "algorithm.lr=tag(log, interval(1e-4, 1e-3))",
            "algorithm.clip_epsilon=choice(0.1, 0.2)", *extra, *SWEEP_TINY, "logger=none",
            f"hydra.sweep.dir={sweep}",
        ]  # fmt: skip

    run_train(command(2), cwd=tmp_path)
    assert int(optuna.__version__.split(".")[0]) >= 4
    multirun = OmegaConf.load(sweep / "multirun.yaml")
    assert multirun.hydra.sweeper._target_.startswith("hydra_plugins.rlexp_sweeper.")
    storage = optuna.storages.JournalStorage(
        optuna.storages.journal.JournalFileBackend(str(sweep / "optuna.journal"))
    )
    study = optuna.load_study(study_name="rlexp", storage=storage)
    assert [t.state.name for t in study.trials] == ["COMPLETE"] * 2
    assert study.direction == optuna.study.StudyDirection.MAXIMIZE
    before = {n: (sweep / n / "status.json").read_bytes() for n in ("0", "1")}

    second = run_train(command(4, "hydra/launcher=local"), cwd=tmp_path)
    out = second.stdout + second.stderr
    assert "2 trial(s) kept, 0 killed to re-run, 0 failed to retry, 2 new (n_trials=4)" in out
    study = optuna.load_study(study_name="rlexp", storage=storage)
    assert [t.state.name for t in study.trials] == ["COMPLETE"] * 4
    for t in study.trials:
        job = sweep / str(t.user_attrs["rlexp_job"])
        status = json.loads((job / "status.json").read_text())
        assert status["state"] == "finished"
        assert t.value == status["final_eval"]["eval/episode_return"]
        ran = OmegaConf.load(job / ".hydra" / "overrides.yaml")
        assert ran[:2] == [f"algorithm.lr={t.params['algorithm.lr']}", f"algorithm.clip_epsilon={t.params['algorithm.clip_epsilon']}"]  # fmt: skip
        assert math.isclose(OmegaConf.load(job / "config.yaml").algorithm.lr, t.params["algorithm.lr"])  # fmt: skip
    assert [t.user_attrs["rlexp_job"] for t in study.trials] == [0, 1, 2, 3]
    assert {n: (sweep / n / "status.json").read_bytes() for n in ("0", "1")} == before
    launcher = OmegaConf.load(sweep / "multirun.yaml").hydra.launcher
    assert launcher._target_.endswith("RlexpJoblibLauncher")


def test_a_left_over_hydra_optuna_sweeper_is_named_with_its_fix(monkeypatch):
    """pip does not remove hydra-optuna-sweeper when rlexp's optuna extra drops it; its ConfigStore
    entries then clash with rlexp's hydra/sweeper files (Hydra checks them against its schemas),
    and the one line says to uninstall it."""
    from rlexp import extras

    message = "Error merging 'hydra/sweeper/sampler/tpe' with schema: Incompatible value 'None'"
    plugin = "hydra_plugins.hydra_optuna_sweeper"
    monkeypatch.setattr(extras, "_installed", lambda module: module == plugin)
    assert extras.hint(message).endswith(
        "(hydra-optuna-sweeper is installed and clashes with rlexp's own hydra/sweeper=optuna "
        "(Hydra checks rlexp's files against the plugin's schemas): pip uninstall -y "
        "hydra-optuna-sweeper (rlexp's optuna extra no longer uses it; docs/sweeps.md, Optuna))"
    )
    assert extras.hint("Error merging 'env/hopper' with schema") == "Error merging 'env/hopper' with schema"  # fmt: skip
    monkeypatch.setattr(extras, "_installed", lambda module: module != plugin)
    assert extras.hint(message) == message  # not installed: nothing to remove
