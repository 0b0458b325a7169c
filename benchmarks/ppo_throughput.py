"""Env-steps/s of full PPO training (collection + GAE + updates): rlexp against Stable-Baselines3, a
plain-PyTorch CleanRL-style PPO and a reference loop (physics alone + network work alone); plus start-up.

Every contender runs in a fresh subprocess with one torch thread (``--threads``), builds everything,
runs ``--warmup`` untimed iterations, then ``--iterations`` timed ones; start-up is never timed.
Contenders are interleaved (rlexp, sb3, cleanrl, physics, network, rlexp, ...) over ``--repeats``
rounds and the table reports medians. Settings (``--settings``):

- standard: HalfCheetah-v5, 1 env, 2048 steps per batch, 10 epochs, minibatch 64, 64x64 tanh;
- batched: PushCube (rlexp's native batched task, conf/env/push_cube.yaml), 64 envs x 1024 steps
  per batch, minibatch 8192, 10 epochs, lr 1e-4, entropy 0.01, 256x256 relu (the users' settings).

Start-up (``--startup-repeats``): seconds from launching ``python train.py`` (a tiny config) to its
first env step, against ``python -c "import torchrl"``. The first env step is read off the run's
``metrics.jsonl``: the wall time of the first row minus that iteration's collect and update times.

    PYTHONPATH=src .venv/bin/python benchmarks/ppo_throughput.py --quick          # smoke, < 2 min
    PYTHONPATH=src .venv/bin/python benchmarks/ppo_throughput.py --repeats 3      # the real table
    make bench ARGS="--settings standard --repeats 5"

Whole runs from launch to exit (start-up, evaluation, checkpoints and logging included) are
``benchmarks/end_to_end.py``; its sections of ``results.md`` are kept when this script rewrites it,
and ``--launch-to-exit whole,e2e`` runs its rows after the loop rows, into the same file (#18: the
whole process at 61,440 steps, ~3 min; 1M steps with evaluation on the default schedule, ~13 min):

    PYTHONPATH=src .venv/bin/python benchmarks/ppo_throughput.py --settings standard \
        --launch-to-exit whole,e2e
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CONTENDERS = ("rlexp", "rlexp_compiled", "sb3", "cleanrl", "physics", "network")
#: Extra overrides per rlexp contender. ``rlexp`` runs rlexp's defaults; at the benchmark's run length
#: ``algorithm.compile=auto`` keeps the loss eager (a real run of >= ~340k standard or ~2.8M batched
#: steps compiles it), so ``rlexp_compiled`` shows what those runs get.
RLEXP_OVERRIDES = {"rlexp": [], "rlexp_compiled": ["algorithm.compile=true"]}


@dataclass(frozen=True)
class Setting:
    env: str  # conf/env/<env>.yaml
    policy: str  # conf/policy/<policy>.yaml
    num_envs: int
    steps_per_env: int  # per batch
    num_epochs: int
    mini_batch_size: int
    lr: float
    entropy_coeff: float
    hidden_sizes: tuple[int, ...]
    activation: str

    @property
    def frames_per_batch(self) -> int:
        return self.num_envs * self.steps_per_env


SETTINGS = {
    "standard": Setting("half_cheetah", "mlp", 1, 2048, 10, 64, 3e-4, 0.0, (64, 64), "tanh"),
    "batched": Setting("push_cube", "mlp_256", 64, 1024, 10, 8192, 1e-4, 0.01, (256, 256), "relu"),
}
#: --quick: the batched setting with 128 steps per env (8192 frames, one minibatch per epoch).
QUICK_STEPS = {"standard": 2048, "batched": 128}


# -- configuration: every contender reads the same composed rlexp config ------------------------------
def compose(s: Setting, iterations: int, threads: int, seed: int, extra: list[str] | None = None):
    """rlexp's typed config for a setting, composed from conf/ exactly as ``python train.py`` does."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir

    from rlexp.config.paths import CONF_DIR
    from rlexp.config.schema import register_configs
    from rlexp.config.validate import to_root_config

    overrides = [
        f"env={s.env}",
        f"policy={s.policy}",
        f"env.num_envs={s.num_envs}",
        "env.num_eval_envs=0",
        f"trainer.frames_per_batch={s.frames_per_batch}",
        f"trainer.iterations={iterations}",
        "trainer.eval_every=0",
        "trainer.save_every=0",
        "trainer.progress=false",
        "trainer.device=cpu",
        "trainer.resume=never",
        f"trainer.torch_threads={threads}",
        f"algorithm.num_epochs={s.num_epochs}",
        f"algorithm.mini_batch_size={s.mini_batch_size}",
        f"algorithm.lr={s.lr}",
        f"algorithm.entropy_coeff={s.entropy_coeff}",
        "logger=none",
        f"seed={seed}",
        *(extra or []),
    ]
    register_configs()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return to_root_config(hydra_compose("config", overrides=overrides))


# -- the contenders (each runs in its own process) ----------------------------------------------------
def run_rlexp(s: Setting, config, warmup: int, iterations: int) -> list[float]:
    """``rlexp.app.train`` itself; the timestamps are taken after each iteration's ``log_train``."""
    from rlexp.app import train
    from rlexp.training.trainer import Trainer

    marks: list[float] = []
    log_train, train_loop = Trainer.log_train, Trainer.train

    def timed_log_train(self, losses):  # instrumentation only: the call itself is unchanged
        log_train(self, losses)
        marks.append(time.perf_counter())

    def timed_train(self, total):
        marks.append(time.perf_counter())
        return train_loop(self, total)

    Trainer.log_train, Trainer.train = timed_log_train, timed_train
    with tempfile.TemporaryDirectory() as run_dir:
        train(config, Path(run_dir))
    return marks


def run_sb3(s: Setting, config, warmup: int, iterations: int) -> list[float]:
    """SB3 ``PPO("MlpPolicy")`` with the same hyperparameters: ``VecNormalize`` for rlexp's observation
    normalisation and reward scaling, the learning rate annealed as rlexp's (``algorithm.anneal_lr``)."""
    import torch
    from stable_baselines3 import PPO
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.vec_env import VecNormalize

    a = config.algorithm
    venv = VecNormalize(
        _sb3_env(s, config),
        norm_obs=config.env.normalize_observations,
        clip_obs=config.env.clip_observations,
        # rlexp's reward scaling (algorithm.normalize_rewards / clip_rewards) is VecNormalize's
        norm_reward=a.normalize_rewards,
        clip_reward=a.clip_rewards if a.clip_rewards is not None else float("inf"),
        gamma=a.gamma,
    )
    lr = a.lr
    model = PPO(
        "MlpPolicy",
        venv,
        learning_rate=(lambda remaining: lr * remaining) if a.anneal_lr else lr,
        n_steps=s.steps_per_env,
        batch_size=s.mini_batch_size,
        n_epochs=s.num_epochs,
        gamma=a.gamma,
        gae_lambda=a.lmbda,
        clip_range=a.clip_epsilon,
        ent_coef=a.entropy_coeff,
        vf_coef=a.critic_coeff,
        max_grad_norm=a.max_grad_norm,
        policy_kwargs={
            "net_arch": {"pi": list(s.hidden_sizes), "vf": list(s.hidden_sizes)},
            "activation_fn": {"tanh": torch.nn.Tanh, "relu": torch.nn.ReLU}[s.activation],
        },
        device="cpu",
        seed=config.seed,
        verbose=0,
    )
    marks: list[float] = []

    class Marks(BaseCallback):
        def _on_rollout_start(self) -> None:
            marks.append(time.perf_counter())

        def _on_step(self) -> bool:
            return True

    model.learn(total_timesteps=(warmup + iterations) * s.frames_per_batch, callback=Marks())
    marks.append(time.perf_counter())
    return marks


def _sb3_env(s: Setting, config):
    from stable_baselines3.common.vec_env import DummyVecEnv

    if config.env.backend == "native":
        from sb3_adapter import make_sb3_vec_env

        from rlexp.envs.factory import make_env

        return make_sb3_vec_env(make_env(config.env, s.num_envs, config.seed))
    import gymnasium as gym

    return DummyVecEnv([lambda: gym.make(config.env.name) for _ in range(s.num_envs)])


def _gym_vector_env(s: Setting, config):
    """A Gymnasium vector env with same-step autoreset (CleanRL-style baseline, physics part)."""
    import gymnasium as gym

    if config.env.backend == "native":
        from sb3_adapter import NativeVectorEnv

        from rlexp.envs.factory import make_env

        return NativeVectorEnv(make_env(config.env, s.num_envs, config.seed))
    return gym.vector.SyncVectorEnv(
        [lambda: gym.make(config.env.name) for _ in range(s.num_envs)],
        autoreset_mode=gym.vector.AutoresetMode.SAME_STEP,
    )


def run_cleanrl(s: Setting, config, warmup: int, iterations: int) -> list[float]:
    """``benchmarks/cleanrl_ppo.py`` with the same hyperparameters."""
    import cleanrl_ppo

    a = config.algorithm
    args = cleanrl_ppo.Args(
        steps_per_env=s.steps_per_env,
        num_epochs=s.num_epochs,
        mini_batch_size=s.mini_batch_size,
        lr=a.lr,
        adam_eps=a.adam_eps,
        gamma=a.gamma,
        lmbda=a.lmbda,
        clip_epsilon=a.clip_epsilon,
        entropy_coeff=a.entropy_coeff,
        critic_coeff=a.critic_coeff,
        max_grad_norm=a.max_grad_norm,
        hidden_sizes=s.hidden_sizes,
        activation=s.activation,
        normalize_observations=config.env.normalize_observations,
        seed=config.seed,
    )
    envs = _gym_vector_env(s, config)
    marks = [time.perf_counter()]
    cleanrl_ppo.train(
        envs,
        args,
        (warmup + iterations) * s.frames_per_batch,
        lambda it, stats: marks.append(time.perf_counter()),
    )
    return marks


def run_physics(s: Setting, config, warmup: int, iterations: int) -> list[float]:
    """Reference part: the task's own step function with uniform random actions, nothing else (Gymnasium's
    ``env.step`` for the standard task; ``NativeEnv.step_action`` + auto-reset for the native one)."""
    import numpy as np

    rng = np.random.default_rng(config.seed)
    marks = [time.perf_counter()]
    if config.env.backend == "native":
        import torch

        from rlexp.envs.factory import make_env

        env = make_env(config.env, s.num_envs, config.seed)
        env.reset()
        shape = tuple(env.action_spec.shape)
        marks = [time.perf_counter()]
        for _ in range(warmup + iterations):
            for _ in range(s.steps_per_env):
                nxt = env.step_action(torch.rand(shape) * 2 - 1)
                env.autoreset_observation(nxt)
            marks.append(time.perf_counter())
        return marks
    import gymnasium as gym

    envs = [gym.make(config.env.name) for _ in range(s.num_envs)]
    for i, e in enumerate(envs):
        e.reset(seed=config.seed + i)
    low, high = envs[0].action_space.low, envs[0].action_space.high
    marks = [time.perf_counter()]
    for _ in range(warmup + iterations):
        for _ in range(s.steps_per_env):
            for e in envs:
                _, _, term, trunc, _ = e.step(rng.uniform(low, high).astype(np.float32))
                if term or trunc:
                    e.reset()
        marks.append(time.perf_counter())
    return marks


def run_network(s: Setting, config, warmup: int, iterations: int) -> list[float]:
    """Reference part: the network work of one PPO iteration in a tight plain-torch loop — an actor forward +
    Gaussian sample per env step, one batched critic pass over the rollout (+ bootstrap), then
    epochs x minibatches of actor + critic forward, clipped loss, backward, grad clip, Adam step."""
    import torch
    from cleanrl_ppo import mlp
    from torch import nn

    obs_dim, act_dim = _dims(config)
    n, T, mb = s.num_envs, s.steps_per_env, min(s.mini_batch_size, s.frames_per_batch)
    actor = mlp(obs_dim, act_dim, s.hidden_sizes, s.activation, 0.01)
    critic = mlp(obs_dim, 1, s.hidden_sizes, s.activation, 1.0)
    log_std = nn.Parameter(torch.zeros(act_dim))
    params = [*actor.parameters(), *critic.parameters(), log_std]
    a = config.algorithm
    opt = torch.optim.Adam(params, lr=a.lr, eps=a.adam_eps, fused=True)  # torch's fastest Adam
    scale, shift = torch.ones(obs_dim), torch.zeros(obs_dim)

    def norm(x):
        return torch.clamp(x * scale + shift, -10, 10)

    obs = torch.randn(T, n, obs_dim)
    flat_obs = obs.reshape(-1, obs_dim)
    b_act = torch.randn(T * n, act_dim)
    b_logp = torch.randn(T * n)
    b_adv = torch.randn(T * n)
    b_ret = torch.randn(T * n)
    marks = [time.perf_counter()]
    for _ in range(warmup + iterations):
        with torch.no_grad():
            for t in range(T):
                loc = actor(norm(obs[t]))
                std = log_std.exp()
                noise = torch.randn_like(loc)
                act = loc + std * noise
                (-0.5 * noise.pow(2) - log_std).sum(-1)
                del act
            critic(norm(torch.cat([flat_obs, obs[-1]])))
        for _ in range(s.num_epochs):
            perm = torch.randperm(T * n)
            for start in range(0, T * n - mb + 1, mb):
                idx = perm[start : start + mb]
                o = norm(flat_obs[idx])
                loc = actor(o)
                logp = (-0.5 * ((b_act[idx] - loc) / log_std.exp()).pow(2) - log_std).sum(-1)
                ratio = (logp - b_logp[idx]).exp()
                adv = b_adv[idx]
                adv = (adv - adv.mean()) / (adv.std() + 1e-8)
                pg = torch.max(-adv * ratio, -adv * ratio.clamp(0.8, 1.2)).mean()
                vl = (critic(o).squeeze(-1) - b_ret[idx]).pow(2).mean()
                loss = pg + 0.5 * vl - a.entropy_coeff * log_std.sum()
                opt.zero_grad(set_to_none=True)
                loss.backward()
                nn.utils.clip_grad_norm_(params, a.max_grad_norm)
                opt.step()
        marks.append(time.perf_counter())
    return marks


def _dims(config) -> tuple[int, int]:
    from rlexp.envs.factory import make_env

    env = make_env(config.env, 1, config.seed)
    dims = int(env.observation_spec["observation"].shape[-1]), int(env.action_spec.shape[-1])
    env.close()
    return dims


RUNNERS = {
    "rlexp": run_rlexp,
    "rlexp_compiled": run_rlexp,
    "sb3": run_sb3,
    "cleanrl": run_cleanrl,
    "physics": run_physics,
    "network": run_network,
}


def worker(args: argparse.Namespace) -> None:
    """One contender, one setting: print a ``RESULT {json}`` line with its timed env-steps/s."""
    import torch

    torch.set_num_threads(args.threads)
    sys.path.insert(0, str(Path(__file__).resolve().parent))  # cleanrl_ppo, sb3_adapter
    s = _setting(args)
    total_iters = args.warmup + args.iterations
    config = compose(s, total_iters, args.threads, args.seed, RLEXP_OVERRIDES.get(args.worker))
    torch.manual_seed(args.seed)
    marks = RUNNERS[args.worker](s, config, args.warmup, args.iterations)
    # marks[k] = the end of iteration k (marks[0]: the start of the first); time the last ones.
    if len(marks) != total_iters + 1:
        raise RuntimeError(
            f"{args.worker}: expected {total_iters + 1} timestamps, got {len(marks)}"
        )
    seconds = marks[-1] - marks[args.warmup]
    steps = args.iterations * s.frames_per_batch
    result = {
        "contender": args.worker,
        "steps": steps,
        "seconds": seconds,
        "sps": steps / seconds,
        "first_iteration": marks[1] - marks[0],  # includes rlexp_compiled's one-off compile
    }
    print("RESULT " + json.dumps(result), flush=True)


def _setting(args: argparse.Namespace) -> Setting:
    s = SETTINGS[args.setting]
    if args.steps_per_env:
        s = Setting(**{**asdict(s), "steps_per_env": args.steps_per_env})
    return s


# -- the driver ---------------------------------------------------------------------------------------
def run_contender(name: str, setting: str, args: argparse.Namespace, steps_per_env: int) -> dict:
    cmd = [
        sys.executable,
        __file__,
        "--worker", name,
        "--setting", setting,
        "--iterations", str(args.iterations),
        "--warmup", str(args.warmup),
        "--threads", str(args.threads),
        "--seed", str(args.seed),
        "--steps-per-env", str(steps_per_env),
    ]  # fmt: skip
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(ROOT / "src"), os.environ.get("PYTHONPATH", "")]),
    }
    env.setdefault("MUJOCO_GL", "egl")
    start = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=ROOT)
    wall = time.perf_counter() - start
    for line in proc.stdout.splitlines():
        if line.startswith("RESULT "):
            out = json.loads(line[len("RESULT ") :])
            out["wall"] = wall
            return out
    tail = (proc.stderr or proc.stdout).strip().splitlines()[-15:]
    raise RuntimeError(f"{name} ({setting}) failed (exit {proc.returncode}):\n" + "\n".join(tail))


def measure_startup(repeats: int) -> dict[str, list[float]]:
    """Seconds from launch to ``import torchrl`` done / to train.py's first env step."""
    py = sys.executable
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    out: dict[str, list[float]] = {
        "import_torch": [],
        "import_torchrl": [],
        "train_first_step": [],
        "train_total": [],
    }
    for _ in range(repeats):
        for key, code in (("import_torch", "import torch"), ("import_torchrl", "import torchrl")):
            t0 = time.time()
            subprocess.run([py, "-c", code], check=True, env=env, cwd=ROOT)
            out[key].append(time.time() - t0)
        with tempfile.TemporaryDirectory() as run_dir:
            cmd = [
                py, "train.py",
                "trainer.iterations=1", "trainer.frames_per_batch=64", "algorithm.mini_batch_size=64",
                "algorithm.num_epochs=1", "trainer.eval_every=0", "trainer.save_every=0",
                "env.num_eval_envs=0", "trainer.progress=false", "logger=none",
                f"hydra.run.dir={run_dir}",
            ]  # fmt: skip
            t0 = time.time()
            subprocess.run(cmd, check=True, env=env, cwd=ROOT, capture_output=True)
            out["train_total"].append(time.time() - t0)
            row = json.loads((Path(run_dir) / "metrics.jsonl").read_text().splitlines()[0])
            first_step = row["time"] - row["perf/collect_time"] - row["perf/update_time"]
            out["train_first_step"].append(first_step - t0)
    return out


def reference(physics: float, network: float) -> float:
    """The reference loop's env-steps/s: physics and network work back to back, no overlap and no
    overhead. Not a bound: it runs eager, without GAE, normaliser updates or buffer writes, so a
    trainer that fuses work (the compiled loss) can beat it."""
    return 1 / (1 / physics + 1 / network)


def fmt(x: float) -> str:
    return f"{x:,.0f}"


def report(
    results: dict,
    startup: dict | None,
    args: argparse.Namespace,
    started: str,
    first: dict | None = None,
) -> str:
    from machine import machine_note

    first = first or {}
    lines = [
        f"# PPO throughput ({started})",
        "",
        f"Machine: {machine_note()}.",
        f"Each cell: median env-steps/s over {args.repeats} interleaved round(s); each run "
        f"{args.warmup} warm-up + {args.iterations} timed iteration(s), its own process, "
        f"{args.threads} torch thread(s).{' --quick (batched: 128 steps/env).' if args.quick else ''}",
    ]
    if args.note:
        lines.append(f"Note: {args.note}")
    for setting, runs in results.items():
        s = SETTINGS[setting]
        steps = QUICK_STEPS[setting] if args.quick else (args.steps_per_env or s.steps_per_env)
        lines += [
            "",
            f"## {setting}: {s.env} x{s.num_envs}, {s.num_envs * steps} steps/batch, "
            f"{s.num_epochs} epochs, minibatch {s.mini_batch_size}, "
            f"{'x'.join(map(str, s.hidden_sizes))} {s.activation}",
            "",
            "| contender | env-steps/s (median) | min | max | rlexp / contender |",
            "|---|---:|---:|---:|---:|",
        ]
        med = {c: statistics.median(v) for c, v in runs.items() if v}
        spread: dict[str, list[float]] = {}
        if "physics" in med and "network" in med:
            # The reference loop combines its two parts: its min/max from theirs, not its median.
            med["reference"] = reference(med["physics"], med["network"])
            spread["reference"] = [
                reference(min(runs["physics"]), min(runs["network"])),
                reference(max(runs["physics"]), max(runs["network"])),
            ]
        for c in (*CONTENDERS, "reference"):
            if c not in med:
                continue
            vals = runs.get(c) or spread.get(c, [med[c]])
            ratio = f"{med['rlexp'] / med[c]:.2f}" if "rlexp" in med else ""
            name = {
                "physics": "physics alone (reference part)",
                "network": "network alone (reference part)",
                "reference": "**reference loop** = 1/(1/physics + 1/network)",
                "cleanrl": "CleanRL-style plain PyTorch",
                "sb3": "Stable-Baselines3 PPO",
                "rlexp": "rlexp (defaults)",
                "rlexp_compiled": "rlexp, algorithm.compile=true",
            }.get(c, c)
            lines.append(
                f"| {name} | {fmt(med[c])} | {fmt(min(vals))} | {fmt(max(vals))} | {ratio} |"
            )
        for mine in ("rlexp", "rlexp_compiled"):
            if mine in med:
                parts = [
                    f"{mine} / {k} = {med[mine] / med[k]:.2f}"
                    for k in ("sb3", "cleanrl", "reference")
                    if k in med
                ]
                lines += ["", "Ratios: " + ", ".join(parts) + "."]
        firsts = {c: statistics.median(v) for c, v in first.get(setting, {}).items() if v}
        if "rlexp_compiled" in firsts:
            eager = f" ({firsts['rlexp']:.1f} s eager)" if "rlexp" in firsts else ""
            lines += [
                "",
                f"rlexp_compiled's warm-up iteration, which compiles the loss, took "
                f"{firsts['rlexp_compiled']:.1f} s{eager} (inductor's on-disk cache makes later "
                "compiles of the same graph faster).",
            ]
    if startup:
        m = {k: statistics.median(v) for k, v in startup.items()}
        lines += [
            "",
            f"## Start-up (median of {len(startup['import_torchrl'])})",
            "",
            "| command | seconds |",
            "|---|---:|",
            f'| `python -c "import torch"` (to exit) | {m["import_torch"]:.2f} |',
            f'| `python -c "import torchrl"` (to exit) | {m["import_torchrl"]:.2f} |',
            f"| `python train.py` (tiny config) to its first env step | {m['train_first_step']:.2f} |",
            f"| `python train.py` (tiny config) to exit | {m['train_total']:.2f} |",
            "",
            f"train.py's first env step comes {m['train_first_step'] - m['import_torchrl']:+.2f} s after a "
            "bare torchrl import (target: within +1.5 s).",
        ]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument(
        "--settings", default="standard,batched", help="comma list: standard,batched"
    )
    parser.add_argument(
        "--contenders", default=",".join(CONTENDERS), help="comma list of " + ",".join(CONTENDERS)
    )
    parser.add_argument(
        "--repeats", type=int, default=3, help="interleaved rounds; medians are reported"
    )
    parser.add_argument("--iterations", type=int, default=3, help="timed PPO iterations per run")
    parser.add_argument("--warmup", type=int, default=1, help="untimed iterations first")
    parser.add_argument("--threads", type=int, default=1, help="torch threads per contender")
    parser.add_argument(
        "--steps-per-env", type=int, default=0, help="override the batch length per env"
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--quick",
        action="store_true",
        help="smoke run: 1 round, 1 iteration, batched with 128 steps/env",
    )
    parser.add_argument(
        "--startup-repeats", type=int, default=3, help="0 skips the start-up measurement"
    )
    parser.add_argument(
        "--note", default="", help="a line for the table (e.g. other load on the machine)"
    )
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results.md"))
    parser.add_argument(
        "--launch-to-exit",
        default="",
        metavar="ROW[,ROW]",
        help="then benchmarks/end_to_end.py's rows (whole: 61,440 steps; e2e: 1M with evaluation)",
    )
    parser.add_argument("--worker", choices=CONTENDERS, help=argparse.SUPPRESS)
    parser.add_argument("--setting", choices=list(SETTINGS), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        worker(args)
        return
    if args.quick:
        args.repeats, args.iterations, args.startup_repeats = 1, 1, min(args.startup_repeats, 1)
    settings = [x for x in args.settings.split(",") if x]
    contenders = [x for x in args.contenders.split(",") if x]
    for x in settings:
        if x not in SETTINGS:
            parser.error(f"--settings: unknown {x!r}; choose from {list(SETTINGS)}")
    for x in contenders:
        if x not in CONTENDERS:
            parser.error(f"--contenders: unknown {x!r}; choose from {list(CONTENDERS)}")
    from end_to_end import ROWS, kept_sections

    rows = [x for x in args.launch_to_exit.split(",") if x]
    for x in rows:
        if x not in ROWS:
            parser.error(f"--launch-to-exit: unknown {x!r}; choose from {list(ROWS)}")
    started = datetime.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z")
    results: dict[str, dict[str, list[float]]] = {x: {c: [] for c in contenders} for x in settings}
    first: dict[str, dict[str, list[float]]] = {x: {c: [] for c in contenders} for x in settings}
    for r in range(args.repeats):
        for setting in settings:
            steps = (
                QUICK_STEPS[setting]
                if args.quick
                else (args.steps_per_env or SETTINGS[setting].steps_per_env)
            )
            for c in contenders:
                out = run_contender(c, setting, args, steps)
                results[setting][c].append(out["sps"])
                first[setting][c].append(out["first_iteration"])
                print(
                    f"round {r + 1}/{args.repeats} {setting:8s} {c:14s} {out['sps']:10,.0f} env-steps/s "
                    f"({out['steps']} steps in {out['seconds']:.2f} s; process {out['wall']:.1f} s)",
                    flush=True,
                )
    startup = measure_startup(args.startup_repeats) if args.startup_repeats > 0 else None
    text = report(results, startup, args, started, first)
    print("\n" + text)
    out = Path(args.out)
    # benchmarks/end_to_end.py's sections (hours of runs) stay in the file
    out.write_text(text + (kept_sections(out.read_text()) if out.exists() else ""))
    print(f"written to {args.out}")
    for row in rows:  # each replaces its own section of the same file
        cmd = [sys.executable, str(Path(__file__).with_name("end_to_end.py")), "--row", row]
        subprocess.run([*cmd, "--out", str(out)], check=True)


if __name__ == "__main__":
    main()
