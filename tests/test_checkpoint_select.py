"""One rule for which checkpoint ``rlexp eval`` and ``rlexp export`` take (#30 item 3):
``--checkpoint best|last|PATH`` on both, one selector in the code (``select_checkpoint``)."""

from __future__ import annotations

import re
import shutil

import pytest

from conftest import TINY, run_train
from conftest import rlexp_cli as _cli
from rlexp.checkpoints.files import load_checkpoint, select_checkpoint, step_checkpoints


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """Three iterations, an eval and a checkpoint after each: best.pt and three step files."""
    root = tmp_path_factory.mktemp("select")
    run_train(
        [*TINY, "trainer.total_frames=768", "trainer.keep_last=3", f"hydra.run.dir={root / 'run'}"],
        cwd=root,
    )
    return root / "run"


def test_the_selector_takes_last_by_default_best_and_a_path_when_asked(run, tmp_path):
    steps = step_checkpoints(run / "checkpoints")
    assert [load_checkpoint(p)["global_step"] for p in steps] == [256, 512, 768]
    ckpt, why = select_checkpoint(run)
    assert (ckpt["path"], why) == (str(steps[-1]), "the last checkpoint")
    assert select_checkpoint(run, "last")[0]["path"] == str(steps[-1])
    ckpt, why = select_checkpoint(run, "best")
    assert ckpt["path"] == str(run / "checkpoints" / "best.pt")
    assert why == "--checkpoint best: the best evaluation"
    ckpt, why = select_checkpoint(run, steps[0].name)  # a name inside checkpoints/
    assert (ckpt["global_step"], why) == (256, "--checkpoint PATH")
    ckpt, _ = select_checkpoint(run / "checkpoints", str(steps[1]))  # an absolute path
    assert ckpt["global_step"] == 512
    # the newest unreadable: named and skipped, the previous one taken
    broken = shutil.copytree(run, tmp_path / "broken")
    newest = step_checkpoints(broken / "checkpoints")[-1]
    newest.write_bytes(newest.read_bytes()[:100])
    assert select_checkpoint(broken)[0]["global_step"] == 512


def test_eval_and_export_take_the_same_checkpoint_for_each_choice(run, tmp_path):
    steps = step_checkpoints(run / "checkpoints")
    wanted = {None: steps[-1], "last": steps[-1], "best": run / "checkpoints" / "best.pt",
              steps[0].name: steps[0]}  # fmt: skip
    for choice, path in wanted.items():
        flag = [] if choice is None else ["--checkpoint", choice]
        code, out, err = _cli("eval", run, "--episodes", "1", "--num-envs", "1", *flag)
        assert code == 0, err
        assert re.match(rf"checkpoint {re.escape(str(path))} \(step \d+; ", out), out
        code, out, err = _cli("export", run, "--out", tmp_path / f"{choice}.pt", *flag)
        assert code == 0, err
        assert out.startswith(f"exported {path} (step "), out


def test_a_checkpoint_that_is_not_there_is_one_line_for_both(run):
    for command in ("eval", "export"):
        code, _, err = _cli(command, run, "--checkpoint", "nope.pt")
        assert code == 2 and "Traceback" not in err
        assert err.strip().splitlines() == [
            f"rlexp {command}: --checkpoint 'nope.pt': no such file, nor in {str(run)!r} or its "
            "checkpoints/ (best, last or a checkpoint's path)"
        ]
