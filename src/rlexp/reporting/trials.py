"""The trials table of an Optuna sweep's study (``<sweep dir>/optuna.db``) in ``report.md``."""

from __future__ import annotations

from pathlib import Path

from rlexp.reporting.jobs import first_line
from rlexp.table import fixed, markdown_cell

#: The study of an Optuna sweep (``rlexp.launch.optuna_sweeper.STUDY_FILE``): its trials are listed.
OPTUNA_STUDY = "optuna.db"


def optuna_markdown(sweep_dir: Path) -> list[str]:
    """The trials of an Optuna sweep's study (``<sweep dir>/optuna.db``, rlexp's resumable
    sweeper): number, job dir, state, value and parameters; [] when the sweep dir has no study."""
    if not (sweep_dir / OPTUNA_STUDY).is_file():
        return []
    try:
        from rlexp.launch.optuna_sweeper import read_trials
    except ImportError as exc:  # no rlexp[optuna] where the report runs
        return ["", "## Optuna trials", "", f"`{OPTUNA_STUDY}` not read: {first_line(exc)}."]
    trials = read_trials(sweep_dir)
    if isinstance(trials, str):
        return ["", "## Optuna trials", "", f"`{OPTUNA_STUDY}` not read: {trials}."]
    lines: list[str] = []
    for name in dict.fromkeys(t["study"] for t in trials):
        mine = [t for t in trials if t["study"] == name]
        params = list(dict.fromkeys(k for t in mine for k in t["params"]))
        n_done = sum(t["state"] == "COMPLETE" for t in mine)
        lines += [
            "",
            f"## Optuna trials (study `{name}`: {len(mine)} trials, {n_done} complete)",
            "",
            f"From `{OPTUNA_STUDY}`, in trial order. Job: the trial's dir; a failed trial is retried "
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
