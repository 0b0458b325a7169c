"""Layer 0, leaves every layer may use: a config's function name looked up (``registry``: the
registry or an allowlisted dotted path), text tables (``table``), torch speed-ups (``speedups``).

May import: nothing from rlexp.
"""
