"""``algorithm=grpo`` end to end, in subprocesses on tiny budgets: ``python train.py``, the users' GRPO
JSON files, resume (the frozen reference comes back from the checkpoint), two gloo ranks, a sweep
against PPO with its report, and bad input. The math is in tests/test_grpo_math.py."""

from __future__ import annotations

import csv
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from conftest import REPO, only_run_dir, run_train
from rlexp.checkpoints.files import latest_checkpoint, load_checkpoint
from rlexp.config.validate import to_root_config

EXAMPLES = REPO / "examples" / "json"

#: CartPole, 8 envs (two groups of 4) x 32 steps per iteration, 50-step episodes, 2 eval episodes.
GRPO = [
    "algorithm=grpo",
    "env=cart_pole",
    "env.num_envs=8",
    "env.num_eval_envs=2",
    "env.max_episode_steps=50",
    "trainer.frames_per_batch=256",
    "trainer.eval_every=256",
    "trainer.eval_episodes=2",
    "trainer.save_every=256",
    "algorithm.num_epochs=2",
    "trainer.progress=false",
]


def _rows(run_dir: Path) -> list[dict]:
    return [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]


def _evals(run_dir: Path) -> dict[int, dict[str, float]]:
    return {r["step"]: r for r in _rows(run_dir) if "eval/episode_return" in r}


def _status(run_dir: Path) -> dict:
    return json.loads((run_dir / "status.json").read_text())


def _actor(ckpt: dict) -> dict[str, torch.Tensor]:
    """The policy's actor as ``GRPO.reference`` holds it (``policy.actor``'s state dict)."""
    return {k[len("actor.") :]: v for k, v in ckpt["policy"].items() if k.startswith("actor.")}


# -- python train.py algorithm=grpo -------------------------------------------------------------------
@pytest.mark.parametrize("kl_coeff", [0.02, 0.0])
def test_train_py_runs_grpo_and_keeps_a_reference_only_with_a_kl_penalty(tmp_path, kl_coeff):
    run_train([*GRPO, "trainer.total_frames=512", f"algorithm.kl_coeff={kl_coeff}"], cwd=tmp_path)
    run_dir = only_run_dir(tmp_path)
    assert _status(run_dir)["state"] == "finished" and _status(run_dir)["global_step"] == 512
    train = [r for r in _rows(run_dir) if "perf/sps" in r]
    assert [r["step"] for r in train] == [256, 512]
    for row in train:
        assert "loss/policy" in row and 0.0 < row["grpo/mask_fraction"] <= 1.0, row
        assert "loss/value" not in row, "GRPO has no critic: no value loss"
        assert ("loss/kl_ref" in row) is (kl_coeff > 0), row
    assert sorted(_evals(run_dir)) == [256, 512]
    config = to_root_config(OmegaConf.to_container(OmegaConf.load(run_dir / "config.yaml")))
    assert config.algorithm.name == "grpo" and config.policy.name == "actor_only"  # chosen by grpo
    assert config.trainer.exp_name == "cart_pole_grpo"

    first, last = (load_checkpoint(p) for p in sorted((run_dir / "checkpoints").glob("*_step_*")))
    assert (first["global_step"], last["global_step"]) == (256, 512)
    if kl_coeff == 0:
        assert "reference" not in last["algorithm"]
        return
    # The reference is the initial actor: the same in every checkpoint, not the trained one.
    ref = last["algorithm"]["reference"]
    assert ref.keys() == _actor(last).keys()
    assert all(torch.equal(ref[k], first["algorithm"]["reference"][k]) for k in ref)
    assert any(not torch.equal(ref[k], v) for k, v in _actor(last).items() if "mlp" in k)


# -- the users' GRPO files ----------------------------------------------------------------------------
#: Overrides that only shorten a file: one iteration of 4 envs (one group) x 16 steps, 10-step
#: episodes, one epoch of two minibatches; push_cube's evaluation: one episode on one env.
TINY_JSON = [
    "trainer.iterations=1",
    "env.num_envs=4",
    "trainer.frames_per_batch=64",
    "algorithm.mini_batch_size=32",
    "algorithm.num_epochs=1",
    "env.max_episode_steps=10",
    "trainer.progress=false",
]
TINY_EVAL = ["env.num_eval_envs=1", "trainer.eval_episodes=1"]


@pytest.mark.parametrize("task", ["cart_pole", "push_cube"])
def test_the_users_grpo_file_runs_unchanged(task, tmp_path):
    path = EXAMPLES / task / "train_config_grpo.json"
    run_train(["--config-json", str(path), *TINY_JSON, *TINY_EVAL], cwd=tmp_path)
    run_dir = only_run_dir(tmp_path)
    log = (run_dir / "train.log").read_text()
    assert log.count("with task file") == 1
    assert log.count("accepted but not applicable to the MuJoCo CPU rebuild") == 1
    assert _status(run_dir)["state"] == "finished"
    config = to_root_config(OmegaConf.to_container(OmegaConf.load(run_dir / "config.yaml")))
    assert (config.algorithm.name, config.algorithm.kl_coeff, config.algorithm.group_size) == (
        "grpo",
        0.0,
        4,
    )
    assert config.algorithm.lr == 1e-4 and config.algorithm.entropy_coeff == 0.01  # the file's
    assert config.policy.name == "actor_only" and config.policy.actor.hidden_sizes == [256, 256]
    assert config.trainer.exp_name == f"{task}_grpo" and config.seed == 42
    ckpts = sorted(p.name for p in (run_dir / "checkpoints").glob("*_step_*.pt"))
    assert ckpts == [f"{task}_grpo_step_000000064.pt"], ckpts
    ckpt = load_checkpoint(run_dir / "checkpoints" / ckpts[0])
    assert "reference" not in ckpt["algorithm"]  # kl_coef 0.0 in the file: no reference kept
    rows = _rows(run_dir)
    assert any("grpo/mask_fraction" in r for r in rows)
    assert not any("loss/value" in r for r in rows)
    written = json.loads((run_dir / "train_config.json").read_text())
    assert written["algorithm"]["name"] == "grpo" and written["policy"]["name"] == "actor_only"
    videos = sorted(run_dir.rglob("*.mp4"))
    if task == "cart_pole":
        # The file has no enable_eval (the format's default: false): its eval video event is
        # configured, but no evaluation runs, so nothing is recorded.
        assert config.trainer.eval_every == 0 and not _evals(run_dir) and videos == []
        return
    # push_cube evaluates: record_camera_data_async writes its video under its save_path, inside
    # the run dir; use_wandb: true runs W&B (offline here).
    assert sorted(_evals(run_dir)) == [64]
    assert [v.relative_to(run_dir).parent.as_posix() for v in videos] == [
        "outputs/videos_ppo1/eval"
    ]
    assert videos[0].stat().st_size > 0
    assert (run_dir / "wandb_run_id.txt").is_file()


def test_an_actor_only_file_with_a_critic_block_is_read_with_a_warning(tmp_path):
    from rlexp.config.json_format import load_json_experiment

    train = json.loads((EXAMPLES / "cart_pole" / "train_config_grpo.json").read_text())
    train["policy"]["critic"] = train["policy"]["actor"]
    (tmp_path / "train_config.json").write_text(json.dumps(train))
    shutil.copy(EXAMPLES / "cart_pole" / "gym_config.json", tmp_path)
    exp = load_json_experiment(tmp_path / "train_config.json", cwd=tmp_path)
    assert exp.groups["policy"] == "actor_only" and exp.groups["algorithm"] == "grpo"
    warnings = [n for n in exp.notes if "policy.critic" in n]
    assert warnings == [
        "warning: policy.critic is not used: policy.name='actor_only' has no critic (ignored)"
    ]


# -- resume -------------------------------------------------------------------------------------------
def test_stop_and_resume_with_a_kl_penalty_is_bit_identical(tmp_path):
    """Stopped after 2 iterations and continued from that checkpoint to 4, equal to 4 iterations in
    one go: parameters, optimiser state, reference, losses and evaluations. The continuing process
    starts from another initial policy (``policy.init_log_std``; the checkpoint's policy replaces
    it), so a reference copied from its own fresh policy instead of read from the checkpoint would
    pull towards another policy and change the result (with the same seed, the fresh policy would
    be the original initial one, and such a bug would go unseen)."""
    args = [*GRPO, "algorithm.kl_coeff=0.05", "algorithm.entropy_coeff=0.01", "seed=7"]
    whole, first, second = tmp_path / "whole", tmp_path / "first", tmp_path / "second"
    run_train([*args, "trainer.total_frames=1024", f"hydra.run.dir={whole}"], cwd=tmp_path)
    run_train([*args, "trainer.total_frames=512", f"hydra.run.dir={first}"], cwd=tmp_path)
    stopped_at = latest_checkpoint(first / "checkpoints")
    stopped = load_checkpoint(stopped_at)
    assert stopped["global_step"] == 512 and "reference" in stopped["algorithm"]
    proc = run_train(
        [*args, "trainer.total_frames=1024", f"trainer.resume={stopped_at}",
         "policy.init_log_std=-1.0", f"hydra.run.dir={second}"],
        cwd=tmp_path,
    )  # fmt: skip
    assert f"[resume] continuing from {stopped_at} at step 512" in proc.stdout + proc.stderr

    a = load_checkpoint(latest_checkpoint(whole / "checkpoints"))
    b = load_checkpoint(latest_checkpoint(second / "checkpoints"))
    assert a["global_step"] == b["global_step"] == 1024
    assert a["algorithm"]["iteration"] == b["algorithm"]["iteration"] == 4
    for key, value in a["policy"].items():
        assert torch.equal(value, b["policy"][key]), f"policy.{key} differs after resume"
    for key, value in a["algorithm"]["reference"].items():
        assert torch.equal(value, b["algorithm"]["reference"][key]), f"reference.{key} differs"
        assert torch.equal(value, stopped["algorithm"]["reference"][key])
    for i, state in a["algorithm"]["optimizer"]["state"].items():
        for k, v in state.items():
            assert torch.equal(v, b["algorithm"]["optimizer"]["state"][i][k]), f"optimizer {i}.{k}"
    assert a["windows"]["returns"] == b["windows"]["returns"]
    assert a["last_eval"] == b["last_eval"] and a["best_metric"] == b["best_metric"]
    # Every iteration's losses (kl_ref included) and every evaluation, split over the two processes.
    assert sorted(_evals(whole)) == [256, 512, 768, 1024]
    assert _untimed(_evals(whole)) == _untimed({**_evals(first), **_evals(second)})
    train = {
        d: [_untimed(r) for r in _rows(d) if "loss/kl_ref" in r] for d in (whole, first, second)
    }
    assert len(train[whole]) == 4 and train[whole] == train[first] + train[second]


def _untimed(rows: dict) -> dict:
    """A metrics row, or {step: row}, without the wall-clock values, which differ between runs."""
    if all(isinstance(k, int) for k in rows):
        return {step: _untimed(r) for step, r in rows.items()}
    return {k: v for k, v in rows.items() if k != "time" and not k.startswith("perf/")}


# -- distributed ---------------------------------------------------------------------------------------
DIST = [
    "algorithm=grpo",
    "env=cart_pole",
    "env.num_envs=4",
    "env.max_episode_steps=50",
    "trainer.frames_per_batch=128",
    "algorithm.num_epochs=2",
    "trainer.eval_every=0",
    "trainer.save_every=0",
    "trainer.progress=false",
    "seed=11",
]


def test_two_gloo_ranks_average_grpo_gradients(tmp_path):
    env = {**os.environ, "PYTHONPATH": str(REPO / "src"), "OMP_NUM_THREADS": "1"}
    (tmp_path / "dist").mkdir()
    proc = subprocess.run(
        [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2",
         str(REPO / "train.py"), "--distributed", *DIST, "trainer.total_frames=256"],
        cwd=tmp_path / "dist", env=env, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-4000:]
    run_dir = only_run_dir(tmp_path / "dist")
    ckpt = load_checkpoint(latest_checkpoint(run_dir))
    assert ckpt["global_step"] == 256  # one iteration of 128 per rank
    assert "reference" in ckpt["algorithm"]  # kl_coeff 0.02 by default
    digests = []
    for name in ("train.log", "train_rank1.log"):
        m = re.search(
            r"parameters identical on all 2 ranks \(sha256 (\w+)\)", (run_dir / name).read_text()
        )
        assert m, f"no sync line in {name}"
        digests.append(m.group(1))
    assert digests[0] == digests[1]

    # Rank 0 alone (same seed, same envs) computes something else: the update used the gradient
    # averaged with rank 1's.
    (tmp_path / "single").mkdir()
    run_train([*DIST, "trainer.total_frames=128"], cwd=tmp_path / "single")
    alone = load_checkpoint(latest_checkpoint(only_run_dir(tmp_path / "single")))
    assert alone["global_step"] == 128
    dist_p, alone_p = _actor(ckpt), _actor(alone)
    assert any(not torch.equal(dist_p[k], alone_p[k]) for k in dist_p if "mlp" in k), (
        "gradients were not averaged"
    )


# -- a sweep against PPO and its report ---------------------------------------------------------------
def test_a_sweep_over_ppo_and_grpo_reports_one_row_per_algorithm(tmp_path):
    sweep = tmp_path / "sweep"
    tiny = [o for o in GRPO if o != "algorithm=grpo" and not o.startswith("algorithm.")]
    run_train(
        ["-m", "algorithm=ppo,grpo", "seed=0,1", *tiny, "trainer.total_frames=512",
         "algorithm.num_epochs=1", f"hydra.sweep.dir={sweep}"],
        cwd=tmp_path,
    )  # fmt: skip
    jobs = sorted(p for p in sweep.iterdir() if p.is_dir())
    assert len(jobs) == 4
    for job in jobs:
        assert _status(job)["state"] == "finished", job
        algo = OmegaConf.load(job / "config.yaml").algorithm.name
        assert any("loss/value" in r for r in _rows(job)) is (algo == "ppo")

    proc = subprocess.run(
        [sys.executable, "-m", "rlexp.cli", "report", str(sweep), "--threshold", "10", "--no-plot"],
        capture_output=True, text=True, timeout=120,
        env={**os.environ, "PYTHONPATH": str(REPO / "src")},
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    md = (sweep / "report.md").read_text()
    assert "4 finished" in md
    assert "## Steps to threshold: `eval/episode_return` >= 10" in md
    for algo in ("ppo", "grpo"):
        assert f"| `algorithm={algo}` | 2 | " in md  # the main table: two seeds pooled
        assert re.search(rf"\| `algorithm={algo}` \| [0-2]/2 \| ", md), md
    with open(sweep / "report.csv") as f:
        table = {r["configuration"]: r for r in csv.DictReader(f)}
    assert sorted(table) == ["algorithm=grpo", "algorithm=ppo"]
    for row in table.values():
        assert row["n_seeds"] == "2" and row["seeds"] == "0 1"
        assert (row["threshold_metric"], row["threshold"]) == ("eval/episode_return", "10.0")


# -- bad input: one line, exit 2, nothing written ---------------------------------------------------------
def _json_file(folder: Path, **cfg) -> Path:
    """The users' cart_pole GRPO file with ``algorithm.cfg`` keys changed, in ``folder``."""
    folder.mkdir()
    train = json.loads((EXAMPLES / "cart_pole" / "train_config_grpo.json").read_text())
    train["algorithm"]["cfg"].update(cfg)
    shutil.copy(EXAMPLES / "cart_pole" / "gym_config.json", folder / "gym_config.json")
    (folder / "train_config.json").write_text(json.dumps(train, indent=2))
    return folder / "train_config.json"


@pytest.mark.parametrize(
    ("args", "expected"),
    [
        (
            ["algorithm=grpo", "env=cart_pole", "env.num_envs=6", "trainer.frames_per_batch=384"],
            "algorithm.group_size=4 must divide env.num_envs=6",
        ),
        (
            ["algorithm=grpo", "algorithm.lmbda=0.9"],
            "algorithm.lmbda is not a key of algorithm=grpo",
        ),
        (
            ["policy=actor_only"],
            "algorithm=ppo needs a critic, but policy.name='actor_only' has none",
        ),
        ({"vf_coef": 0.5}, "unknown key 'algorithm.cfg.vf_coef'"),
        ({"group_size": 1}, "algorithm.cfg.group_size=1 is out of range: must be >= 2"),
    ],
    ids=[
        "group_size_does_not_divide",
        "ppo_key",
        "ppo_without_critic",
        "json_vf_coef",
        "json_group_size_1",
    ],  # fmt: skip
)
def test_bad_grpo_input_is_one_line_and_exit_2(tmp_path, args, expected):
    if isinstance(args, dict):
        args = ["--config-json", str(_json_file(tmp_path / "files", **args))]
    proc = run_train([*args, "trainer.total_frames=512"], cwd=tmp_path, check=False, timeout=120)
    assert proc.returncode == 2, proc.stdout + proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("config error: "), proc.stderr
    assert expected in lines[0], lines[0]
    if "lmbda" in expected:
        assert lines[0].endswith("algorithm.lmbda belongs to algorithm=ppo")
    assert "Traceback" not in proc.stdout + proc.stderr
    assert not list(tmp_path.rglob("outputs")) and not list(tmp_path.rglob("multirun"))
