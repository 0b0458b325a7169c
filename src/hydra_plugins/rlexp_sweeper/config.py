"""The schema of ``hydra/sweeper=optuna`` (conf/hydra/sweeper/optuna.yaml names it first), stored
in Hydra's ConfigStore when Hydra scans its plugins: a mistyped ``hydra.sweeper.*`` key fails at
compose time. Imports neither optuna nor rlexp (Hydra imports this module in every run)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from hydra.core.config_store import ConfigStore


@dataclass
class OptunaSweeperConfig:
    """rlexp's Optuna sweeper (``rlexp.launch.optuna_sweeper``); docs/sweeps.md, "Optuna"."""

    _target_: str = "hydra_plugins.rlexp_sweeper.optuna_sweeper.RlexpOptunaSweeper"
    # The sampler and pruner dicts reach the sweeper as config, which checks their _target_
    # against its allowlist before building them (Hydra would build them on its own otherwise).
    _recursive_: bool = False
    # A short name (tpe, random, cmaes, gp, qmc, nsgaii, nsgaiii, grid, bruteforce) or a dict with
    # _target_ optuna.samplers.*; the hydra/sweeper/sampler group holds the dicts (default: tpe).
    sampler: Any = None
    # null (none), or a short name (median, percentile, successive_halving, hyperband, threshold,
    # patient, wilcoxon, nop) or a dict with _target_ optuna.pruners.*: each trial's job reports
    # its eval/episode_return at every evaluation to the study and stops (status pruned) when
    # the pruner says so (docs/sweeps.md, "Pruning").
    pruner: Any = None
    # maximize (rlexp's trials return their final eval/episode_return) or minimize; a list for
    # several objectives.
    direction: Any = "maximize"
    # journal://PATH (Optuna's JournalStorage: cluster file systems), sqlite:///PATH or another
    # SQLAlchemy URL, or null (in memory: the sweep cannot be continued).
    storage: str | None = "journal://${hydra.sweep.dir}/optuna.journal"
    # null: the storage's only study, or "rlexp" in an empty storage.
    study_name: str | None = None
    # Trials in the study in total, over every run of the same command.
    n_trials: int = 20
    # Trials asked and launched together (in parallel with hydra/launcher=local or slurm).
    n_jobs: int = 2
    # Stop asking new trials when a batch fails more than this share (1.0: never stop).
    max_failure_rate: float = 1.0
    # The search space, in Hydra's sweep syntax: {algorithm.lr: "tag(log, interval(1e-5, 1e-3))"}.
    params: dict[str, str] | None = None
    # Deprecated by Hydra 1.2 (write params): {name: {type: float, low: 0, high: 1, log: false}}.
    search_space: dict[str, Any] | None = None
    # module.function(cfg, trial) that suggests more parameters on each new trial.
    custom_search_space: str | None = None
    # true: each of the n_jobs workers takes the next trial as soon as its job ends (no barrier);
    # false: batches of n_jobs trials, the next batch asked once the whole batch is back.
    async_trials: bool = True
    # Seeds (jobs) per trial: seed, seed+1, ... (the same for every trial); the trial's value is
    # their trial_objective.
    trial_seeds: int = 1
    # How a trial of several seeds scores: mean or iqm (the interquartile mean).
    trial_objective: str = "mean"
    # After the search: re-run the top_k best trials on `seeds` seeds no trial used, as jobs of
    # the sweep (dirs 10000, ...); null: no confirmation. {top_k: 3, seeds: 5}. docs/sweeps.md,
    # "Confirmation on fresh seeds".
    confirm: Any = None


ConfigStore.instance().store(
    group="hydra/sweeper", name="optuna_schema", node=OptunaSweeperConfig, provider="rlexp"
)
