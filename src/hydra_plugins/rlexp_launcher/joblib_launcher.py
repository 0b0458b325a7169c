"""``hydra/launcher=local``: hydra-joblib-launcher's launcher whose jobs stop as a single run does on
Ctrl-C, SIGTERM or SIGHUP (``rlexp.launch.sweep_stop``)."""

from __future__ import annotations

from collections.abc import Sequence

from hydra.core.utils import JobReturn

try:
    from hydra_plugins.hydra_joblib_launcher.joblib_launcher import JoblibLauncher
except ImportError:  # hydra-joblib-launcher missing: hydra/launcher=local fails to compose
    JoblibLauncher = object  # type: ignore[assignment,misc]


class RlexpJoblibLauncher(JoblibLauncher):
    """Runs a batch of jobs in joblib (loky) worker processes, ``n_jobs`` at a time. A stop signal
    lets the running jobs save at their safe point, starts no new job, and exits 128 + N."""

    def launch(
        self, job_overrides: Sequence[Sequence[str]], initial_job_idx: int
    ) -> Sequence[JobReturn]:
        from rlexp.launch.sweep_stop import launch_stoppable

        sweep_dir = str(self.config.hydra.sweep.dir) if self.config is not None else "?"
        return launch_stoppable(
            lambda: super(RlexpJoblibLauncher, self).launch(job_overrides, initial_job_idx),
            self.joblib,
            sweep_dir,
        )
