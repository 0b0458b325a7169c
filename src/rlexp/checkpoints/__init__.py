"""Layer 2, checkpoint files: save / load / select / RNG capture (``files``), a checkpoint's declared
sizes checked before torch materialises anything (``scan``), every field a load uses type- and
range-checked (``fields``).

May import: layers 0-1 and the other pieces (``algorithms.normalize``: the normaliser's state check).
"""
