"""rlexp's Hydra launcher plugin (Hydra loads launcher classes only from the ``hydra_plugins`` package)."""

from hydra_plugins.rlexp_launcher.joblib_launcher import RlexpJoblibLauncher
from hydra_plugins.rlexp_launcher.slurm_launcher import RlexpSlurmLauncher

__all__ = ["RlexpJoblibLauncher", "RlexpSlurmLauncher"]
