"""--distributed: two CPU processes (gloo) whose gradients really synchronise."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys

import pytest
import torch

from conftest import PLAIN_PPO, REPO, Children, only_run_dir, run_train
from rlexp.checkpoints.files import latest_checkpoint, load_checkpoint

ARGS = [
    "env=inverted_pendulum",
    "trainer.frames_per_batch=256",
    "algorithm.num_epochs=2",
    "trainer.eval_every=0",
    "trainer.save_every=0",
    "seed=11",
]


def _torchrun(args: list[str], cwd) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(REPO / "src"), "OMP_NUM_THREADS": "1"}
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "torch.distributed.run",
            "--standalone",
            "--nproc_per_node=2",
            str(REPO / "train.py"),
            "--distributed",
            *args,
        ],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-4000:]
    return proc


def _params(ckpt) -> dict[str, torch.Tensor]:
    return {k: v for k, v in ckpt["policy"].items() if "normalizer" not in k}


def test_two_ranks_average_gradients_share_one_run_dir_and_load_single_process(tmp_path):
    (tmp_path / "dist").mkdir()
    _torchrun([*ARGS, "trainer.total_frames=512"], cwd=tmp_path / "dist")  # one iteration per rank
    run_dir = only_run_dir(tmp_path / "dist")  # one run dir for the whole job
    ckpt = load_checkpoint(latest_checkpoint(run_dir))
    assert ckpt["global_step"] == 512  # 256 per rank, counted over both ranks

    # Both ranks ended with the same parameters, and that is what rank 0 saved.
    from rlexp.training.loop import parameter_digest

    digests = []
    for name in ("train.log", "train_rank1.log"):
        m = re.search(
            r"parameters identical on all 2 ranks \(sha256 (\w+)\)", (run_dir / name).read_text()
        )
        assert m, f"no sync line in {name}"
        digests.append(m.group(1))
    from torchrl.data import Bounded

    from rlexp.config.validate import to_root_config
    from rlexp.policies.actor_critic import make_policy

    config = to_root_config(ckpt["config"])
    policy = make_policy(config.policy, 4, 1, Bounded(-3.0, 3.0, shape=(1, 1)))
    policy.load_state_dict(ckpt["policy"])
    assert digests[0] == digests[1] == parameter_digest(policy)

    # Rank 0 alone, on its own data (same seed, same envs), would have computed something else:
    # the update used the gradient averaged with rank 1's.
    (tmp_path / "single").mkdir()
    run_train([*ARGS, "trainer.total_frames=256"], cwd=tmp_path / "single")
    alone = load_checkpoint(latest_checkpoint(only_run_dir(tmp_path / "single")))
    dist_p, alone_p = _params(ckpt), _params(alone)
    assert any(not torch.equal(dist_p[k], alone_p[k]) for k in dist_p), (
        "gradients were not averaged"
    )

    # The distributed checkpoint loads in a single-process run and training continues from it.
    (tmp_path / "resume").mkdir()
    proc = run_train(
        [*ARGS, "trainer.total_frames=1024", f"trainer.resume={latest_checkpoint(run_dir)}"],
        cwd=tmp_path / "resume",
    )
    assert "continuing from" in proc.stdout + proc.stderr
    assert (
        load_checkpoint(latest_checkpoint(only_run_dir(tmp_path / "resume")))["global_step"] == 1024
    )


def test_distributed_without_a_launcher_is_one_clear_error(tmp_path):
    env = {
        k: v
        for k, v in os.environ.items()
        if k not in ("RANK", "WORLD_SIZE", "MASTER_ADDR", "MASTER_PORT")
    }
    env["PYTHONPATH"] = str(REPO / "src")
    proc = subprocess.run(
        [sys.executable, str(REPO / "train.py"), "--distributed"],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2 and "torchrun --nproc_per_node" in proc.stderr
    assert "Traceback" not in proc.stderr


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _rank_env(rank: int, port: int) -> dict[str, str]:
    """The environment torchrun would give rank ``rank`` of two on this machine."""
    return {
        **os.environ,
        "PYTHONPATH": str(REPO / "src"),
        "OMP_NUM_THREADS": "1",
        "RANK": str(rank),
        "LOCAL_RANK": str(rank),
        "WORLD_SIZE": "2",
        "MASTER_ADDR": "127.0.0.1",
        "MASTER_PORT": str(port),
    }


def run_worker_on_two_ranks(script: str, args: list[str], timeout: float = 120) -> list[str]:
    """``python -c script *args`` as ranks 0 and 1 of a gloo group; both must exit 0. Their outputs."""
    port = _free_port()
    with Children() as children:  # both ranks' groups killed when this returns or fails
        procs = [
            children.popen(
                [sys.executable, "-c", script, *args],
                env=_rank_env(rank, port),
                stdout=subprocess.PIPE,
                stderr=subprocess.STDOUT,
                text=True,
            )
            for rank in (0, 1)
        ]
        outs = [p.communicate(timeout=timeout)[0] for p in procs]
    assert [p.returncode for p in procs] == [0, 0], "\n".join(outs)
    return outs


def _two_ranks(
    args: list[str], rank1_args: list[str], cwd, timeout: float = 120
) -> list[subprocess.CompletedProcess]:
    """Ranks 0 and 1 as two plain processes (no torchrun, which would kill the second when the
    first fails): each one's exit code is its own, and a rank left blocked shows as a timeout."""
    import time

    port = _free_port()
    done = []
    with Children() as children:  # both ranks' groups killed when this returns or fails
        procs = [
            children.popen(
                [sys.executable, str(REPO / "train.py"), "--distributed", *args, *extra],
                cwd=cwd,
                env=_rank_env(rank, port),
                stdout=subprocess.PIPE,
                stderr=subprocess.STDOUT,
                text=True,
            )
            for rank, extra in ((0, []), (1, rank1_args))
        ]
        deadline = time.monotonic() + timeout
        for rank, proc in enumerate(procs):
            try:
                out, _ = proc.communicate(timeout=max(1.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                raise AssertionError(f"rank {rank} still running after {timeout} s") from None
            done.append(subprocess.CompletedProcess(proc.args, proc.returncode, out, ""))
    return done


# Swimmer-v5's control-cost weight is a gymnasium.make kwarg, given to rank 1 only: 1e300 gives it an
# infinite reward (caught in the rollout), -1e30 a finite one whose squared value error overflows
# (caught in the PPO update). Rank 1's config differs from rank 0's, so no rank resumes a run dir.
@pytest.mark.parametrize(
    ("weight", "reason"),
    [
        ("1e300", "non-finite next/reward from the env on rank 1 at step 512"),
        ("-1e30", "non-finite loss (loss_critic on rank 1) in PPO update (epoch 0, minibatch 0)"),
    ],
    ids=["rollout", "update"],
)
def test_nan_on_one_rank_stops_both_ranks_with_the_nan_guard_error(tmp_path, weight, reason):
    run_dir = tmp_path / "run"
    args = [
        "env=swimmer",
        "trainer.total_frames=1024",
        "trainer.frames_per_batch=256",
        "trainer.eval_every=0",
        "trainer.save_every=0",
        "algorithm.num_epochs=1",
        "algorithm.normalize_rewards=false",  # raw rewards: the scaled ones never overflow
        "algorithm.clip_rewards=null",
        "trainer.resume=never",
        f"hydra.run.dir={run_dir}",
    ]
    ranks = _two_ranks(args, [f"+env.kwargs.ctrl_cost_weight={weight}"], cwd=tmp_path)
    outputs = "\n".join(
        f"--- rank {r}, exit {p.returncode}:\n{p.stdout[-3000:]}" for r, p in enumerate(ranks)
    )
    for proc in ranks:
        assert proc.returncode == 3, outputs
        assert reason in proc.stdout and "Traceback" not in proc.stdout, outputs
    status = json.loads((run_dir / "status.json").read_text())
    assert status["state"] == "failed" and status["reason"].startswith(reason), status


# One PPO update per rank, each on its own rollout, with the gradient sync the trainer uses; every
# gradient the optimiser stepped with is saved for the test to compare with single-process ones.
_GRAD_WORKER = """
import sys
import torch
from tensordict import TensorDict
from torchrl.data import Bounded
from rlexp.algorithms.ppo import make_algorithm
from rlexp.config.schema import AlgorithmConfig, PolicyConfig
from rlexp.runtime import distributed
from rlexp.policies.actor_critic import make_policy

distributed.init_in_job()
rank = distributed.info().rank
torch.manual_seed(0)  # the same initial parameters on both ranks
pol = make_policy(PolicyConfig(), 5, 2, Bounded(-1.0, 1.0, shape=(2,)))
initial = {k: v.clone() for k, v in pol.state_dict().items()}
torch.manual_seed(100 + rank)  # each rank its own rollout
steps = 32
obs, next_obs = torch.randn(1, steps, 5), torch.randn(1, steps, 5)
obs[:, 1:] = next_obs[:, :-1]
with torch.no_grad():
    _, _, action, log_prob = pol.sampling_policy().sample(obs)
no = torch.zeros(1, steps, 1, dtype=torch.bool)
batch = TensorDict(
    {
        "observation": obs,
        "action": action,
        "action_log_prob": log_prob + 0.2 * torch.randn(1, steps),
        "next": {
            "observation": next_obs,
            "reward": torch.randn(1, steps, 1),
            "terminated": no,
            "truncated": no,
            "done": no,
        },
    },
    batch_size=[1, steps],
)
cfg = AlgorithmConfig(**{CFG})
algo = make_algorithm(cfg, pol, 1, grad_sync=distributed.all_reduce_mean_)
stepped = []
step = algo.optimizer.step
def record(*args, **kwargs):
    stepped.append([p.grad.clone() for p in algo.params])
    return step(*args, **kwargs)
algo.optimizer.step = record
algo.update(batch.clone())
torch.save({"initial": initial, "batch": batch, "grads": stepped}, sys.argv[1] + f"/rank{rank}.pt")
distributed.shutdown()
"""

# One minibatch of the whole rollout, no clipping: the stepped gradient is the loss's own.
_GRAD_CFG = {
    "num_epochs": 2,
    "mini_batch_size": 32,
    "max_grad_norm": 0.0,
    "compile": "false",
    **PLAIN_PPO,
}


def test_the_gradient_each_rank_steps_with_is_the_mean_of_the_ranks_gradients(tmp_path):
    """Averaged, not summed: Adam nearly hides a factor of 2 in the parameters, so the gradients
    themselves are compared with the mean of each rank's gradient computed in a single process."""

    from torchrl.data import Bounded

    from rlexp.algorithms.ppo import make_algorithm
    from rlexp.config.schema import AlgorithmConfig, PolicyConfig
    from rlexp.policies.actor_critic import make_policy

    run_worker_on_two_ranks(_GRAD_WORKER.replace("{CFG}", repr(_GRAD_CFG)), [str(tmp_path)])

    ranks = [torch.load(tmp_path / f"rank{r}.pt", weights_only=False) for r in (0, 1)]
    alone = []  # each rank's gradients, computed in this process with no sync
    for saved in ranks:
        pol = make_policy(PolicyConfig(), 5, 2, Bounded(-1.0, 1.0, shape=(2,)))
        pol.load_state_dict(saved["initial"])
        algo = make_algorithm(AlgorithmConfig(**_GRAD_CFG), pol, 1)
        algo.use_fused_step = False  # the ranks' path (distributed): optimizer.step is spied on
        stepped, step = [], algo.optimizer.step

        def record(*args, _stepped=stepped, _step=step, _algo=algo, **kwargs):
            _stepped.append([p.grad.clone() for p in _algo.params])
            return _step(*args, **kwargs)

        algo.optimizer.step = record
        algo.update(saved["batch"].clone())
        alone.append(stepped)

    assert len(ranks[0]["grads"]) == len(alone[0]) == 2  # two epochs of one minibatch each
    # The first step: both ranks start from the same parameters, so the synced gradient must be the
    # mean of what each rank computes alone (the second step follows from the first).
    first = [(a + b) / 2 for a, b in zip(alone[0][0], alone[1][0], strict=True)]
    assert any(not torch.allclose(a, b) for a, b in zip(alone[0][0], alone[1][0], strict=True))
    for r, saved in enumerate(ranks):
        for i, (got, want) in enumerate(zip(saved["grads"][0], first, strict=True)):
            torch.testing.assert_close(
                got, want, rtol=1e-5, atol=1e-7, msg=f"rank {r}, parameter {i}: not the mean"
            )
    for a, b in zip(ranks[0]["grads"][1], ranks[1]["grads"][1], strict=True):
        assert torch.equal(a, b), "the ranks stepped with different gradients"
