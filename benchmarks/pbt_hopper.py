"""Population Based Training, measured (issue #33): a population on Hopper-v5 against independent
runs of the default config with the same total env steps, on this machine.

Three sweeps, one after another (each runs its members side by side, ``--population`` at once):

    python train.py -m +sweep=pbt env=hopper hooks.pbt.params.population_size=P seed=range(0,P) ...
    python train.py -m +sweep=pbt ... hooks.pbt.params.mode=sync
    python train.py -m env=hopper seed=range(0,P) hydra/launcher=local hydra.launcher.n_jobs=P ...

then a markdown table per sweep: the best member's final eval (``status.json``'s final_eval), the
IQM of the population's final evals, how many members reached CleanRL's Hopper return (2382.86,
analysis/reporting/anchors.py) and the median first eval step at which they did, the exploits, and the
sweep's wall time (launch to exit).

    python benchmarks/pbt_hopper.py                               # 4 x 1M steps each: hours on 2 cores
    python benchmarks/pbt_hopper.py --steps 200000 --ready 20000  # a shorter look
    python benchmarks/pbt_hopper.py --read benchmarks/out/pbt_hopper/<stamp>   # the table only
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
CLEANRL_HOPPER = 2382.86  # CleanRL's ppo_continuous_action, Hopper-v4, 1M steps (anchors.py)


def sweeps(p: int, steps: int, ready: int) -> dict[str, list[str]]:
    common = ["env=hopper", f"trainer.total_frames={steps}", "trainer.progress=false",
              f"seed=range(0,{p})"]  # fmt: skip
    pbt = ["+sweep=pbt", f"hooks.pbt.params.population_size={p}",
           f"hooks.pbt.params.ready_every={ready}"]  # fmt: skip
    return {
        "pbt_async": [*pbt, *common],
        "pbt_sync": [*pbt, *common, "hooks.pbt.params.mode=sync"],
        "independent": [
            *common,
            "hydra/launcher=local",
            f"hydra.launcher.n_jobs={p}",
            f"trainer.save_every={ready}",
        ],  # fmt: skip
    }


def first_reach(job: Path, threshold: float) -> int | None:
    for line in (job / "metrics.jsonl").read_text().splitlines():
        row = json.loads(line)
        if row.get("eval/episode_return", -np.inf) >= threshold:
            return int(row["step"])
    return None


def table(root: Path) -> str:
    from rlexp.analysis.stats import iqm

    rows = ["| sweep | best member final eval | population IQM | reached 2383 | median step "
            "to 2383 | exploits | wall s |", "|---|---|---|---|---|---|---|"]  # fmt: skip
    for name in ("pbt_async", "pbt_sync", "independent"):
        sweep = root / name
        jobs = sorted(p for p in sweep.glob("[0-9]*") if (p / "status.json").is_file())
        if not jobs:
            continue
        finals = [json.loads((j / "status.json").read_text())["final_eval"].get(
            "eval/episode_return", np.nan) for j in jobs]  # fmt: skip
        reach = [s for s in (first_reach(j, CLEANRL_HOPPER) for j in jobs) if s is not None]
        exploits = sum(
            line.count('"exploit"')
            for j in jobs
            if (j / "pbt" / "lineage.jsonl").is_file()
            for line in (j / "pbt" / "lineage.jsonl").read_text().splitlines()
        )
        wall = (
            (sweep / "wall_s.txt").read_text().strip() if (sweep / "wall_s.txt").is_file() else "-"
        )
        median = f"{np.median(reach):.0f}" if reach else "-"
        rows.append(f"| {name} | {np.nanmax(finals):.1f} | {float(iqm(np.array(finals))):.1f} | "
                    f"{len(reach)}/{len(jobs)} | {median} | {exploits} | {wall} |")  # fmt: skip
    return "\n".join(rows)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--population", type=int, default=4)
    ap.add_argument("--steps", type=int, default=1_000_000, help="env steps per member")
    ap.add_argument("--ready", type=int, default=50_000, help="hooks.pbt.params.ready_every")
    ap.add_argument("--only", nargs="*", default=None, help="pbt_async, pbt_sync, independent")
    ap.add_argument("--read", type=Path, default=None, help="print the table of an earlier run")
    args = ap.parse_args()
    if args.read is not None:
        print(table(args.read))
        return
    root = REPO / "benchmarks" / "out" / "pbt_hopper" / time.strftime("%Y%m%d-%H%M%S")
    for name, overrides in sweeps(args.population, args.steps, args.ready).items():
        if args.only and name not in args.only:
            continue
        cmd = [sys.executable, str(REPO / "train.py"), "-m", *overrides,
               f"hydra.sweep.dir={root / name}"]  # fmt: skip
        print(" ".join(cmd[1:]), flush=True)
        t0 = time.perf_counter()
        subprocess.run(cmd, cwd=REPO, check=False)
        (root / name).mkdir(parents=True, exist_ok=True)
        (root / name / "wall_s.txt").write_text(f"{time.perf_counter() - t0:.0f}\n")
    print(table(root))
    print(f"\n(runs in {root}; rlexp report {root}/pbt_async for the lineage and schedules)")


if __name__ == "__main__":
    main()
