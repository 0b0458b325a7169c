"""The ``optuna_prune`` hook: a sweep trial's evaluations reported to its Optuna trial, and the
study's pruner asked whether to go on (docs/sweeps.md, "Pruning").

rlexp's Optuna sweeper (``rlexp.launch.optuna_sweeper``) adds this hook to every trial's job when
``hydra.sweeper.pruner`` names a pruner; a user never writes it. In the job's process it opens the
study's storage (the sweep's journal file, or its RDB URL: the job may run on another machine), finds
its trial (the RUNNING trial whose job dirs hold this job's number), and at each ``eval_end``:

- reports the objective (``eval/episode_return``) at the env step (``trial.report``), from the
  trial's first job only (a trial of ``hydra.sweeper.trial_seeds=N`` runs N jobs: the first seed's
  curve is the trial's);
- asks the pruner (``trial.should_prune``; every job of the trial asks, so its other seeds stop
  too) and, when it says prune, stops the run as a hook's stop does (at the next safe point, a
  checkpoint, exit 0) with status ``pruned``; the sweeper then tells the study PRUNED.

The pruner is rebuilt here from its config (an Optuna pruner is not kept in the storage) and may
only be a class of ``optuna.pruners`` (the config never imports other code). A storage that cannot
be reached is a warning: the run trains on, unpruned.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from rlexp.config.native_task import Number, ParamRule, Text
from rlexp.hooks.base import HookControl, HookState, register_hook

log = logging.getLogger(__name__)

#: The trial attrs the sweeper records (``rlexp.launch.optuna_study``: JOB_ATTR, JOBS_ATTR,
#: SWEEP_ATTR).
JOB_ATTR, JOBS_ATTR, SWEEP_ATTR = "rlexp_job", "rlexp_jobs", "rlexp_sweep"
#: Where a pruner's ``_target_`` may point.
PRUNER_MODULE = "optuna.pruners."


class _Pruner(ParamRule):
    """An Optuna pruner as a ``_target_`` dict (nested ones too) inside ``optuna.pruners``."""

    text = "a dict with _target_ optuna.pruners.<Class>"

    def check(self, value: Any, where: str, env: Any = None) -> None:
        if not isinstance(value, Mapping) or "_target_" not in value:
            raise TypeError(f"{where}={value!r} must be {self.text}")
        check_targets(value, where)


def check_targets(node: Any, where: str) -> None:
    """Every ``_target_`` under ``node`` names a class defined in ``optuna.pruners``."""
    if isinstance(node, Mapping):
        target = node.get("_target_")
        if target is not None:
            from rlexp.common.registry import reach

            module, _, name = str(target).rpartition(".")
            if not str(target).startswith(PRUNER_MODULE):
                raise ValueError(f"{where}._target_={target!r}: must be inside {PRUNER_MODULE}")
            if not isinstance(reach(module, name, f"{where}._target_", [PRUNER_MODULE]), type):
                raise ValueError(f"{where}._target_={target!r}: not a pruner class")
        for key, value in node.items():
            check_targets(value, f"{where}.{key}")
    elif isinstance(node, list):
        for i, value in enumerate(node):
            check_targets(value, f"{where}[{i}]")


def open_storage(spec: str) -> Any:
    """``journal://PATH`` as Optuna's JournalStorage (file backend), anything else as an RDB URL."""
    if spec.startswith("journal://"):
        from optuna.storages import JournalStorage
        from optuna.storages.journal import JournalFileBackend

        return JournalStorage(JournalFileBackend(spec[len("journal://") :]))
    return spec


@register_hook(
    "optuna_prune",
    points=("eval_end",),
    params={
        "storage": Text(),
        "study": Text(),
        "job": Number(ge=0, integer=True),
        "pruner": _Pruner(),
        "metric": Text(),
    },
    required=("storage", "study", "job", "pruner"),
)
class OptunaPrune:
    """Report each evaluation's ``metric`` to this job's Optuna trial; stop ``pruned`` when the
    study's pruner says so (module docstring)."""

    def __init__(
        self,
        storage: str,
        study: str,
        job: int,
        pruner: Mapping[str, Any],
        metric: str = "eval/episode_return",
    ) -> None:
        self.storage, self.study_name, self.job = str(storage), str(study), int(job)
        self.pruner_cfg = dict(pruner)
        self.metric = metric
        self._trial: tuple[Any, int] | None = None  # (the study, the trial's id)
        self._reports = False  # this job is its trial's first: its curve is the trial's
        self._broken = False  # the study could not be reached: warned once, the run goes on

    def _find_trial(self, sweep_dir: str) -> Any:
        """(the study, the trial id) of this job's RUNNING trial: its job dirs hold this job, in
        this sweep dir (``sweep_dir``, the run dir's parent; a study may be shared)."""
        import optuna
        from hydra.utils import instantiate

        optuna.logging.set_verbosity(optuna.logging.WARNING)
        pruner = instantiate(self.pruner_cfg, _convert_="all")
        study = optuna.load_study(
            study_name=self.study_name, storage=open_storage(self.storage), pruner=pruner
        )
        running = study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.RUNNING,))
        mine = [
            t
            for t in running
            if self.job in _jobs(t) and t.user_attrs.get(SWEEP_ATTR, sweep_dir) == sweep_dir
        ]
        if not mine:
            raise LookupError(f"no RUNNING trial of study {self.study_name!r} runs job {self.job}")
        frozen = max(mine, key=lambda t: t.number)
        self._reports = _jobs(frozen)[0] == self.job
        return study, frozen._trial_id

    def __call__(self, state: HookState, control: HookControl) -> None:
        if state.point != "eval_end" or state.rank != 0 or self._broken:
            return
        value = state.eval_metrics.get(self.metric)
        if value is None or not math.isfinite(float(value)):
            return
        try:
            import optuna

            if self._trial is None:
                self._trial = self._find_trial(str(Path(state.run_dir).resolve().parent))
            # a Trial reads the storage once: a fresh one sees what the trial's other jobs wrote
            trial = optuna.trial.Trial(*self._trial)
            if self._reports:
                trial.report(float(value), state.global_step)
            prune = trial.should_prune()
        except Exception as exc:  # the storage gone, the trial told meanwhile: train on, unpruned
            self._broken = True
            log.warning(
                "[hooks] %s: cannot reach the Optuna study %r in %s (%s: %s); this run goes on "
                "without pruning",
                state.hook or "optuna_prune",
                self.study_name,
                self.storage,
                type(exc).__name__,
                str(exc).splitlines()[0] if str(exc) else "",
            )
            return
        if prune:
            name = str(self.pruner_cfg["_target_"]).rsplit(".", 1)[-1]
            control.request_stop(
                f"pruned by Optuna's {name} at step {state.global_step}: {self.metric}="
                f"{float(value):.4g} (trial {trial.number})",
                status="pruned",
            )


def _jobs(trial: Any) -> list[int]:
    """The job numbers of a trial (``rlexp_jobs``, or its one ``rlexp_job``)."""
    jobs = trial.user_attrs.get(JOBS_ATTR)
    if isinstance(jobs, list) and jobs:
        return [int(j) for j in jobs]
    job = trial.user_attrs.get(JOB_ATTR)
    return [int(job)] if isinstance(job, int) else []
