"""Train PPO with rlexp: ``python train.py [--config-json FILE] [hydra overrides]`` (see README.md).

``--config-json FILE`` (or ``--config FILE``) runs one of our users' JSON experiment files; Hydra
overrides still apply on top of it (docs/json_format.md).
"""

from rlexp.launch.json_entry import main

if __name__ == "__main__":
    main()
