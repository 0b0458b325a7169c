"""Layer 3, a run dir and what a run records: the one owner of a run's life, from the lock to
its exit code (``lifecycle``), lock, status.json, heartbeat and config files (``rundir``), what a dir's files prove before a run continues there (``proof``), the paths tried
before training (``writable``), a step that stands still (``stalls``), what a run records about
itself (``provenance``), metric sinks (``metrics``), the progress bar (``progress``), the run's last
line (``next_steps``).

May import: layers 0-2 and ``training`` (the same layer).
"""
