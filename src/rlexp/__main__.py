"""``python -m rlexp ...``: the ``rlexp`` command (train, eval, report)."""

from rlexp.cli import main

if __name__ == "__main__":
    main()
