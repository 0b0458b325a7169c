"""Layer 4, a trained policy used outside training: ``rlexp eval`` (``policy_eval``: a checkpoint's
or an exported file's deterministic episodes) and ``rlexp export`` (``export``: TorchScript / ONNX).

May import: layers 0-3.
"""
