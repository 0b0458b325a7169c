"""rlexp: Hydra-based experiment management for PPO on MuJoCo, built on TorchRL."""

__version__ = "0.1.0"
