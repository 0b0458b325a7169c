"""Table cells and tables: numbers and durations as ``rlexp runs`` / ``rlexp compare`` show them,
their aligned tables on the terminal, and the cells of ``rlexp report``'s markdown tables.

No numpy here: ``rlexp runs`` imports this module and must start fast.
"""

from __future__ import annotations

import math
import sys


def format_duration(seconds: float) -> str:
    """``45s``, ``3m12s``, ``1h02m``, ``2d03h``."""
    s = int(seconds)
    if s < 60:
        return f"{s}s"
    if s < 3600:
        return f"{s // 60}m{s % 60:02d}s"
    if s < 86400:
        return f"{s // 3600}h{s % 3600 // 60:02d}m"
    return f"{s // 86400}d{s % 86400 // 3600:02d}h"


def format_count(n: int | None) -> str:
    """A step count in three digits with an SI suffix (``1.54k``, ``2M``); ``?`` when missing."""
    if n is None:
        return "?"
    for size, suffix in ((10**9, "G"), (10**6, "M"), (10**3, "k")):
        if abs(n) >= size:
            return f"{n / size:.3g}{suffix}"
    return str(n)


def format_number(x: float | None) -> str:
    """A score for a table cell: ``-`` when missing."""
    if x is None:
        return "-"
    return f"{x:,.0f}" if abs(x) >= 1000 else f"{x:.2f}" if abs(x) >= 1 else f"{x:.3g}"


def print_table(
    headers: list[str],
    rows: list[list[str]],
    right: set[int] = frozenset(),
    title: str | None = None,
) -> None:
    """An aligned table: rich's on a terminal, plain text (pipes, files, tests) otherwise."""
    if sys.stdout.isatty():
        from rich import box
        from rich.console import Console
        from rich.table import Table

        table = Table(title=title, box=box.SIMPLE_HEAD, title_justify="left")
        for i, h in enumerate(headers):
            table.add_column(h, justify="right" if i in right else "left", overflow="fold")
        for row in rows:
            table.add_row(*row)
        Console().print(table)
        return
    widths = [max([len(h)] + [len(r[i]) for r in rows]) for i, h in enumerate(headers)]
    if title:
        print(title)
    for row in [headers, *rows]:
        cells = [
            c.rjust(w) if i in right else c.ljust(w)
            for i, (c, w) in enumerate(zip(row, widths, strict=True))
        ]
        print("  ".join(cells).rstrip())


def fixed(x: float | None, digits: int = 2) -> str:
    """A number in a markdown cell with ``digits`` decimals; ``n/a`` when missing or NaN."""
    return "n/a" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.{digits}f}"


def markdown_cell(text: object) -> str:
    """Text for one markdown table cell (a reason may hold ``|`` or a newline)."""
    return " ".join(str(text).split()).replace("|", "\\|")
