"""The parts of ``rlexp report`` (``rlexp.analysis.report`` is its entry point and re-exports them): job
dirs (``jobs``), the sweep's plan (``plan``), statistics per configuration (``summary``),
``report.md`` / ``report.csv`` (``render``), the results per env of a sweep over envs
(``results``) and the published numbers shown next to them (``anchors``), Optuna trials
(``trials``) and ``curves.png`` / ``results.png`` (``plot``).

Part of ``analysis`` (layer 4, tools on run dirs). May import: layers 0-3 (and, lazily,
``launch.optuna_study``: the one listed exception).
"""
