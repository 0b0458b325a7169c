"""Layer 4, tools on run dirs: ``rlexp runs`` (``runs``, ``run_files``, dead-run rules in
``liveness``), ``rlexp compare`` (``compare``), ``rlexp report`` (``report`` and its parts in the
``reporting`` package), statistics (``stats``: IQM, bootstrap, probability of improvement).

May import: layers 0-3.
"""
