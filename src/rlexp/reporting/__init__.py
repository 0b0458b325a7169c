"""The parts of ``rlexp report`` (``rlexp.report`` is its entry point and re-exports them): job
dirs (``jobs``), the sweep's plan (``plan``), statistics per configuration (``summary``),
``report.md`` / ``report.csv`` (``render``), Optuna trials (``trials``) and ``curves.png``
(``plot``)."""
