"""Layer 0, run-dir file I/O: the one atomic write and the one holder lock (``fsutil``), bounded
readers of run-dir files (``safe_read``), the walk over ``outputs/`` and ``multirun/`` (``dirwalk``).

May import: nothing from rlexp.
"""
