"""Layer 3, training: the loop (``trainer``), a run's objects built from a RootConfig (``build``),
small loop helpers (``loop``), the rollout collector (``collector``), the next rollout collected
during the update (``overlap``), training-episode statistics (``episodes``), evaluation episodes
(``evaluation``) and the eval worker process (``eval_worker``).

May import: layers 0-2 and ``run`` (the same layer: metric sinks, the progress bar).
"""
