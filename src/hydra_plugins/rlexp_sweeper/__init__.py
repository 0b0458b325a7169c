"""rlexp's Hydra sweeper plugin (Hydra loads sweeper classes only from the ``hydra_plugins`` package)."""

from hydra_plugins.rlexp_sweeper.optuna_sweeper import RlexpOptunaSweeper

__all__ = ["RlexpOptunaSweeper"]
