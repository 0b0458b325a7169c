"""rlexp's Hydra sweeper plugin (Hydra loads sweeper classes only from the ``hydra_plugins``
package) and the schema of its config."""

from hydra_plugins.rlexp_sweeper import config
from hydra_plugins.rlexp_sweeper.optuna_sweeper import RlexpOptunaSweeper

__all__ = ["RlexpOptunaSweeper", "config"]
