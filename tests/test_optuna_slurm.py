"""An asynchronous Optuna study on SLURM (#50 item 1): two SLURM jobs at a time, each a trial, both
reporting their evaluations to the sweep dir's journal from their own job processes (the pruning
hook), the sweep's process asking and telling. Marked ``slurm``: skipped when no cluster answers
(``sudo scripts/local-slurm.sh start``; ``make test-slurm``)."""

from __future__ import annotations

import json

import optuna
import pytest
from optuna.trial import TrialState
from test_slurm import SLURM, TINY, cluster, finish, sweep  # noqa: F401  (cluster: a fixture)

from conftest import journal_order


@pytest.mark.slurm
def test_two_slurm_jobs_share_the_journal_of_an_async_study(cluster, tmp_path, children):  # noqa: F811
    sweep_dir = tmp_path / "sweep"
    never = "+hydra.sweeper.pruner={_target_:optuna.pruners.ThresholdPruner,lower:-1e9}"
    out = finish(
        sweep(
            children,
            [
                *SLURM,
                "+sweep=ppo_optuna",
                "hydra.sweeper.n_trials=3",
                "hydra.sweeper.n_jobs=2",
                never,
                *TINY,
                "trainer.total_frames=768",
                "trainer.eval_every=256",
                "logger=none",
                f"hydra.sweep.dir={sweep_dir}",
            ],
            tmp_path,
        ),
        timeout=600,
    )
    storage = optuna.storages.JournalStorage(
        optuna.storages.journal.JournalFileBackend(str(sweep_dir / "optuna.journal"))
    )
    trials = optuna.load_study(study_name="ppo", storage=storage).get_trials()
    assert [t.state for t in trials] == [TrialState.COMPLETE] * 3, out[-3000:]
    for t in trials:
        job = sweep_dir / str(t.user_attrs["rlexp_job"])
        status = json.loads((job / "status.json").read_text())
        # written by the SLURM job itself into the shared journal, at each evaluation
        assert sorted(t.intermediate_values) == [256, 512, 768]
        assert t.value == status["final_eval"]["eval/episode_return"]
    # one SLURM job per trial (submit, not an array), the third submitted when a slot freed
    ids = {p.name for p in (sweep_dir / ".submitit").iterdir() if p.name.isdigit()}
    assert len(ids) == 3, sorted(ids)
    created, finished = journal_order(sweep_dir)  # the journal's order, not wall-clock datetimes
    assert created[2] > min(finished[0], finished[1])


@pytest.mark.slurm
def test_two_local_workers_and_two_slurm_jobs_share_one_study(cluster, tmp_path, children):  # noqa: F811
    """Two sweeps at once, one on the local launcher, one on SLURM, one journal: each runs its 3
    trials in its own dir; the study holds all 6, each with its evaluations."""
    shared = tmp_path / "shared.journal"
    common = [
        "+sweep=ppo_optuna",
        "hydra.sweeper.n_trials=3",
        "hydra.sweeper.n_jobs=2",
        f"hydra.sweeper.storage=journal://{shared}",
        "+hydra.sweeper.pruner={_target_:optuna.pruners.ThresholdPruner,lower:-1e9}",
        *TINY,
        "trainer.total_frames=768",
        "trainer.eval_every=256",
        "logger=none",
    ]
    on_slurm = sweep(children, [*SLURM, *common, f"hydra.sweep.dir={tmp_path / 'slurm'}"], tmp_path)
    local = ["hydra/launcher=local", *common, f"hydra.sweep.dir={tmp_path / 'local'}"]
    out_local = finish(sweep(children, local, tmp_path), timeout=600)
    out_slurm = finish(on_slurm, timeout=600)
    storage = optuna.storages.JournalStorage(
        optuna.storages.journal.JournalFileBackend(str(shared))
    )
    trials = optuna.load_study(study_name="ppo", storage=storage).get_trials()
    assert [t.state for t in trials] == [TrialState.COMPLETE] * 6, out_local[-2000:] + out_slurm[-2000:]  # fmt: skip
    for name in ("local", "slurm"):
        where = str((tmp_path / name).resolve())
        own = [t for t in trials if t.user_attrs["rlexp_sweep"] == where]
        assert sorted(t.user_attrs["rlexp_job"] for t in own) == [0, 1, 2]
        for t in own:
            assert sorted(t.intermediate_values) == [256, 512, 768]
            status = json.loads((tmp_path / name / str(t.user_attrs["rlexp_job"]) / "status.json").read_text())  # fmt: skip
            assert t.value == status["final_eval"]["eval/episode_return"]
