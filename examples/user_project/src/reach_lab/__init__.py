"""reach_lab: an example project on rlexp (a native task, a reward term and an event).

rlexp loads it through the ``rlexp.plugins`` entry point (``reach_lab.plugin:register``).
"""

__version__ = "0.1.0"
