"""Moved: ``rlexp.checkpoint`` is now ``rlexp.checkpoints.files`` (docs/api.md).

This name keeps old imports working; new code imports ``rlexp.checkpoints.files``."""

# rlexp layout shim (issue 46)
import rlexp.checkpoints.files as _moved
from rlexp.checkpoints.files import *  # noqa: F401,F403
from rlexp.checkpoints.files import load_checkpoint, save_checkpoint, select_checkpoint  # noqa: F401


def __getattr__(name: str):
    return getattr(_moved, name)
