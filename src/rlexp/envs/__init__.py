"""Layer 2, environments: ``make_env`` (``factory``), the Gymnasium adapter, native batched MuJoCo
tasks (``rlexp.envs.native``), batched torch envs named ``package.module:callable`` (``batched``).

May import: layers 0-1 and the other pieces.
"""
