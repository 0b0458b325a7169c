"""Population Based Training across a sweep (docs/pbt.md): settings (``config``), the population on
a shared filesystem (``population``), the exploit's load (``exploit``), lineage for reports and
export (``lineage``). The member-side controller is the ``pbt`` hook (``rlexp.hooks.pbt``).

Layer 2 (pieces). May import: layers 0-1 and the other pieces (``checkpoints``).
"""
