"""``rlexp report``: its arguments and what it does (the ``rlexp`` command's ``cli.py`` adds the
subcommand and calls :func:`report_command`)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any


def threshold_arg(text: str) -> tuple[str | None, float]:
    """``rlexp report --threshold``: VALUE or METRIC=VALUE (rlexp.analysis.report.parse_threshold)."""
    from rlexp.analysis.report import parse_threshold

    try:
        return parse_threshold(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def add_report_parser(sub: Any) -> None:
    """The ``report`` subcommand and its options on ``sub`` (argparse subparsers)."""
    rep = sub.add_parser(
        "report", help="a sweep's per-configuration statistics: report.md, report.csv, curves.png"
    )
    rep.add_argument("sweep_dir", help="a multirun dir, e.g. multirun/2026-11-22/10-00-00")
    rep.add_argument("--metric", default="eval/episode_return", help="score and curve metric")
    rep.add_argument("--no-plot", action="store_true", help="skip curves.png")
    rep.add_argument(
        "--threshold",
        type=threshold_arg,
        default=None,
        metavar="[METRIC=]VALUE",
        help="also the steps each seed took to reach VALUE (first time, and 3 logged values in "
        "a row) in --metric, or in METRIC: e.g. 475, or eval/success_rate=0.9",
    )
    rep.add_argument(
        "--results",
        action="store_true",
        default=None,
        help="the results per env (train/eval return next to published anchors, wall time, "
        "env steps/s; results.csv, results.png) for a sweep of one env too (automatic over several)",
    )
    rep.add_argument(
        "--results-plot",
        type=Path,
        default=None,
        metavar="PNG",
        help="also write the results figure here, e.g. docs/results_1m.png (implies --results)",
    )
    rep.add_argument(
        "--write-preset",
        type=Path,
        default=None,
        metavar="YAML",
        help="an Optuna sweep confirmed on fresh seeds (hydra.sweeper.confirm): write its winner "
        "as a preset, e.g. conf/tuned/my_hopper.yaml (then: train.py env=hopper tuned=my_hopper)",
    )
    rep.add_argument("--force", action="store_true", help="--write-preset over an existing file")


def report_command(args: argparse.Namespace) -> None:
    """``rlexp report``: the report on stdout and in the sweep dir; one line and exit 2 on a
    missing dir, a missing extra or a refused ``--write-preset``."""
    from rlexp.analysis.report import report
    from rlexp.extras import MissingExtra, require

    try:
        plots = not args.no_plot or args.results_plot is not None
        require("report", "rlexp report", None if plots else ("scipy",))
        threshold_metric, threshold = args.threshold or (None, None)
        md = report(
            Path(args.sweep_dir),
            args.metric,
            plot=not args.no_plot,
            threshold=threshold,
            threshold_metric=threshold_metric,
            results=args.results,
            results_plot=args.results_plot,
        )
        print(md, end="")
        if args.write_preset is not None:
            from rlexp.analysis.reporting.confirm import write_preset

            written = write_preset(Path(args.sweep_dir), args.write_preset, args.force)
            print(f"rlexp report: wrote the confirmed winner's preset {written}")
    except (FileNotFoundError, MissingExtra, ValueError) as exc:
        print(f"rlexp report: {exc}", file=sys.stderr)
        sys.exit(2)
