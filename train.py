"""Train PPO with rlexp: ``python train.py [hydra overrides]`` (see README.md)."""

from rlexp.app import main

if __name__ == "__main__":
    main()
