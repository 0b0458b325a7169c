"""The same Optuna search three ways (docs/sweeps.md, "Measured"): batches of n_jobs trials
(``hydra.sweeper.async_trials=false``), asynchronous workers, and asynchronous workers with ASHA
(``SuccessiveHalvingPruner``); each then confirms its best trials on fresh seeds. Prints, per
variant: the search's wall time, the whole sweep's (with the confirmation), trials pruned, the
best trial's search score and confirmed IQM (the search's optimism), and the confirmed winner.

    .venv/bin/python benchmarks/optuna_async.py --out multirun/optuna_async_bench
    .venv/bin/python benchmarks/optuna_async.py --trials 8 --frames 8192   # a quick look

Each variant is one ``python train.py -m ...`` process (launch to exit), on the local launcher
with 2 workers; the sampler is seeded (TPE, seed 0), so the asynchronous variants see the same
first proposals. Run on a quiet machine: the wall times are the measurement.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))

VARIANTS = {
    "batch": ["hydra.sweeper.async_trials=false"],
    "async": [],
    "async+asha": [
        "+hydra.sweeper.pruner={_target_:optuna.pruners.SuccessiveHalvingPruner,"
        "min_resource:EVAL,reduction_factor:3}"
    ],
}


def command(sweep: Path, args: argparse.Namespace, extra: list[str]) -> list[str]:
    return [
        sys.executable,
        str(ROOT / "train.py"),
        "-m",
        "+sweep=ppo_optuna",
        f"env={args.env}",
        "hydra/launcher=local",
        f"hydra.sweeper.n_trials={args.trials}",
        f"hydra.sweeper.n_jobs={args.workers}",
        f"+hydra.sweeper.confirm={{top_k:{args.top_k},seeds:{args.seeds}}}",
        f"trainer.total_frames={args.frames}",
        f"trainer.eval_every={args.eval_every}",
        f"trainer.save_every={args.frames}",
        "trainer.eval_episodes=5",
        "logger=none",
        *[e.replace("EVAL", str(args.eval_every)) for e in extra],
        f"hydra.sweep.dir={sweep}",
    ]


def summarize(sweep: Path) -> dict:
    import optuna

    from rlexp.analysis.reporting.confirm import optimism, read_confirmation

    storage = optuna.storages.JournalStorage(
        optuna.storages.journal.JournalFileBackend(str(sweep / "optuna.journal"))
    )
    trials = optuna.load_study(study_name=None, storage=storage).get_trials()
    states = [t.state.name for t in trials]
    found = read_confirmation(sweep)
    plan, rows = found if found else ({}, [])
    gap = optimism(plan, rows) if rows else None
    return {
        "complete": states.count("COMPLETE"),
        "pruned": states.count("PRUNED"),
        "failed": states.count("FAIL"),
        "best_search": gap[0] if gap else None,
        "best_confirmed": gap[1] if gap else None,
        "winner_trial": rows[0].trial if rows else None,
        "winner_iqm": rows[0].iqm if rows else None,
        "winner_ci": list(rows[0].ci) if rows else None,
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, default=ROOT / "multirun" / "optuna_async_bench")
    p.add_argument("--env", default="pendulum")
    p.add_argument("--trials", type=int, default=24)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--frames", type=int, default=24576)
    p.add_argument("--eval-every", type=int, default=4096)
    p.add_argument("--top-k", type=int, default=3)
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument("--variants", default=",".join(VARIANTS))
    args = p.parse_args()
    results = {}
    for name in args.variants.split(","):
        sweep = args.out / name.replace("+", "_")
        log = args.out / f"{name.replace('+', '_')}.log"
        log.parent.mkdir(parents=True, exist_ok=True)
        t0 = time.time()
        with open(log, "w") as f:
            rc = subprocess.call(command(sweep, args, VARIANTS[name]), stdout=f, stderr=f, cwd=ROOT)
        wall = time.time() - t0
        search_end = (sweep / "optimization_results.yaml").stat().st_mtime
        results[name] = {"rc": rc, "wall_s": wall, "search_s": search_end - t0, **summarize(sweep)}
        print(name, json.dumps(results[name]), flush=True)
    (args.out / "results.json").write_text(json.dumps(results, indent=2) + "\n")
    print(
        "| variant | search wall (s) | with confirmation (s) | complete / pruned | best trial: "
        "search score | its confirmed IQM | confirmed winner (trial: IQM [95% CI]) |"
    )
    print("|---|---|---|---|---|---|---|")
    for name, r in results.items():
        ci = r["winner_ci"] or [float("nan")] * 2
        print(
            f"| {name} | {r['search_s']:.0f} | {r['wall_s']:.0f} | {r['complete']} / {r['pruned']} "
            f"| {r['best_search']:.1f} | {r['best_confirmed']:.1f} | {r['winner_trial']}: "
            f"{r['winner_iqm']:.1f} [{ci[0]:.1f}, {ci[1]:.1f}] |"
        )


if __name__ == "__main__":
    main()
