"""The command lines users type, in a subprocess on tiny budgets."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import torch

from conftest import REPO, TINY, only_run_dir, run_train, train_here
from rlexp.checkpoints.files import latest_checkpoint, load_checkpoint


def test_train_writes_tensorboard_metrics_and_checkpoints_and_eval_reloads(tmp_path):
    run_train(TINY, cwd=tmp_path)
    run_dir = only_run_dir(tmp_path)

    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(run_dir / "tensorboard"))
    acc.Reload()
    tags = set(acc.Tags()["scalars"])
    for tag in (
        "train/episode_return",
        "train/episode_length",
        "loss/policy",
        "loss/value",
        "perf/sps",
        "eval/episode_return",
        "eval/episode_length",
    ):
        assert tag in tags, f"{tag} missing from TensorBoard; have {sorted(tags)}"
    assert [e.step for e in acc.Scalars("loss/policy")] == [256, 512]

    rows = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    assert any("loss/policy" in r for r in rows) and any("eval/episode_return" in r for r in rows)
    assert max(r["step"] for r in rows) == 512

    ckpts = sorted((run_dir / "checkpoints").glob("*_step_*.pt"))
    assert [c.name for c in ckpts] == [
        "InvertedPendulum-v5_ppo_step_000000256.pt",
        "InvertedPendulum-v5_ppo_step_000000512.pt",
    ]
    best = load_checkpoint(run_dir / "checkpoints" / "best.pt")
    evals = [r["eval/episode_return"] for r in rows if "eval/episode_return" in r]
    assert best["best_metric"] == max(evals) and best["last_eval"]["eval/episode_return"] == max(
        evals
    )
    ckpt = load_checkpoint(ckpts[-1])  # weights_only=True inside
    assert ckpt["global_step"] == 512
    assert {"policy", "algorithm", "windows", "rng", "config"} <= set(ckpt)
    assert "normalizer.mean" in ckpt["policy"] and float(ckpt["policy"]["normalizer.count"]) == 512
    assert ckpt["algorithm"]["optimizer"]["state"], "optimiser state missing"
    assert (run_dir / "config.yaml").is_file() and (run_dir / ".hydra" / "config.yaml").is_file()

    env = {**os.environ, "PYTHONPATH": str(REPO / "src")}
    proc = subprocess.run(
        [sys.executable, "-m", "rlexp.cli", "eval", str(ckpts[-1]), "--episodes", "3"],
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    assert "mean return" in proc.stdout and "over 3 episodes" in proc.stdout
    # A run dir works too (newest checkpoint).
    assert latest_checkpoint(run_dir) == ckpts[-1]


def _params(run_root):
    ckpt = load_checkpoint(latest_checkpoint(only_run_dir(run_root)))
    return ckpt["policy"]


def test_same_seed_gives_identical_parameters(tmp_path):
    for name, seed in (("a", 7), ("b", 7), ("c", 8)):
        (tmp_path / name).mkdir()
        run_train([*TINY, f"seed={seed}", "trainer.eval_every=0"], cwd=tmp_path / name)
    a, b, c = (_params(tmp_path / n) for n in "abc")
    assert a.keys() == b.keys()
    for key in a:
        assert torch.equal(a[key], b[key]), f"{key} differs between two runs with the same seed"
    assert any(not torch.equal(a[k], c[k]) for k in a), "a different seed gave identical parameters"


def test_ctrl_c_saves_a_checkpoint_and_exits_130(tmp_path, children):
    """Ctrl-C stops at the end of the iteration with a checkpoint; exit 130 (128 + SIGINT), so a
    shell loop around train.py stops too (docs/faults.md)."""
    args = [
        "env=inverted_pendulum",
        "trainer.total_frames=10000000",
        "trainer.frames_per_batch=256",
        "trainer.save_every=0",
        "trainer.eval_every=0",
    ]
    proc = children.train(args, tmp_path, tmp_path / "console.txt")  # killed on teardown
    deadline = time.time() + 120
    log_file = None
    while time.time() < deadline:
        logs = list(tmp_path.glob("outputs/*/*/train.log"))
        if logs and "[train] step=512" in logs[0].read_text():
            log_file = logs[0]
            break
        time.sleep(0.2)
    assert log_file is not None, "training did not start"
    proc.send_signal(signal.SIGINT)
    proc.wait(timeout=120)
    assert proc.returncode == 128 + signal.SIGINT, (tmp_path / "console.txt").read_text()
    run_dir = log_file.parent
    ckpt = load_checkpoint(latest_checkpoint(run_dir))
    assert ckpt["global_step"] >= 512
    assert "interrupted" in log_file.read_text()


def test_collection_and_eval_run_one_torch_thread_and_the_update_torch_threads(
    tmp_path, monkeypatch
):
    """trainer.torch_threads is for the update; stepping envs with more threads only slows it."""
    from rlexp.algorithms.ppo import PPO
    from rlexp.envs.gym import GymnasiumEnv

    seen: dict[str, set[int]] = {"step": set(), "update": set()}
    step, update = GymnasiumEnv.step_tensors, PPO.update  # (step_action steps through it too)

    def spy_step(self, action):
        seen["step"].add(torch.get_num_threads())
        return step(self, action)

    def spy_update(self, batch):
        seen["update"].add(torch.get_num_threads())
        return update(self, batch)

    monkeypatch.setattr(GymnasiumEnv, "step_tensors", spy_step)
    monkeypatch.setattr(PPO, "update", spy_update)
    train_here(
        [
            "env=inverted_pendulum",
            "trainer.total_frames=512",
            "trainer.frames_per_batch=256",
            "trainer.eval_every=256",
            "trainer.eval_episodes=1",
            "algorithm.num_epochs=1",
            "trainer.torch_threads=2",
            "logger=none",
        ],  # fmt: skip
        tmp_path / "run",
    )
    assert seen == {"step": {1}, "update": {2}}


def test_best_pt_keeps_the_better_eval_when_a_later_one_is_worse(tmp_path, monkeypatch):
    """Three eval rounds scoring 1, 5, 2: best.pt is the step-512 state, not the last one."""
    import rlexp.training.evaluation as evaluation_mod  # the Trainer's in-process rounds run_episodes

    scores = iter([1.0, 5.0, 2.0])
    real_run_episodes = evaluation_mod.run_episodes

    def scripted(*args, **kwargs):
        metrics = real_run_episodes(*args, **kwargs)  # the real episodes, a scripted score
        metrics["eval/episode_return"] = next(scores)
        return metrics

    monkeypatch.setattr(evaluation_mod, "run_episodes", scripted)
    train_here(
        [*TINY, "trainer.total_frames=768", "trainer.keep_last=0", "algorithm.num_epochs=1",
         "logger=none"],
        tmp_path / "run",
    )  # fmt: skip
    ckpts = tmp_path / "run" / "checkpoints"
    best = load_checkpoint(ckpts / "best.pt")
    assert best["global_step"] == 512
    assert best["best_metric"] == 5.0 and best["last_eval"]["eval/episode_return"] == 5.0
    at_512 = load_checkpoint(ckpts / "InvertedPendulum-v5_ppo_step_000000512.pt")
    last = load_checkpoint(ckpts / "InvertedPendulum-v5_ppo_step_000000768.pt")
    assert last["last_eval"]["eval/episode_return"] == 2.0 and last["best_metric"] == 5.0
    for key, value in best["policy"].items():
        assert torch.equal(value, at_512["policy"][key]), f"best.pt {key} is not step 512's"
    assert any(not torch.equal(v, last["policy"][k]) for k, v in best["policy"].items())


def test_the_gc_is_off_while_a_run_builds_and_walks_only_what_training_creates(
    tmp_path, monkeypatch
):
    """Start-up runs without the cyclic GC (imports and the build trigger dozens of full
    collections, ~0.2 s each); training runs with it on and everything built before frozen; a later
    run in the same process unfreezes what the earlier one froze, and the GC is on again after."""
    import gc

    import rlexp.training.build as build_mod
    from conftest import compose
    from rlexp.app import train
    from rlexp.config.validate import to_root_config
    from rlexp.training.trainer import Trainer

    seen: list[tuple[str, bool, int]] = []
    real_build, real_train = build_mod.build, Trainer.train

    def spy_build(*args, **kwargs):
        seen.append(("build", gc.isenabled(), gc.get_freeze_count()))
        return real_build(*args, **kwargs)

    def spy_train(self, total):
        seen.append(("train", gc.isenabled(), gc.get_freeze_count()))
        return real_train(self, total)

    monkeypatch.setattr(build_mod, "build", spy_build)
    monkeypatch.setattr(Trainer, "train", spy_train)
    config = to_root_config(compose([*TINY, "logger=none"]))
    assert gc.isenabled()
    try:
        train(config, tmp_path / "a")
        assert gc.isenabled() and gc.get_freeze_count() > 0  # left frozen until the next run
        train(config, tmp_path / "b")
        enabled_after = gc.isenabled()
    finally:
        gc.unfreeze()
        gc.enable()
    (b1, on1, _), (t1, on2, frozen1), (b2, on3, frozen2), (t2, on4, _) = seen
    assert (b1, t1, b2, t2) == ("build", "train", "build", "train")
    assert (on1, on2, on3, on4) == (False, True, False, True)
    assert frozen1 > 10_000  # the imports' objects: out of the collector's reach while training
    assert frozen2 == 0  # the second run released the first one's before building
    assert enabled_after


def test_a_run_imports_nothing_it_does_not_use(tmp_path):
    """The default run (TensorBoard, evaluation, checkpoints) imports no W&B, plotting, statistics,
    launcher, sweeper, video or export library (``python -X importtime``, #18's fixed costs)."""
    proc = run_train(
        [*TINY, "trainer.eval_every=256", "trainer.eval_episodes=1"],
        cwd=tmp_path,
        env_extra={"PYTHONPROFILEIMPORTTIME": "1"},
    )
    imported = {
        line.split("|")[-1].strip().split(".")[0]
        for line in proc.stderr.splitlines()
        if line.startswith("import time:") and "|" in line
    }
    assert {"torch", "torchrl", "hydra", "tensorboard"} <= imported  # (the profile was read)
    # (imageio itself comes with Gymnasium's MuJoCo envs, which import their renderer; Hydra
    # imports every installed plugin's module, submitit's launcher config and ours, not submitit)
    unused = {
        "wandb", "matplotlib", "scipy", "submitit", "optuna", "imageio_ffmpeg", "onnx",
        "onnxruntime", "onnxscript", "stable_baselines3", "pandas",
    }  # fmt: skip
    assert not imported & unused, sorted(imported & unused)


def test_a_sweeps_own_loop_keeps_the_gc_and_a_single_run_starts_without_it(monkeypatch):
    """``python train.py -m``: the sweeper, the launcher and its SLURM polling run for hours in the
    parent, with the GC (each job builds without it, in app.train); a single run starts without."""
    import gc

    import hydra

    from rlexp import app
    from rlexp.common import speedups as _speedups

    seen: list[bool] = []

    def fake_main(**kwargs):
        return lambda task: lambda: seen.append(gc.isenabled())

    monkeypatch.setattr(hydra, "main", fake_main)
    monkeypatch.setattr(app, "_prompt_exit", lambda: None)
    monkeypatch.setattr(app, "_PRECHECKED", {})  # main records its check for the job: not kept
    for argv in (["-m", "seed=0,1", *TINY], TINY):
        monkeypatch.setattr(sys, "argv", ["train.py", *argv])
        with _speedups.startup_gc():  # as rlexp.cli.train runs app.main
            app.main()
    assert seen == [True, False]
    assert gc.isenabled()
