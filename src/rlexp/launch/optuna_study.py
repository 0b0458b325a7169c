"""An Optuna sweep's study: its storage, sampler and pruner as the config names them, and its
trials as ``rlexp report`` lists them.

``hydra.sweeper.storage``:

- ``journal://PATH`` (the default: ``journal://${hydra.sweep.dir}/optuna.journal``): Optuna's
  JournalStorage with its file backend, an append-only log of operations written under a lock
  that needs no ``fcntl`` (a symlink), so it works on the NFS or Lustre file systems of a cluster,
  where SQLite's locking does not. ``journal:///abs/path`` is absolute, ``journal://rel/path``
  relative to the working directory;
- an SQLAlchemy URL (``sqlite:///PATH``, ``postgresql://...``): Optuna's RDB storage;
- ``null``: in memory; the sweep cannot be continued.

``hydra.sweeper.sampler`` / ``pruner``: a short name (:data:`SAMPLERS`, :data:`PRUNERS`) or a
``_target_`` dict of a class in ``optuna.samplers`` / ``optuna.pruners`` (a config may not import
other code). The ``hydra/sweeper/sampler=NAME`` config group holds the same dicts.
"""

from __future__ import annotations

import difflib
import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

#: The prefix of a journal-file storage in ``hydra.sweeper.storage``.
JOURNAL = "journal://"
#: The study files ``rlexp report`` looks for in a sweep dir: the default journal, then the SQLite
#: file of sweeps made before rlexp used the journal (and of ``storage=sqlite:///<dir>/optuna.db``).
STUDY_FILES = ("optuna.journal", "optuna.db")
#: The study's name when ``hydra.sweeper.study_name`` is null and the storage holds no study.
DEFAULT_STUDY = "rlexp"
#: Trial user attr: the job number (job dir name) the trial runs in.
JOB_ATTR = "rlexp_job"
#: Trial user attr of a retry: the number of the failed trial it repeats.
RETRY_ATTR = "rlexp_retry_of"
#: Trial user attr: every job dir of the trial, one per seed (``hydra.sweeper.trial_seeds``).
JOBS_ATTR = "rlexp_jobs"
#: Trial user attr: the ``seed`` each of those jobs ran with, in the same order.
SEEDS_ATTR = "rlexp_seeds"
#: Trial user attr: the trial's job overrides without ``seed=`` and the pruning hook's.
OVERRIDES_ATTR = "rlexp_overrides"
#: Trial user attr: the sweep dir (absolute) whose job dirs the trial runs in: sweeps of other dirs
#: may share the study (their trials inform the sampler, never this sweep's plan).
SWEEP_ATTR = "rlexp_sweep"

#: Short names of ``hydra.sweeper.sampler`` (also the options of ``hydra/sweeper/sampler``).
SAMPLERS = {
    "tpe": "optuna.samplers.TPESampler",
    "random": "optuna.samplers.RandomSampler",
    "cmaes": "optuna.samplers.CmaEsSampler",
    "gp": "optuna.samplers.GPSampler",
    "qmc": "optuna.samplers.QMCSampler",
    "nsgaii": "optuna.samplers.NSGAIISampler",
    "nsgaiii": "optuna.samplers.NSGAIIISampler",
    "grid": "optuna.samplers.GridSampler",
    "bruteforce": "optuna.samplers.BruteForceSampler",
}
#: Short names of ``hydra.sweeper.pruner``.
PRUNERS = {
    "nop": "optuna.pruners.NopPruner",
    "median": "optuna.pruners.MedianPruner",
    "percentile": "optuna.pruners.PercentilePruner",
    "successive_halving": "optuna.pruners.SuccessiveHalvingPruner",
    "hyperband": "optuna.pruners.HyperbandPruner",
    "threshold": "optuna.pruners.ThresholdPruner",
    "patient": "optuna.pruners.PatientPruner",
    "wilcoxon": "optuna.pruners.WilcoxonPruner",
}
#: Where a ``_target_`` of a sampler or pruner config may point.
ALLOWED_TARGETS = ("optuna.samplers.", "optuna.pruners.")


class StudyConfigError(ValueError):
    """A storage, sampler, pruner or direction the sweep cannot use; one line naming the key."""


def leaf_config(key: str, value: Any, names: Mapping[str, str]) -> dict[str, Any] | None:
    """``value`` (a short name, a ``_target_`` dict, or None) as a ``_target_`` dict whose every
    ``_target_`` (nested ones too) is in :data:`ALLOWED_TARGETS`."""
    if value is None:
        return None
    if isinstance(value, str):
        if value in names:
            return {"_target_": names[value]}
        close = difflib.get_close_matches(value, list(names), n=1)
        raise StudyConfigError(
            f"{key}={value!r} is not known; choose from {sorted(names)}"
            + (f"; did you mean {close[0]!r}?" if close else "")
            + " (or a dict with _target_)"
        )
    if not isinstance(value, Mapping) or "_target_" not in value:
        raise StudyConfigError(f"{key} must be a name from {sorted(names)} or a dict with _target_")
    _check_targets(key, value)
    return {k: v for k, v in value.items() if k != "_partial_"}


def _check_targets(key: str, node: Any) -> None:
    if isinstance(node, Mapping):
        target = node.get("_target_")
        if target is not None and not str(target).startswith(ALLOWED_TARGETS):
            raise StudyConfigError(
                f"{key}._target_={target!r}: must be inside {list(ALLOWED_TARGETS)} "
                "(a config may not import arbitrary code)"
            )
        if (
            target is not None
        ):  # and reach only a class Optuna defines there (rlexp.common.registry)
            from rlexp.common.registry import reach

            module, _, name = str(target).rpartition(".")
            try:
                found = reach(module, name, f"{key}._target_={target!r}", ALLOWED_TARGETS)
            except ValueError as exc:
                raise StudyConfigError(str(exc)) from None
            if not isinstance(found, type):
                raise StudyConfigError(f"{key}._target_={target!r}: not a sampler or pruner class")
        for k, v in node.items():
            _check_targets(f"{key}.{k}", v)
    elif isinstance(node, list):
        for i, v in enumerate(node):
            _check_targets(f"{key}[{i}]", v)


def build(cfg: dict[str, Any] | None, **kwargs: Any) -> Any:
    """The object a :func:`leaf_config` names (None for None); ``kwargs`` override its keys."""
    if cfg is None:
        return None
    from hydra.utils import instantiate

    return instantiate({**cfg, **kwargs}, _convert_="all")


def check_pruner(cfg: dict[str, Any] | None, n_objectives: int = 1) -> None:
    """A pruner prunes from one objective's intermediate values: none for several directions."""
    if cfg is None or cfg["_target_"] == PRUNERS["nop"] or n_objectives == 1:
        return
    raise StudyConfigError(
        f"hydra.sweeper.pruner={cfg['_target_']}: Optuna prunes single-objective studies only, "
        f"this one has {n_objectives} directions (hydra.sweeper.direction); set "
        "hydra.sweeper.pruner=null"
    )


def directions(direction: Any) -> list[str]:
    """``hydra.sweeper.direction`` (a word or a list of them) as Optuna's directions."""
    given = list(direction) if isinstance(direction, (list, tuple)) else [direction]
    out = [str(getattr(d, "name", d)).lower() for d in given]
    bad = [d for d in out if d not in ("minimize", "maximize")]
    if bad or not out:
        raise StudyConfigError(
            f"hydra.sweeper.direction={direction!r}: each must be maximize or minimize"
        )
    return out


def journal_path(spec: str) -> Path | None:
    """The file of a ``journal://PATH`` storage (None for another storage)."""
    return Path(spec[len(JOURNAL) :]) if spec.startswith(JOURNAL) else None


def make_storage(spec: Any) -> Any:
    """The storage ``hydra.sweeper.storage`` names: None (in memory), a JournalStorage, or the
    URL itself (Optuna opens RDB URLs); the file's folder is created."""
    if spec is None:
        return None
    if not isinstance(spec, str) or not spec:
        raise StudyConfigError(f"hydra.sweeper.storage={spec!r}: a journal:// path, a URL or null")
    path = journal_path(spec)
    if path is not None:
        from optuna.storages import JournalStorage
        from optuna.storages.journal import JournalFileBackend

        if not str(path):
            raise StudyConfigError(f"hydra.sweeper.storage={spec!r}: journal:// needs a file path")
        path.parent.mkdir(parents=True, exist_ok=True)
        return JournalStorage(JournalFileBackend(str(path)))
    if spec.startswith("sqlite:///"):
        db = spec[len("sqlite:///") :]
        if db and db != ":memory:":
            Path(db).parent.mkdir(parents=True, exist_ok=True)
    return spec


def open_study(
    storage: Any, spec: Any, study_name: str | None, wanted: list[str], sampler: Any, pruner: Any
) -> Any:
    """The study ``study_name`` in ``storage`` (created if missing) with ``wanted`` directions.
    A null name takes the storage's only study, or :data:`DEFAULT_STUDY` in an empty one."""
    import optuna

    try:
        if study_name is None and storage is not None:
            names = optuna.get_all_study_names(storage)
            if len(names) > 1:
                raise StudyConfigError(
                    f"storage {spec} holds studies {sorted(names)}: name one with "
                    "hydra.sweeper.study_name"
                )
            study_name = names[0] if names else DEFAULT_STUDY
        study = optuna.create_study(
            study_name=study_name or DEFAULT_STUDY,
            storage=storage,
            sampler=sampler,
            pruner=pruner,
            directions=wanted,
            load_if_exists=True,
        )
    except StudyConfigError:
        raise
    except Exception as exc:  # a URL it cannot open, an old schema, a file that is not a study
        raise StudyConfigError(f"cannot open the Optuna study in {spec}: {exc}") from None
    have = [d.name.lower() for d in study.directions]
    if have != wanted:
        raise StudyConfigError(
            f"study {study.study_name!r} in {spec} was created to {have}, this sweep asks "
            f"{wanted} (hydra.sweeper.direction): use a new hydra.sweep.dir or "
            "hydra.sweeper.study_name"
        )
    return study


def trial_attr(trial: Any, name: str) -> Any:
    """A trial's rlexp attr: a user attr, or the system attr sweeps before optuna 4 set."""
    value = trial.user_attrs.get(name)
    return value if value is not None else trial.system_attrs.get(name)


def job_of(trial: Any) -> int | None:
    """The job number a trial ran in (None: a trial rlexp did not launch)."""
    job = trial_attr(trial, JOB_ATTR)
    return job if isinstance(job, int) and not isinstance(job, bool) else None


def in_sweep(trial: Any, sweep_dir: str) -> bool:
    """The trial runs in ``sweep_dir`` (one without :data:`SWEEP_ATTR`: a sweep before it, or the
    only one: in every sweep dir)."""
    where = trial_attr(trial, SWEEP_ATTR)
    return where is None or where == sweep_dir


def jobs_of(trial: Any) -> list[int]:
    """Every job number of a trial (:data:`JOBS_ATTR`; a trial before it: its one job)."""
    jobs = trial_attr(trial, JOBS_ATTR)
    if isinstance(jobs, list) and jobs and all(isinstance(j, int) for j in jobs):
        return list(jobs)
    job = job_of(trial)
    return [] if job is None else [job]


def seeds_of(trial: Any) -> list[int]:
    """The seeds of a trial's jobs (:data:`SEEDS_ATTR`; [] for a trial that did not record them)."""
    seeds = trial_attr(trial, SEEDS_ATTR)
    return list(seeds) if isinstance(seeds, list) else []


def overrides_of(trial: Any) -> list[str]:
    """A trial's overrides (:data:`OVERRIDES_ATTR`): its parameters, then the fixed overrides."""
    overrides = trial_attr(trial, OVERRIDES_ATTR)
    return [str(o) for o in overrides] if isinstance(overrides, list) else []


def study_file(sweep_dir: Path) -> Path | None:
    """The study file of the sweep in ``sweep_dir`` (:data:`STUDY_FILES`), if there is one."""
    return next((sweep_dir / f for f in STUDY_FILES if (sweep_dir / f).is_file()), None)


def read_trials(sweep_dir: Path) -> list[dict[str, Any]] | str:
    """The trials of the study in the sweep dir (number, job, state, values, params, retry_of), or
    why they cannot be read. Only loads: a study is never created or changed."""
    path = study_file(sweep_dir)
    if path is None:
        return f"no {' or '.join(STUDY_FILES)} in the sweep dir"
    try:
        import optuna

        optuna.logging.set_verbosity(optuna.logging.WARNING)
        storage = make_storage(
            f"{JOURNAL}{path}" if path.suffix == ".journal" else f"sqlite:///{path}"
        )
        out = []
        for name in optuna.get_all_study_names(storage):
            study = optuna.load_study(study_name=name, storage=storage)
            for t in study.get_trials(deepcopy=False):
                out.append(
                    {
                        "study": name,
                        "number": t.number,
                        "job": job_of(t),
                        "state": t.state.name,
                        "values": t.values,
                        "params": dict(t.params),
                        "retry_of": trial_attr(t, RETRY_ATTR),
                    }
                )
        return out
    except ImportError as exc:
        return str(exc)
    except Exception as exc:  # a damaged or foreign file: the report goes on without it
        return f"{path.name} is not readable ({type(exc).__name__}: {str(exc).splitlines()[0]})"
