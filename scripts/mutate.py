"""Check that tests catch a bug: put the bug into a copy of the tree and run the tests there.

    .venv/bin/python scripts/mutate.py -r src/rlexp/checkpoints/files.py \\
        'tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")' 'tmp = path' \\
        -- tests/test_checkpoint_writes.py     # a checkpoint written in place

copies the files git knows (tracked and untracked, not ignored) into a temporary directory,
replaces each OLD with NEW (exactly one occurrence each; ``--all`` replaces every one; for a
multi-line OLD or NEW, use the shell's ``$'...\\n...'``), and runs
``pytest ARGS`` in the copy with ``PYTHONPATH`` at the copy's ``src/``. Exit 0: the tests failed,
the mutation was caught ("killed"); 1: they passed, it survived; 2: something else went wrong
(OLD not found, the tests could not be collected). The working tree is never touched.
See docs/architecture.md, "Checking that the tests catch bugs".
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def copy_tree(dest: Path) -> None:
    """The files git lists (tracked, and untracked but not ignored) into ``dest``; ``shared/``
    next to the checkout, which some tests read, is linked next to the copy."""
    listed = subprocess.run(
        ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
        cwd=REPO, capture_output=True, check=True,
    ).stdout.decode().split("\0")  # fmt: skip
    for name in filter(None, listed):
        src = REPO / name
        if src.is_file():  # listed but deleted in the working tree: skipped
            (dest / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dest / name)
    shared = REPO.parent / "shared"
    if shared.is_dir():
        (dest.parent / "shared").symlink_to(shared)


def apply(tree: Path, file: str, old: str, new: str, every: bool) -> None:
    """Replace ``old`` by ``new`` in ``tree/file``: exactly once, or every time with ``every``."""
    path = tree / file
    text = path.read_text()
    count = text.count(old)
    if count == 0 or (count > 1 and not every):
        print(f"mutate: {old!r} occurs {count} times in {file}; it must occur once (or use --all)",
              file=sys.stderr)  # fmt: skip
        raise SystemExit(2)  # not 1: that would read as a surviving mutation
    path.write_text(text.replace(old, new))
    print(f"mutate: {file}: {old!r} -> {new!r} ({count}x)")


def main(argv: list[str] | None = None) -> int:
    """Apply the mutations to a copy, run the tests, and say whether they caught it."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument(
        "-r", "--replace", nargs=3, action="append", required=True, metavar=("FILE", "OLD", "NEW"),
        help="a replacement (repeatable)",
    )  # fmt: skip
    parser.add_argument("--all", action="store_true", help="replace every occurrence of OLD")
    parser.add_argument("--keep", action="store_true", help="keep the mutated copy; print its path")
    parser.add_argument("pytest_args", nargs="+", help="after --: the tests to run (paths as here)")
    args = parser.parse_args(argv)

    top = Path(tempfile.mkdtemp(prefix="rlexp-mutant-"))
    tree = top / "tree"
    try:
        copy_tree(tree)
        for file, old, new in args.replace:
            apply(tree, file, old, new, args.all)
        env = {**os.environ, "PYTHONPATH": str(tree / "src")}
        # The copy's tests: tests/conftest.py puts its own checkout's src/ first on sys.path.
        tests = [a.replace(str(REPO), str(tree), 1) for a in args.pytest_args]
        cmd = [sys.executable, "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider", *tests]
        code = subprocess.run(cmd, cwd=tree, env=env).returncode
    finally:
        if args.keep:
            print(f"mutate: the mutated copy is {tree}")
        else:
            shutil.rmtree(top, ignore_errors=True)
    if code == 1:
        print("mutate: KILLED (a test failed)")
        return 0
    if code == 0:
        print("mutate: SURVIVED (every test passed with the bug in)")
        return 1
    print(f"mutate: pytest exited {code} (not a test failure: collection or usage error)")
    return 2


if __name__ == "__main__":
    sys.exit(main())
