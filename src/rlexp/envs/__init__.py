"""Environments: native batched MuJoCo tasks (``rlexp.envs.native``) and the Gymnasium adapter."""
