"""Layer 5, entry code: ``python train.py --config-json`` (``json_entry``), the checks before Hydra
writes anything (``precheck``, ``checks``: the config built once), a sweep's summary and stop
(``sweep``, ``sweep_stop``), the job's log (``job_log``), SLURM requeue (``slurm``), the resumable
Optuna sweeper (``optuna_sweeper``, ``optuna_space``, ``optuna_study``).

May import: anything in rlexp (``app`` included).
"""
