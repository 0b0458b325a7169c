"""The trials table of an Optuna sweep's study (``<sweep dir>/optuna.journal``, or ``optuna.db``
from before rlexp used the journal) in ``report.md``."""

from __future__ import annotations

from pathlib import Path

from rlexp.analysis.reporting.jobs import first_line
from rlexp.common.table import fixed, markdown_cell

#: The study files of an Optuna sweep (``rlexp.launch.optuna_study.STUDY_FILES``): their trials
#: are listed; the first one found is read.
OPTUNA_STUDY = ("optuna.journal", "optuna.db")


def optuna_markdown(sweep_dir: Path) -> list[str]:
    """The trials of an Optuna sweep's study (rlexp's resumable sweeper): number, job dir, state,
    value and parameters; [] when the sweep dir has no study."""
    found = next((name for name in OPTUNA_STUDY if (sweep_dir / name).is_file()), None)
    if found is None:
        return []
    try:
        from rlexp.launch.optuna_study import read_trials
    except ImportError as exc:  # no rlexp[optuna] where the report runs
        return ["", "## Optuna trials", "", f"`{found}` not read: {first_line(exc)}."]
    trials = read_trials(sweep_dir)
    if isinstance(trials, str):
        return ["", "## Optuna trials", "", f"`{found}` not read: {trials}."]
    lines: list[str] = []
    for name in dict.fromkeys(t["study"] for t in trials):
        mine = [t for t in trials if t["study"] == name]
        params = list(dict.fromkeys(k for t in mine for k in t["params"]))
        n_done = sum(t["state"] == "COMPLETE" for t in mine)
        lines += [
            "",
            f"## Optuna trials (study `{name}`: {len(mine)} trials, {n_done} complete)",
            "",
            f"From `{found}`, in trial order. Job: the trial's dir; a failed trial is retried "
            "with its parameters in its own dir (`retry of`: the trial it repeats).",
            "",
            "| trial | job | state | value | "
            + " | ".join(f"`{p}`" for p in params)
            + " | retry of |",
            "|---|---|---|---|" + "---|" * len(params) + "---|",
        ]
        for t in mine:
            value = ", ".join(fixed(v) for v in t["values"]) if t["values"] else "n/a"
            cells = [
                str(t["number"]),
                f"`{t['job']}`" if t["job"] is not None else "n/a",
                t["state"],
                value,
                *(
                    f"{t['params'][p]:.6g}"
                    if isinstance(t["params"].get(p), float)
                    else markdown_cell(t["params"].get(p, ""))
                    for p in params
                ),
                str(t["retry_of"]) if t["retry_of"] is not None else "",
            ]
            lines.append("| " + " | ".join(cells) + " |")
    return lines
