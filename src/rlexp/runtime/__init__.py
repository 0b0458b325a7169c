"""Layer 1, this process: where things run (``devices``), the process group (``distributed``), stop
signals while a run trains (``signals``) and outside one (``outside_run``), how the process was
launched and the command that resumes it (``relaunch``), the dir Hydra gives a job (``job_dir``), the
entry points' last guard (``entry``: one line and the documented exit code).

May import: layer 0 and ``config``.
"""
