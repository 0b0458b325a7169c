"""``hydra/sweeper=optuna`` (or ``rlexp_optuna``): rlexp's resumable ask-and-tell Optuna sweeper
(``rlexp.launch.optuna_sweeper`` has the loop; this is the plugin class Hydra finds)."""

from __future__ import annotations

from typing import Any

from hydra.plugins.sweeper import Sweeper
from hydra.types import HydraContext, TaskFunction
from omegaconf import DictConfig


class RlexpOptunaSweeper(Sweeper):
    """Takes ``hydra.sweeper`` (``OptunaSweeperConfig``); optuna is imported only when the sweeper
    is built, so Hydra's plugin scan works without rlexp's ``optuna`` extra."""

    def __init__(self, **sweeper: Any) -> None:
        from rlexp.extras import require

        require("optuna", "hydra/sweeper=optuna (rlexp's Optuna sweeper)")
        from rlexp.launch.optuna_sweeper import OptunaSweep

        self.sweeper = OptunaSweep(**sweeper)

    def setup(
        self, *, hydra_context: HydraContext, task_function: TaskFunction, config: DictConfig
    ) -> None:
        self.sweeper.setup(hydra_context=hydra_context, task_function=task_function, config=config)

    def sweep(self, arguments: list[str]) -> None:
        return self.sweeper.sweep(arguments)
