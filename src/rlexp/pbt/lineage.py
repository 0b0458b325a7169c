"""Reading a PBT population after (or while) it runs: each member's hyperparameter schedule, the
best member and its lineage (whose weights it carries, back to step 0), the ``rlexp report``
section and figure, and the export of a member's schedule as a ``hooks`` config that replays it
without a population (``python train.py hooks=<name>``: the ``piecewise`` hook)."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rlexp.files import safe_read
from rlexp.pbt.population import (
    LINEAGE,
    PBT_DIR,
    job_names,
    name_strays,
    out_of_range,
    read_lineage,
    read_ready,
    scan,
)

log = logging.getLogger(__name__)


@dataclass
class Member:
    """One member's files, read once."""

    name: str
    path: Path
    lineage: list[dict[str, Any]]
    final: float | None  # its final eval (status.json) or, without one, its last ready score
    step: int  # the last step it reported
    problems: list[str] = field(default_factory=list)  # lines of its ready.jsonl left out: why

    def schedule(self) -> dict[str, list[tuple[int, float]]]:
        """Each tuned hyperparameter as (step, value from that step on), from its lineage (checked
        on reading: steps never go back); two records at one step: the later one's value."""
        out: dict[str, list[tuple[int, float]]] = {}
        for rec in self.lineage:
            values = rec.get("hyperparameters") if rec.get("event") == "start" else rec.get("new")
            for name, value in (values or {}).items():
                points = out.setdefault(str(name), [])
                step = int(rec["step"])
                if points and points[-1][0] == step:
                    points.pop()
                if not points or points[-1][1] != float(value):
                    points.append((step, float(value)))
        return out

    def current(self) -> dict[str, float]:
        """The hyperparameters it trains with now (as its lineage last set them)."""
        return {name: points[-1][1] for name, points in self.schedule().items()}


def is_member(run_dir: Path) -> bool:
    return (run_dir / PBT_DIR / LINEAGE).is_file()


def read_member(run_dir: Path, metric: str = "eval/episode_return") -> Member:
    """A member's files, read bounded and checked; Unreadable (the file, the line and the value)
    when its lineage cannot be used; lines of its ready.jsonl that fail are left out
    (``Member.problems``)."""
    try:
        lineage = read_lineage(run_dir)
    except safe_read.Unreadable as exc:
        raise safe_read.Unreadable(f"{PBT_DIR}/{LINEAGE} {exc}") from None
    problems: list[str] = []
    ready = read_ready(run_dir, problems)
    final = None
    try:
        status = safe_read.read_checked(run_dir / "status.json", safe_read.STATUS_FIELDS)
        value = (status.get("final_eval") or {}).get(metric)
        final = float(value) if isinstance(value, (int, float)) and math.isfinite(value) else None
    except safe_read.Unreadable:  # named by whoever lists the run (rlexp runs, report)
        status = {}
    if final is None and ready and ready[-1].score is not None:
        final = ready[-1].score
    step = max([int(status.get("global_step") or 0)] + [r.step for r in ready])
    return Member(run_dir.name, run_dir, lineage, final, step, problems)


def population_size_of(sweep_dir: Path) -> int | None:
    """The PBT population's size as the sweep's ``multirun.yaml`` sets it (None: not known)."""
    from rlexp.pbt.config import population_size

    try:
        data = safe_read.load_yaml(Path(sweep_dir) / "multirun.yaml")
        size = population_size(data.get("hooks") if isinstance(data, dict) else None)
    except (safe_read.Unreadable, AttributeError, TypeError, ValueError):
        return None
    return size if size is not None and 2 <= size <= 100_000 else None


def read_population(
    sweep_dir: Path,
    metric: str = "eval/episode_return",
    skipped: dict[str, str] | None = None,
    quiet: bool = False,
) -> list[Member]:
    """The sweep's PBT members, by name: its own jobs (``multirun.yaml``; without one, the job
    dirs with a lineage), never a stray dir or symlink (named once). A member whose files cannot
    be used is left out with one warning (none with ``quiet``: read a second time), and why goes
    into ``skipped``."""
    warn = log.debug if quiet else log.warning
    sweep_dir = Path(sweep_dir)
    size = population_size_of(sweep_dir)
    if size is not None:
        dirs, strays = scan(sweep_dir, job_names(sweep_dir, size))
    else:  # not known: every real job dir with a lineage
        dirs, strays = scan(sweep_dir, [])
        dirs = {name: sweep_dir / name for name, why in strays.items() if "symlink" not in why}
        strays = {name: why for name, why in strays.items() if "symlink" in why}
    strays = {k: v for k, v in strays.items() if is_member(sweep_dir / k)}
    name_strays(strays, set(strays) if quiet else set())
    members = []
    for name, path in dirs.items():
        if not is_member(path):
            continue
        try:
            member = read_member(path, metric)
        except safe_read.Unreadable as exc:
            warn("[pbt] member %s left out: %s", name, exc)
            if skipped is not None:
                skipped[name] = str(exc)
            continue
        if member.problems:
            warn("[pbt] member %s: %s (left out)", name, "; ".join(member.problems[:3]))
        members.append(member)
    return members


def best_member(members: list[Member]) -> Member | None:
    scored = [m for m in members if m.final is not None]
    return max(scored, key=lambda m: (m.final, m.name)) if scored else None


def ancestry(members: list[Member], best: Member) -> list[str]:
    """Whose weights ``best`` carries, newest first: 'member m steps a-b' spans back to step 0."""
    by_name = {m.name: m for m in members}
    spans, member, end = [], best, best.step
    for _ in range(10_000):  # a lineage is finite; a damaged one must not loop
        exploits = [r for r in member.lineage if r.get("event") == "exploit" and r["step"] <= end]
        if not exploits:
            spans.append(f"member {member.name} steps 0-{end}")
            break
        last = exploits[-1]
        spans.append(
            f"member {member.name} steps {last['step']}-{end} (copied member {last['source']} at "
            f"its step {last['source_step']}, score {last['score']:.4g} < {last['source_score']:.4g})"
        )
        source = by_name.get(str(last["source"]))
        if source is None:
            spans.append(f"member {last['source']} (its files are gone)")
            break
        member, end = source, int(last["source_step"])
    return spans


def pbt_markdown(sweep_dir: Path, metric: str = "eval/episode_return") -> list[str]:
    """The report's PBT section ([] for a sweep without PBT members)."""
    members = read_population(sweep_dir, metric)
    if not members:
        return []
    best = best_member(members)
    lines = ["", "## Population Based Training", ""]
    exploits = sum(1 for m in members for r in m.lineage if r.get("event") == "exploit")
    lines.append(f"{len(members)} members, {exploits} exploits in all (pbt/lineage.jsonl).")
    lines += ["", "| member | final score | step | exploits | current hyperparameters |",
              "|---|---|---|---|---|"]  # fmt: skip
    for m in members:
        n = sum(1 for r in m.lineage if r.get("event") == "exploit")
        final = "-" if m.final is None else f"{m.final:.4g}"
        hps = ", ".join(f"{k}={v:.4g}" for k, v in m.current().items())
        lines.append(f"| {m.name} | {final} | {m.step} | {n} | {hps} |")
    if best is not None:
        lines += ["", f"Best member: **{best.name}** ({metric} {best.final:.4g}). Its weights come "
                  "from (newest first):", ""]  # fmt: skip
        lines += [f"- {span}" for span in ancestry(members, best)]
        lines += ["", "Its hyperparameter schedule (value from that step on):", ""]
        for name, points in best.schedule().items():
            lines.append(f"- {name}: " + ", ".join(f"{s}: {v:.4g}" for s, v in points))
        lines += ["", f"Replay it without a population: `rlexp pbt export {sweep_dir} --member "
                  f"{best.name} -o conf/hooks/pbt_best.yaml`, then `python train.py hooks=pbt_best`."]  # fmt: skip
    return lines + [""]


def plot_schedules(sweep_dir: Path, path: Path, metric: str = "eval/episode_return") -> bool:
    """``pbt_schedules.png``: each tuned hyperparameter over env steps, one line per member, the
    best one bold; False (nothing written) for a sweep without PBT members."""
    members = read_population(sweep_dir, metric, quiet=True)  # pbt_markdown warned
    if not members:
        return False
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    best = best_member(members)
    names = sorted({n for m in members for n in m.schedule()})
    fig, axes = plt.subplots(
        len(names), 1, figsize=(8, 2.6 * len(names)), sharex=True, squeeze=False
    )
    for ax, name in zip(axes[:, 0], names, strict=True):
        for m in members:
            points = m.schedule().get(name)
            if not points:
                continue
            steps = [s for s, _ in points] + [m.step]
            values = [v for _, v in points] + [points[-1][1]]
            bold = best is not None and m.name == best.name
            ax.step(steps, values, where="post", linewidth=2.5 if bold else 1,
                    label=f"member {m.name}" + (" (best)" if bold else ""))  # fmt: skip
        ax.set_ylabel(name)
        ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize="small")
    axes[0, 0].set_title("PBT hyperparameter schedules (pbt/lineage.jsonl)")
    axes[-1, 0].set_xlabel("env steps")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return True


def export_schedule(member: Member, prefix: str = "pbt") -> str:
    """A ``conf/hooks/<name>.yaml`` that replays ``member``'s schedule: one ``piecewise`` hook per
    tuned hyperparameter (values set before each update, by env step). The weights the member
    copied are not part of it: the schedule alone, on one run. ValueError (one line) for a
    schedule ``train.py`` would refuse: a name that is not a mutable hyperparameter of the member's
    algorithm, a value out of its field's range, no point at all."""
    mutable = _mutable_of(member.path)
    schedule = member.schedule()
    where = f"member {member.name}'s {PBT_DIR}/{LINEAGE}"
    if not schedule:
        raise ValueError(f"{where} holds no hyperparameter values: nothing to export")
    for name, points in schedule.items():
        if name not in mutable:
            raise ValueError(f"{where} sets {name!r}, not a mutable hyperparameter (one of "
                             f"{sorted(mutable)}); nothing written")  # fmt: skip
        bad = next((why for _, v in points if (why := out_of_range(name, v))), "")
        if bad or any(not math.isfinite(v) for _, v in points):
            raise ValueError(f"{where}: {bad or name + ' is not finite'}; nothing written")
    lines = [
        f"# The hyperparameter schedule of PBT member {_one_line(member.name)} "
        f"({_one_line(str(member.path))}), exported by",
        "# `rlexp pbt export`: python train.py hooks=<this file's name> (docs/pbt.md). It replays",
        "# the values over env steps on one run; the weights the member copied are not replayed.",
        "# The run's other settings (algorithm.anneal_lr, ...) should be the population's.",
    ]
    for name, points in schedule.items():
        pts = ", ".join(f"[{s}, {_yaml_float(v)}]" for s, v in points)
        lines += [f"{prefix}_{name}:", "  func: piecewise", "  params:", f"    name: {name}",
                  f"    points: [{pts}]"]  # fmt: skip
    return "\n".join(lines) + "\n"


def _one_line(text: str) -> str:
    """``text`` for a YAML comment: a dir name with a line break must not start a YAML line."""
    return "".join(c if c.isprintable() else "?" for c in text)


def _mutable_of(run_dir: Path) -> set[str]:
    """The mutable hyperparameters of the member's algorithm (its ``config.yaml``); every
    algorithm's where that cannot be read."""
    from rlexp.config.rules import MUTABLE_HYPERPARAMETERS

    try:
        name = safe_read.load_yaml(run_dir / "config.yaml")["algorithm"]["name"]
        return set(MUTABLE_HYPERPARAMETERS[name])
    except (safe_read.Unreadable, KeyError, TypeError):
        return {n for names in MUTABLE_HYPERPARAMETERS.values() for n in names}


def _yaml_float(v: float) -> str:
    """``v`` as a float both YAML 1.1 (PyYAML) and OmegaConf read back: 1e-05 -> 1.0e-05."""
    text = repr(float(v))
    if "e" in text and "." not in text.split("e")[0]:
        mantissa, exp = text.split("e")
        text = f"{mantissa}.0e{exp if exp[0] in '+-' else '+' + exp}"
    return text
