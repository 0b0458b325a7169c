"""``hydra/launcher=slurm``: hydra-submitit-launcher's SLURM launcher + rlexp's preemption requeue."""

from hydra_plugins.hydra_submitit_launcher.submitit_launcher import SlurmLauncher

from rlexp.launch.slurm import RequeueOnPreemption


class RlexpSlurmLauncher(RequeueOnPreemption, SlurmLauncher):
    """Submits each sweep job as a SLURM array task; a job stopped by SLURM's signal requeues."""
