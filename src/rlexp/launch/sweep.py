"""The end of a sweep: which jobs finished or stopped early, which failed and why, and the sweep's
exit code.

A Hydra callback, registered in ``conf/config.yaml`` (``hydra.callbacks.rlexp_sweep``). A sweep job
that fails records ``failed`` and its reason in its own ``status.json`` and returns, so the launcher
goes on with the other jobs (``rlexp.app._task``). When the sweeper is done, ``on_multirun_end``
reads the job dirs against the jobs the sweep was to run (``rlexp.analysis.report``: the basic sweeper's
grid, Optuna's ``n_trials``), logs one line, and exits with :data:`EXIT_JOBS_FAILED` when a job
failed or never started. A job a hook ended early (``stopped_early``, e.g. the median stopping
rule) is a result, not a failure: the line counts it as done, with its reason and the budget
saved. It runs in the process that launched the sweep (basic, joblib, submitit launchers alike).
In a single run (no ``-m``) Hydra instantiates it too; it does nothing there.
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf, open_dict, read_write

from rlexp.files.fsutil import HolderLock, atomic_write

log = logging.getLogger(__name__)

#: The exit code of ``python train.py -m ...`` when a job failed or never started (0: every job
#: finished or was stopped early by a hook).
EXIT_JOBS_FAILED = 1
#: Failed (or stopped early) jobs named in the summary line; the rest are counted (``rlexp report``
#: lists them all).
MAX_NAMED = 10


def _config_loader() -> Any:
    """The sweep's config loader (it expands ``glob(...)`` over config groups), if Hydra has one."""
    from hydra.core.global_hydra import GlobalHydra

    gh = GlobalHydra.instance()
    return gh.config_loader() if gh.is_initialized() else None


def _named(items: Sequence[Any], name: Callable[[Any], str]) -> str:
    """The first MAX_NAMED items by ``name(item)``, and how many more there are."""
    text = ", ".join(name(x) for x in items[:MAX_NAMED])
    return text + (f" and {len(items) - MAX_NAMED} more" if len(items) > MAX_NAMED else "")


def summarize_sweep(sweep_dir: Path, config: DictConfig) -> tuple[str, bool]:
    """(one line on how the sweep's jobs ended, whether none failed or went missing)."""
    from rlexp.analysis.report import budget_saved, plan_from_config, read_sweep

    plan = plan_from_config(config, _config_loader())
    sweep = read_sweep(sweep_dir, metric=None, plan=plan)
    jobs = sweep.planned
    early = [j for j in jobs if j.stopped_early]
    failed = [j for j in jobs if j.state != "finished" and not j.stopped_early]
    total = len(plan.jobs) if plan.jobs is not None else len(jobs)
    n_finished = len(jobs) - len(failed) - len(early)
    if early:  # a hook's stop is a result: counted as done, with why and what it saved
        line = (
            f"sweep {sweep_dir}: {n_finished + len(early)} of {total} jobs done: {n_finished} "
            f"finished, {len(early)} stopped early: "
            f"{_named(early, lambda j: f'{j.path} ({j.why})')}; "
            f"budget saved: {budget_saved(jobs).describe()}"
        )
    else:  # the line sweeps without hooks always had
        line = f"sweep {sweep_dir}: {n_finished} of {total} jobs finished"
    if failed:
        line += f"; {len(failed)} failed: {_named(failed, lambda j: f'{j.path} ({j.why})')}"
    never = sweep.never_started
    if never:
        line += f"; {len(never)} never started: {_named(never, lambda e: f'#{e.num} ({e.label})')}"
    ok = not failed and not never
    if not ok:
        line += f" (rlexp report {sweep_dir})"
    return line, ok


class SweepDirTaken(Exception):
    """The sweep dir holds another sweep (``claim_sweep_dir``); the message says which overrides."""


#: Held (flock) by a sweep while it checks the sweep dir and writes its ``multirun.yaml``.
CLAIM_LOCK = ".multirun.lock"


def check_same_sweep(sweep_dir: Path, config: DictConfig) -> None:
    """``SweepDirTaken`` when the sweep dir holds another sweep (other overrides): its
    ``multirun.yaml`` would be replaced and ``rlexp report`` would then expect jobs that never ran.
    Re-running the same sweep (to finish or skip its jobs) is fine."""
    path = sweep_dir / "multirun.yaml"
    if not path.is_file():
        return
    try:
        old = list(OmegaConf.load(path).hydra.overrides.task)
    except Exception:
        return  # unreadable: nothing to compare with (rlexp report names it)
    new = list(OmegaConf.select(config, "hydra.overrides.task", default=[]))
    if sorted(old) != sorted(new):
        gone = sorted(set(old) - set(new))
        added = sorted(set(new) - set(old))
        there = f"there {gone}" if gone else ""
        here = f"{'; ' if gone else ''}here {added}" if added else ""
        raise SweepDirTaken(
            f"sweep dir {sweep_dir} holds another sweep (its overrides differ: {there}{here}); "
            "use a new hydra.sweep.dir, or re-run that sweep with its own overrides"
        )


def claim_sweep_dir(sweep_dir: Path, config: DictConfig) -> None:
    """Check that ``sweep_dir`` holds no other sweep and write this one's ``multirun.yaml``, as one
    step: both under an exclusive ``flock`` on ``<sweep_dir>/.multirun.lock``. Two sweeps with
    different overrides started together into one dir once both passed the check (each checked
    before the other had written) and mixed their jobs; now the second one to take the lock sees
    the first one's ``multirun.yaml`` and gets ``SweepDirTaken``. The lock is held for
    milliseconds; the file stays (removing it would race with the next holder)."""
    with HolderLock(sweep_dir / CLAIM_LOCK).acquire(blocking=True):
        check_same_sweep(sweep_dir, config)
        # readers never see half a file
        atomic_write(sweep_dir / "multirun.yaml", lambda tmp: OmegaConf.save(config, tmp))


def _joblib_with_stop_handling(config: DictConfig) -> None:
    """The plugin's own ``hydra/launcher=joblib`` runs as rlexp's subclass, which lets the jobs
    save at their safe point on Ctrl-C / SIGTERM / SIGHUP (``rlexp.launch.sweep_stop``); the
    launcher is built from this config after this callback."""
    target = OmegaConf.select(config, "hydra.launcher._target_", default=None)
    if target == PLUGIN_JOBLIB:
        with open_dict(config), read_write(config):
            config.hydra.launcher._target_ = RLEXP_JOBLIB


def _pbt_side_by_side(config: DictConfig) -> None:
    """A PBT population (rlexp.pbt) runs all its members at once: the launcher's parallelism is
    raised to the population's size where it is lower (logged)."""
    from rlexp.pbt.config import population_size, widen_launcher

    hooks = OmegaConf.select(config, "hooks", default=None)
    size = population_size(OmegaConf.to_container(hooks, resolve=True) if hooks else None)
    if size is None:
        return
    with open_dict(config), read_write(config):
        changed = widen_launcher(config.hydra.launcher, size)
    if changed:
        log.info("PBT population of %d: %s (members run side by side)", size, ", ".join(changed))


PLUGIN_JOBLIB = "hydra_plugins.hydra_joblib_launcher.joblib_launcher.JoblibLauncher"
RLEXP_JOBLIB = "hydra_plugins.rlexp_launcher.joblib_launcher.RlexpJoblibLauncher"


class SweepSummary(Callback):
    """``hydra.callbacks``: the sweep's ``multirun.yaml`` at its start, its summary at its end."""

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        """Save the sweep's config as ``multirun.yaml``, as Hydra's basic sweeper does (the Optuna
        sweeper does not): ``rlexp report`` reads from it how many jobs the sweep was to run."""
        sweep_dir = Path(str(config.hydra.sweep.dir))
        _joblib_with_stop_handling(config)
        _pbt_side_by_side(config)
        try:
            claim_sweep_dir(sweep_dir, config)
        except SweepDirTaken as exc:
            log.error("%s", exc)
            sys.exit(2)
        except OSError as exc:
            log.warning("could not write multirun.yaml: %s", exc)

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        """Log how the jobs ended; exit :data:`EXIT_JOBS_FAILED` if any failed or never started
        (jobs stopped early by a hook are results: they don't)."""
        line, ok = summarize_sweep(Path(str(config.hydra.sweep.dir)), config)
        if ok:
            log.info("%s", line)
            return
        log.error("%s", line)
        sys.exit(EXIT_JOBS_FAILED)
