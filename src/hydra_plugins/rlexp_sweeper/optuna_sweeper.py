"""``hydra/sweeper=rlexp_optuna``: hydra-optuna-sweeper with its study in the sweep dir, so that a
sweep can be continued (``rlexp.launch.optuna_sweeper`` has the loop; this is the plugin Hydra finds).
"""

from __future__ import annotations

from typing import Any

from hydra.plugins.sweeper import Sweeper
from hydra.types import HydraContext, TaskFunction
from omegaconf import DictConfig


class RlexpOptunaSweeper(Sweeper):
    """Takes hydra-optuna-sweeper's config (``hydra/sweeper/optuna``); optuna is imported only when
    the sweeper is built, so Hydra's plugin scan works without rlexp's ``optuna`` extra."""

    def __init__(
        self,
        sampler: Any,
        direction: Any,
        storage: Any,
        study_name: str | None,
        n_trials: int,
        n_jobs: int,
        max_failure_rate: float,
        search_space: DictConfig | None,
        custom_search_space: str | None,
        params: DictConfig | None,
    ) -> None:
        from rlexp.launch.optuna_sweeper import ResumableOptunaSweeperImpl

        self.sweeper = ResumableOptunaSweeperImpl(
            sampler,
            direction,
            storage,
            study_name,
            n_trials,
            n_jobs,
            max_failure_rate,
            search_space,
            custom_search_space,
            params,
        )

    def setup(
        self, *, hydra_context: HydraContext, task_function: TaskFunction, config: DictConfig
    ) -> None:
        self.sweeper.setup(hydra_context=hydra_context, task_function=task_function, config=config)

    def sweep(self, arguments: list[str]) -> None:
        return self.sweeper.sweep(arguments)
