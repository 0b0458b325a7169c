"""Train PPO with rlexp: ``python train.py [--config-json FILE] [hydra overrides]`` (see README.md).

``--config-json FILE`` (or ``--config FILE``) runs one of our users' JSON experiment files; Hydra
overrides still apply on top of it (docs/json_format.md). The same as ``rlexp train``: installed
``rlexp.plugins`` load first (docs/user_project.md).
"""

import sys

from rlexp.cli import train

if __name__ == "__main__":
    train(sys.argv[1:], prog="train.py")
