"""``hydra/launcher=local``: hydra-joblib-launcher's config, rlexp's job pool: each job in a process
of its own, so one that dies (the OOM killer) never takes the others down
(``rlexp.launch.job_pool``); its jobs stop as a single run does on Ctrl-C, SIGTERM or SIGHUP
(``rlexp.launch.sweep_stop``)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

from hydra.core.utils import JobReturn

try:
    from hydra_plugins.hydra_joblib_launcher.joblib_launcher import JoblibLauncher
except ImportError:  # hydra-joblib-launcher missing: hydra/launcher=local fails to compose
    JoblibLauncher = object  # type: ignore[assignment,misc]


class RlexpJoblibLauncher(JoblibLauncher):
    """Runs a batch of jobs, each in a process of its own, ``n_jobs`` at a time; a job that dies
    is recorded ``failed`` and the others go on. A stop signal lets the running jobs save at their
    safe point, starts no new job, and exits 128 + N."""

    def launch(
        self, job_overrides: Sequence[Sequence[str]], initial_job_idx: int
    ) -> Sequence[JobReturn]:
        from rlexp.launch.job_pool import launch_jobs

        return launch_jobs(self, job_overrides, initial_job_idx)

    def launch_stream(
        self, n_jobs: int, take: Callable[[], Any], done: Callable[[int, JobReturn], None]
    ) -> None:
        """An asynchronous Optuna sweep's jobs: the next one starts as soon as one of ``n_jobs``
        ends (``rlexp.launch.job_pool.stream_jobs``)."""
        from rlexp.launch.job_pool import stream_jobs

        stream_jobs(self, n_jobs, take, done)
