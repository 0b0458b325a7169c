"""The end of a sweep: which jobs finished, which failed and why, and the sweep's exit code.

A Hydra callback, registered in ``conf/config.yaml`` (``hydra.callbacks.rlexp_sweep``). A sweep job
that fails records ``failed`` and its reason in its own ``status.json`` and returns, so the launcher
goes on with the other jobs (``rlexp.app._task``). When the sweeper is done, ``on_multirun_end``
reads the job dirs against the jobs the sweep was to run (``rlexp.report``: the basic sweeper's
grid, Optuna's ``n_trials``), logs one line, and exits with :data:`EXIT_JOBS_FAILED` when a job
failed or never started. It runs in the process that launched the sweep (basic, joblib, submitit
launchers alike). In a single run (no ``-m``) Hydra instantiates it too; it does nothing there.
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

log = logging.getLogger(__name__)

#: The exit code of ``python train.py -m ...`` when a job failed or never started (0: all finished).
EXIT_JOBS_FAILED = 1
#: Failed jobs named in the summary line; the rest are counted (``rlexp report`` lists them all).
MAX_NAMED = 10


def _config_loader() -> Any:
    """The sweep's config loader (it expands ``glob(...)`` over config groups), if Hydra has one."""
    from hydra.core.global_hydra import GlobalHydra

    gh = GlobalHydra.instance()
    return gh.config_loader() if gh.is_initialized() else None


def summarize_sweep(sweep_dir: Path, config: DictConfig) -> tuple[str, bool]:
    """(one line on how the sweep's jobs ended, whether they all finished)."""
    from rlexp.report import plan_from_config, read_sweep

    plan = plan_from_config(config, _config_loader())
    sweep = read_sweep(sweep_dir, metric=None, plan=plan)
    jobs = sweep.planned
    failed = [j for j in jobs if j.state != "finished"]
    total = len(plan.jobs) if plan.jobs is not None else len(jobs)
    line = f"sweep {sweep_dir}: {len(jobs) - len(failed)} of {total} jobs finished"
    if failed:
        named = ", ".join(f"{j.path} ({j.why})" for j in failed[:MAX_NAMED])
        more = f" and {len(failed) - MAX_NAMED} more" if len(failed) > MAX_NAMED else ""
        line += f"; {len(failed)} failed: {named}{more}"
    never = sweep.never_started
    if never:
        named = ", ".join(f"#{e.num} ({e.label})" for e in never[:MAX_NAMED])
        more = f" and {len(never) - MAX_NAMED} more" if len(never) > MAX_NAMED else ""
        line += f"; {len(never)} never started: {named}{more}"
    ok = not failed and not never
    if not ok:
        line += f" (rlexp report {sweep_dir})"
    return line, ok


def check_same_sweep(sweep_dir: Path, config: DictConfig) -> None:
    """A sweep dir that holds another sweep (other overrides) is refused before anything is written:
    its ``multirun.yaml`` would be replaced and ``rlexp report`` would then expect jobs that never
    ran. Re-running the same sweep (to finish or skip its jobs) is fine."""
    path = sweep_dir / "multirun.yaml"
    if not path.is_file():
        return
    try:
        old = list(OmegaConf.load(path).hydra.overrides.task)
    except Exception:
        return  # unreadable: nothing to compare with (rlexp report names it)
    new = list(config.hydra.overrides.task)
    if sorted(old) != sorted(new):
        gone = sorted(set(old) - set(new))
        added = sorted(set(new) - set(old))
        log.error(
            "sweep dir %s holds another sweep (its overrides differ: %s%s); use a new "
            "hydra.sweep.dir, or re-run that sweep with its own overrides",
            sweep_dir,
            f"there {gone}" if gone else "",
            f"{'; ' if gone else ''}here {added}" if added else "",
        )
        sys.exit(2)


class SweepSummary(Callback):
    """``hydra.callbacks``: the sweep's ``multirun.yaml`` at its start, its summary at its end."""

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        """Save the sweep's config as ``multirun.yaml``, as Hydra's basic sweeper does (the Optuna
        sweeper does not): ``rlexp report`` reads from it how many jobs the sweep was to run."""
        sweep_dir = Path(str(config.hydra.sweep.dir))
        check_same_sweep(sweep_dir, config)
        try:
            sweep_dir.mkdir(parents=True, exist_ok=True)
            OmegaConf.save(config, sweep_dir / "multirun.yaml")
        except OSError as exc:
            log.warning("could not write multirun.yaml: %s", exc)

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        """Log how the jobs ended; exit :data:`EXIT_JOBS_FAILED` if any failed or never started."""
        line, ok = summarize_sweep(Path(str(config.hydra.sweep.dir)), config)
        if ok:
            log.info("%s", line)
            return
        log.error("%s", line)
        sys.exit(EXIT_JOBS_FAILED)
