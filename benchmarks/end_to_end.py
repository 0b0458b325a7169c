"""Launch-to-exit wall time of whole training runs: rlexp's ``python train.py`` against a
Stable-Baselines3 script doing the same job (issue #18 "the benchmark measures what users wait for",
issue #15 "time to result").

Two rows (``--row``, presets of the options below); each run writes a section of
``benchmarks/results.md`` (``--out``), replacing the section with the same heading:

- ``whole``: 61,440 env steps (30 PPO iterations of 2048), 3 alternating rounds. Target: rlexp
  >= 1.5x SB3.
- ``e2e``: 1M env steps with evaluation on the default schedule (every 50,000 steps, 10 episodes);
  rlexp with ``trainer.eval_async=false`` and ``=true`` (``--variant``), and SB3; 1 round. Target:
  rlexp >= 1.8x SB3.

Every row also gives env-steps/s (env steps / launch-to-exit seconds), the final training return
(mean of the last 100 episodes), the last evaluation's mean return, and the time to result: the
seconds from launch at which the mean of the last 100 training episodes first reaches ``--anchor``
(default: CleanRL's PPO at 1M steps: HalfCheetah 1,443, Hopper 2,383, Walker2d 2,288; other tasks
need ``--anchor`` for this column).

What runs. rlexp: ``python train.py env=<env> trainer.total_frames=<steps> hydra.run.dir=<dir>``
plus the variant's overrides (and ``trainer.eval_every=`` with ``--eval-every``), the default config
otherwise: TensorBoard + metrics.jsonl + console lines, evaluation every ``trainer.eval_every``
steps (10 deterministic episodes on the env's eval copies), checkpoints every
``trainer.save_every`` steps and at the end, ``algorithm.compile=auto``, one torch thread; no
progress bar (its output is a file, not a terminal). SB3: ``benchmarks/sb3_ppo.py`` with every flag
filled in from the same composed rlexp config (PPO hyperparameters; VecNormalize for rlexp's
observation and reward normalisation; the eval schedule and episodes; the checkpoint interval;
TensorBoard; seed; threads) — the first variant's config, when variants differ; its eval env has
one copy (rl-zoo's default, ``--sb3-eval-envs``). A config the SB3 script cannot mirror is refused
before anything runs, and so is a variant whose overrides do not compose.

Timing. The parent takes ``time.perf_counter()`` around ``subprocess.run`` of each run (stdout and
stderr go to ``<run dir>.log`` beside it); within a round the contenders run one after another
(rlexp variants, then SB3), rounds repeat that order, and the table gives medians over rounds. Time
to result is ``time.time()`` at the event minus the parent's ``time.time()`` just before launch:
rlexp's event is the first metrics.jsonl row with ``train/episode_return`` >= anchor (its ``time``
minus its ``perf/update_time``: the end of that rollout), SB3's a callback at each rollout end
over ``model.ep_info_buffer``.

    python benchmarks/end_to_end.py --row whole                              # ~5 min on 2 cores
    python benchmarks/end_to_end.py --row e2e                                # ~35 min on 2 cores
    python benchmarks/end_to_end.py --row e2e --env hopper                   # or walker2d, ...
    python benchmarks/end_to_end.py --row e2e --variant sync: \
        --variant overlap:algorithm.overlap=true --no-sb3 --no-floors        # ~6 min on 2 cores
    python benchmarks/end_to_end.py --row whole --steps 4096 --eval-every 2048 --rounds 1 \\
        --out /tmp/e2e.md                                                    # smoke, ~1 min
    make bench-e2e ARGS="--row whole"
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import shlex
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(ROOT / "src"))
sys.path.insert(0, str(HERE))
from phase_floors import floor_table, measure_floors, phase_sums  # noqa: E402

#: The time-to-result anchors of #15: CleanRL's ppo_continuous_action.py at 1M env steps, the mean
#: return of the last 100 training episodes, mean of 3 seeds on the v4 tasks (CleanRL's
#: docs/benchmark/ppo_continuous_action.md; the same numbers as rlexp.analysis.reporting.anchors).
ANCHORS = {"half_cheetah": 1442.64, "hopper": 2382.86, "walker2d": 2287.95}
#: The heading every section of this benchmark starts with (``ppo_throughput.py`` keeps them).
SECTION = "## Launch to exit: "
#: Stands for a run's own directory in the command templates.
RUN_DIR = "<run dir>"


@dataclass(frozen=True)
class Row:
    steps: int
    rounds: int
    variants: tuple[str, ...]  # LABEL:OVERRIDES of the rlexp runs
    target: float  # rlexp's launch-to-exit speed-up over SB3 that the issue asks for


ROWS = {
    "whole": Row(61_440, 3, ("defaults:",), 1.5),
    "e2e": Row(
        1_000_000,
        1,
        ("eval sync:trainer.eval_async=false", "eval async:trainer.eval_async=true"),
        1.8,
    ),
}


@dataclass(frozen=True)
class Contender:
    label: str
    kind: str  # rlexp | sb3
    template: tuple[str, ...]  # the command, RUN_DIR standing for the run's directory

    def command(self, run_dir: Path) -> list[str]:
        cmd = [a.replace(RUN_DIR, str(run_dir)) for a in self.template]
        return [sys.executable, *cmd[1:]]  # "python": this interpreter (the venv's)

    def shown(self) -> str:
        return shlex.join(self.template)


# -- configuration -------------------------------------------------------------------------------------
def gym_id(config) -> str:
    """The Gymnasium id of the row's env (``env.name`` of a Gymnasium task)."""
    return config.env.name


def compose(overrides: list[str]):
    """rlexp's typed config, composed from conf/ exactly as ``python train.py`` does."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir

    from rlexp.config.paths import CONF_DIR
    from rlexp.config.schema import register_configs
    from rlexp.config.validate import to_root_config

    register_configs()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return to_root_config(hydra_compose("config", overrides=overrides))


def sb3_flags(config, eval_envs: int) -> list[str]:
    """``sb3_ppo.py``'s flags for the job an rlexp config describes; ``ValueError`` naming each
    setting the script cannot mirror."""
    from rlexp.config.validate import total_frames
    from rlexp.training.build import EVAL_SEED_OFFSET

    e, a, p, t, lg = config.env, config.algorithm, config.policy, config.trainer, config.logger
    problems = [
        msg
        for bad, msg in (
            (e.backend != "gymnasium", f"env.backend={e.backend} (the script runs Gymnasium ids)"),
            (bool(e.kwargs) or e.max_episode_steps is not None, "env.kwargs / max_episode_steps"),
            (a.name != "ppo", f"algorithm={a.name}"),
            (p.name != "actor_critic", f"policy.name={p.name}"),
            (
                p.actor.activation != p.critic.activation,
                "different actor and critic activations (SB3 takes one activation_fn)",
            ),
            (a.desired_kl is not None, "algorithm.desired_kl"),
            (a.loss_critic_type != "l2", f"algorithm.loss_critic_type={a.loss_critic_type}"),
            (
                a.clip_rewards is not None and not a.normalize_rewards,
                "algorithm.clip_rewards without normalize_rewards (VecNormalize clips the scaled "
                "rewards only)",
            ),
            (t.frames_per_batch % e.num_envs != 0, "frames_per_batch not a multiple of num_envs"),
            (bool(config.hooks), "hooks"),
            (bool(config.events.train) or bool(config.events.eval), "events"),
            (lg.wandb.enabled, "logger.wandb"),
        )
        if bad
    ]
    if problems:
        raise ValueError("sb3_ppo.py cannot mirror this rlexp config: " + "; ".join(problems))

    def on(flag: str, value: bool) -> str:
        return f"--{flag}" if value else f"--no-{flag}"

    def num(x: float | None) -> str:
        return "inf" if x is None else repr(x)

    return [
        "--env-id", e.name,
        "--num-envs", str(e.num_envs),
        "--steps", str(total_frames(config)),
        "--seed", str(config.seed),
        "--eval-seed", str(config.seed + EVAL_SEED_OFFSET),
        "--threads", str(t.torch_threads),
        "--n-steps", str(t.frames_per_batch // e.num_envs),
        "--batch-size", str(a.mini_batch_size),
        "--n-epochs", str(a.num_epochs),
        "--lr", repr(a.lr),
        on("anneal-lr", a.anneal_lr),
        "--adam-eps", repr(a.adam_eps),
        "--gamma", repr(a.gamma),
        "--gae-lambda", repr(a.lmbda),
        "--clip-range", repr(a.clip_epsilon),
        *(["--clip-range-vf", repr(a.clip_value)] if a.clip_value is not None else []),
        "--ent-coef", repr(a.entropy_coeff),
        "--vf-coef", repr(a.critic_coeff),
        "--max-grad-norm", num(a.max_grad_norm if a.max_grad_norm > 0 else None),
        on("normalize-advantage", a.normalize_advantage),
        "--pi-arch", ",".join(map(str, p.actor.hidden_sizes)),
        "--vf-arch", ",".join(map(str, p.critic.hidden_sizes)),
        "--activation", p.actor.activation,
        "--log-std-init", repr(p.init_log_std),
        on("ortho-init", p.ortho_init),
        on("norm-obs", e.normalize_observations),
        "--clip-obs", repr(e.clip_observations),
        on("norm-reward", a.normalize_rewards),
        "--clip-reward", num(a.clip_rewards),
        "--eval-every", str(t.eval_every),
        "--eval-episodes", str(t.eval_episodes),
        "--eval-envs", str(eval_envs),
        "--save-every", str(t.save_every),
        on("tensorboard", lg.tensorboard.enabled),
        "--verbose", "1" if lg.console else "0",
    ]  # fmt: skip


def held_equal(config, eval_envs: int) -> str:
    """One paragraph: the job both sides do, read off the composed config."""
    e, a, p, t, lg = config.env, config.algorithm, config.policy, config.trainer, config.logger
    net = "x".join(map(str, p.actor.hidden_sizes))
    lr = f"lr {a.lr:g}" + (" annealed linearly to 0" if a.anneal_lr else "")
    norm = [
        f"observation normalisation (clip {e.clip_observations:g})"
        if e.normalize_observations
        else "",
        f"reward scaling (clip {a.clip_rewards:g})" if a.normalize_rewards else "",
    ]
    evals = (
        f"evaluation every {t.eval_every:,} steps, {t.eval_episodes} deterministic episodes "
        f"(rlexp on {e.num_eval_envs} eval env copies, SB3 on {eval_envs})"
        if t.eval_every > 0 and t.eval_episodes > 0
        else "no evaluation"
    )
    saves = (
        f"checkpoints every {t.save_every:,} steps and at the end"
        if t.save_every > 0
        else "a checkpoint at the end"
    )
    logs = ", ".join(
        x
        for x in (
            "TensorBoard" if lg.tensorboard.enabled else "",
            "console lines" if lg.console else "",
        )
        if x
    )
    return (
        f"Held equal (read off rlexp's composed config): {e.name} x{e.num_envs}, "
        f"{t.frames_per_batch} steps per rollout, {a.num_epochs} epochs, minibatch "
        f"{a.mini_batch_size}, {lr}, gamma {a.gamma:g}, GAE {a.lmbda:g}, clip {a.clip_epsilon:g}, "
        f"entropy {a.entropy_coeff:g}, value {a.critic_coeff:g}, grad-norm {a.max_grad_norm:g}, "
        f"{net} {p.actor.activation} actor and critic (separate), "
        f"{' and '.join(x for x in norm if x) or 'no normalisation'}, {t.torch_threads} torch "
        f"thread(s), seed {config.seed}; {evals}; {saves}; the best model saved on improvement; "
        f"{logs or 'no logging'}. rlexp also writes metrics.jsonl (SB3 an evaluations.npz) and "
        f"runs with algorithm.compile={a.compile}."
    )


# -- running -------------------------------------------------------------------------------------------
def run_once(c: Contender, run_dir: Path, anchor: float | None) -> dict:
    """Launch one run, time it to its exit, and read its results."""
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    log = run_dir.with_name(run_dir.name + ".log")  # beside the run dir: rlexp creates its own
    with open(log, "w") as out:
        launch = time.time()
        t0 = time.perf_counter()
        proc = subprocess.run(
            c.command(run_dir), stdout=out, stderr=subprocess.STDOUT, env=env, cwd=ROOT
        )
        wall = time.perf_counter() - t0
    if proc.returncode != 0:
        tail = log.read_text().strip().splitlines()[-15:]
        raise RuntimeError(f"{c.label} exited {proc.returncode}:\n" + "\n".join(tail))
    out = read_rlexp(run_dir, anchor) if c.kind == "rlexp" else read_sb3(run_dir)
    if c.kind == "rlexp":
        out.update(phase_sums(run_dir))
    hit = out.pop("anchor_time")
    out["anchor_s"] = hit - launch if hit is not None else None
    out["wall"] = wall
    return out


def read_rlexp(run_dir: Path, anchor: float | None) -> dict:
    """Steps, returns and the anchor's time from an rlexp run dir (status.json, metrics.jsonl)."""
    status = json.loads((run_dir / "status.json").read_text())
    if status.get("state") != "finished":
        raise RuntimeError(f"rlexp run in {run_dir} ended {status.get('state')!r}")
    rows = [json.loads(x) for x in (run_dir / "metrics.jsonl").read_text().splitlines() if x]
    train = [r for r in rows if "train/episode_return" in r]
    evals = [r for r in rows if "eval/episode_return" in r]
    hit = next(
        (r for r in train if anchor is not None and r["train/episode_return"] >= anchor), None
    )
    return {
        "steps": int(status["global_step"]),
        "final_train_return": train[-1]["train/episode_return"] if train else None,
        "final_eval_return": evals[-1]["eval/episode_return"] if evals else None,
        "eval_rounds": len(evals),
        # the row is written after the update: its rollout ended perf/update_time earlier
        "anchor_time": hit["time"] - hit.get("perf/update_time", 0.0) if hit else None,
        "anchor_step": hit["step"] if hit else None,
    }


def read_sb3(run_dir: Path) -> dict:
    """The same from ``sb3_ppo.py``'s result.json."""
    res = json.loads((run_dir / "result.json").read_text())
    hit = res.pop("anchor")
    res["anchor_time"] = hit["time"] if hit else None
    res["anchor_step"] = hit["step"] if hit else None
    return res


# -- the report ----------------------------------------------------------------------------------------
def median_or_none(values: list) -> float | None:
    vals = [v for v in values if v is not None]
    return statistics.median(vals) if vals else None


def cell(x: float | None, spec: str = ",.0f") -> str:
    return "—" if x is None or (isinstance(x, float) and math.isnan(x)) else format(x, spec)


def report(
    contenders: list[Contender],
    runs: dict[str, list[dict]],
    args: argparse.Namespace,
    heading: str,
    config,
    machine: str,
    target: float | None,
    floors: dict | None = None,
) -> str:
    anchor = args.anchor
    anchor_col = f"reaches {anchor:,.0f} at s (step)" if anchor is not None else "time to result"
    lines = [
        heading,
        "",
        f"Machine: {machine}; load average {os.getloadavg()[0]:.1f} at the end.",
        f"Each cell: median over {args.rounds} round(s); in each round the runs go one after "
        f"another in the table's order; each run is its own process, timed by the parent from "
        f"launch to exit (`time.perf_counter()` around `subprocess.run`).",
        "",
        held_equal(config, args.sb3_eval_envs),
    ]
    if args.note:
        lines += ["", f"Note: {args.note}"]
    lines += [
        "",
        f"| run | launch → exit s (median) | min | max | env-steps/s | SB3 s / run s "
        f"| final train return (last 100 ep) | final eval return | eval rounds | {anchor_col} |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    sb3 = statistics.median(r["wall"] for r in runs["sb3"]) if runs.get("sb3") else None
    med: dict[str, dict] = {}
    for c in contenders:
        rs = runs[c.label]
        walls = [r["wall"] for r in rs]
        m = {
            k: median_or_none([r[k] for r in rs])
            for k in (
                "steps",
                "final_train_return",
                "final_eval_return",
                "eval_rounds",
                "anchor_s",
                "anchor_step",
            )
        }
        m["wall"] = statistics.median(walls)
        med[c.label] = m
        reached = sum(r["anchor_s"] is not None for r in rs)
        if anchor is None:
            hit = "—"
        elif m["anchor_s"] is None:
            hit = "not reached"
        else:
            hit = f"{m['anchor_s']:,.0f} ({m['anchor_step']:,.0f})"
            if reached < len(rs):
                hit += f", {reached}/{len(rs)} runs"
        lines.append(
            f"| {c.label} | {m['wall']:,.1f} | {min(walls):,.1f} | {max(walls):,.1f} "
            f"| {cell(m['steps'] / m['wall'])} | {cell(sb3 / m['wall'] if sb3 else None, '.2f')} "
            f"| {cell(m['final_train_return'])} | {cell(m['final_eval_return'])} "
            f"| {cell(m['eval_rounds'], '.0f')} | {hit} |"
        )
    if args.rounds > 1:
        per_round = "; ".join(
            f"{c.label} " + " / ".join(f"{r['wall']:.1f}" for r in runs[c.label])
            for c in contenders
        )
        lines += ["", f"Per round, launch → exit s: {per_round}."]
    if sb3 is not None:
        mine = [c.label for c in contenders if c.kind == "rlexp"]
        speed = ", ".join(f"{x} **{sb3 / med[x]['wall']:.2f}x**" for x in mine)
        goal = f" (target: rlexp >= {target:g}x SB3)" if target else ""
        lines += ["", f"rlexp's speed-up over SB3, launch to exit{goal}: {speed}."]
        sb3_hit = med["sb3"]["anchor_s"]
        hits = [f"{x} {med[x]['anchor_s']:,.0f} s" for x in mine if med[x]["anchor_s"] is not None]
        if anchor is not None and (hits or sb3_hit is not None):
            ratio = ", ".join(
                f"{x} {sb3_hit / med[x]['anchor_s']:.2f}x"
                for x in mine
                if sb3_hit is not None and med[x]["anchor_s"] is not None
            )
            lines += [
                "",
                f"Time to result (#15; mean of the last 100 training episodes >= {anchor:,.0f}): "
                f"{', '.join(hits) or 'rlexp not reached'}; SB3 "
                f"{f'{sb3_hit:,.0f} s' if sb3_hit is not None else 'not reached'}"
                f"{f'; SB3 s / rlexp s: {ratio}' if ratio else ''}.",
            ]
    if floors is not None:
        mine = [c.label for c in contenders if c.kind == "rlexp"]
        lines += ["", floor_table(floors, runs, mine, config)]
    lines += [
        "",
        f"Commands (`{RUN_DIR}`: a fresh directory per run; `python` is the venv's):",
        "",
        "```",
        *(c.shown() for c in contenders),
        "```",
        "",
        f"Driver: `{shlex.join(['python', 'benchmarks/end_to_end.py', *sys.argv[1:]])}`",
    ]
    return "\n".join(lines) + "\n"


def kept_sections(text: str) -> str:
    """The sections of this benchmark in a results file (``ppo_throughput.py`` keeps them when it
    rewrites the file): from each ``SECTION`` heading to the next ``## `` heading."""
    out: list[str] = []
    keep = False
    for line in text.splitlines():
        if line.startswith("## "):
            keep = line.startswith((SECTION, SECTION.replace(":", " (rlexp variants):")))
        if keep:
            out.append(line)
    return ("\n" + "\n".join(out).rstrip() + "\n") if out else ""


def write_section(path: Path, key: str, section: str) -> None:
    """Replace the section whose heading starts with ``key`` in ``path``, or append it."""
    old = path.read_text().splitlines() if path.exists() else []
    start = next((i for i, line in enumerate(old) if line.startswith(key)), None)
    new = section.rstrip().splitlines()
    if start is None:
        lines = [*old, *([""] if old else []), *new]
    else:
        end = next(
            (i for i in range(start + 1, len(old)) if old[i].startswith("## ")),
            len(old),
        )
        tail = old[end:]
        lines = [*old[:start], *new, *([""] if tail else []), *tail]
    path.write_text("\n".join(lines).rstrip() + "\n")


# -- the driver ----------------------------------------------------------------------------------------
def contenders_for(args: argparse.Namespace) -> tuple[list[Contender], object]:
    """The runs of a row and the composed config of the first rlexp variant (what SB3 mirrors)."""
    base = [f"env={args.env}", f"trainer.total_frames={args.steps}"]
    if args.eval_every is not None:
        base.append(f"trainer.eval_every={args.eval_every}")
    if args.seed is not None:
        base.append(f"seed={args.seed}")
    out, configs = [], []
    for variant in args.variant:
        label, _, extra = variant.partition(":")
        overrides = [*base, *extra.split()]
        try:
            configs.append(compose(overrides))
        except Exception as exc:  # Hydra's own message names the key
            raise SystemExit(
                f"--variant {variant!r}: rlexp's config does not compose with "
                f"{' '.join(overrides)}: {str(exc).splitlines()[0]}"
            ) from None
        label = "rlexp" + (f" ({label})" if label else "")
        cmd = ("python", "train.py", *overrides, f"hydra.run.dir={RUN_DIR}")
        out.append(Contender(label, "rlexp", cmd))
    config = configs[0]
    if args.no_sb3:
        return out, config
    flags = sb3_flags(config, args.sb3_eval_envs)
    if args.anchor is not None:
        flags += ["--anchor", repr(args.anchor)]
    cmd = ("python", "benchmarks/sb3_ppo.py", *flags, "--run-dir", RUN_DIR)
    out.append(Contender("sb3", "sb3", cmd))
    return out, config


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__.splitlines()[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--row", choices=list(ROWS), default="whole", help="preset (see above)")
    parser.add_argument("--env", default="half_cheetah", help="conf/env/<env>.yaml (Gymnasium)")
    parser.add_argument("--steps", type=int, help="env steps (whole: 61440, e2e: 1000000)")
    parser.add_argument("--rounds", type=int, help="alternating rounds (whole: 3, e2e: 1)")
    parser.add_argument(
        "--variant",
        action="append",
        help="rlexp run as LABEL:OVERRIDES, repeatable (whole: 'defaults:'; e2e: "
        "'eval sync:trainer.eval_async=false' and 'eval async:trainer.eval_async=true')",
    )
    parser.add_argument(
        "--eval-every", type=int, help="trainer.eval_every for every run (default: the config's)"
    )
    parser.add_argument("--seed", type=int, help="seed= for every run (default: the config's)")
    parser.add_argument(
        "--anchor",
        type=float,
        help=f"training return for the time to result (default: {ANCHORS} where known)",
    )
    parser.add_argument("--sb3-eval-envs", type=int, default=1, help="SB3's eval env copies")
    parser.add_argument("--note", default="", help="a line for the section (e.g. other load)")
    parser.add_argument("--out", type=Path, default=HERE / "results.md")
    parser.add_argument("--keep-runs", type=Path, help="keep the run dirs under this directory")
    parser.add_argument("--dry-run", action="store_true", help="print the commands and stop")
    parser.add_argument(
        "--no-sb3",
        action="store_true",
        help="rlexp's variants alone (e.g. sync against algorithm.overlap=true), no SB3 run",
    )
    parser.add_argument(
        "--no-floors",
        action="store_true",
        help="skip the floors (benchmarks/floors.py, measured first in this invocation)",
    )
    args = parser.parse_args()
    row = ROWS[args.row]
    args.steps = args.steps or row.steps
    args.rounds = args.rounds or row.rounds
    args.variant = args.variant or list(row.variants)
    if args.anchor is None:
        args.anchor = ANCHORS.get(args.env)

    contenders, config = contenders_for(args)
    if args.dry_run:
        print("\n".join(c.shown() for c in contenders))
        return
    from machine import machine_note

    machine = machine_note()
    started = datetime.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z")
    eval_every = config.trainer.eval_every
    section = SECTION.replace(":", " (rlexp variants):") if args.no_sb3 else SECTION
    key = f"{section}{args.env}, {args.steps:,} env steps"  # --no-sb3: SB3's section stays
    heading = (
        f"{key}, eval every {eval_every:,} ({started})" if eval_every else f"{key} ({started})"
    )
    work = args.keep_runs or Path(tempfile.mkdtemp(prefix="rlexp_e2e_"))
    work.mkdir(parents=True, exist_ok=True)
    runs: dict[str, list[dict]] = {c.label: [] for c in contenders}
    floors = None
    if not args.no_floors:  # the floors of this row, in this invocation, before the runs
        floors = measure_floors(gym_id(config), max(config.policy.actor.hidden_sizes))
        print(f"floors: {floors}", flush=True)
    try:
        for r in range(args.rounds):
            for i, c in enumerate(contenders):
                out = run_once(c, work / f"round{r + 1}_{i}_{c.kind}", args.anchor)
                runs[c.label].append(out)
                hit = f", anchor at {out['anchor_s']:.0f} s" if out["anchor_s"] is not None else ""
                print(
                    f"round {r + 1}/{args.rounds} {c.label:22s} {out['wall']:8.1f} s launch to exit, "
                    f"{out['steps']:,} steps, train return {cell(out['final_train_return'])}, "
                    f"eval return {cell(out['final_eval_return'])}{hit}",
                    flush=True,
                )
    finally:
        if args.keep_runs is None:
            shutil.rmtree(work, ignore_errors=True)
    target = row.target if args.steps == row.steps else None
    text = report(contenders, runs, args, heading, config, machine, target, floors)
    print("\n" + text)
    write_section(args.out, key, text)
    print(f"written to {args.out}")


if __name__ == "__main__":
    main()
