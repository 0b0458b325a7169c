"""``rlexp`` command: ``rlexp train [overrides]``, ``rlexp eval CHECKPOINT [--episodes N]``,
``rlexp export CHECKPOINT --format torchscript|onnx``, ``rlexp report SWEEP_DIR``,
``rlexp runs [DIR ...]``, ``rlexp compare DIR ...``, ``rlexp --version`` (also ``python -m rlexp``).

Bad input (an option out of range, a missing or unreadable checkpoint) is one line on stderr and
exit 2; a checkpoint whose policy weights are NaN/Inf exits 3, like a run the NaN guard stopped.
"""

from __future__ import annotations

import argparse
import logging
import os
import re
import sys
from pathlib import Path
from typing import Any, NoReturn

# rlexp eval's work (re-exported: ``from rlexp.cli import evaluate``); a light import, torch-free
from rlexp.analysis.report_cli import threshold_arg
from rlexp.deploy.policy_eval import evaluate

log = logging.getLogger("rlexp")


class _DefaultsHelp(argparse.HelpFormatter):
    """Every option's help ends with its default, unless the help already says it or there is
    none to say (``None``, a switch that is off)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        default = action.default
        if (
            not action.option_strings
            or "default" in text
            or default in (None, False, argparse.SUPPRESS)
            or default == []
            or isinstance(action, argparse._VersionAction)
        ):
            return text
        return f"{text} (default: %(default)s)"


class _Parser(argparse.ArgumentParser):
    """argparse, but a usage error is one line (what is wrong, where the help is), exit 2; option
    help shows the defaults (subcommands' parsers are built by this class too)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs.setdefault("formatter_class", _DefaultsHelp)
        super().__init__(*args, **kwargs)

    def error(self, message: str) -> NoReturn:
        print(f"{self.prog}: {message} (see {self.prog} --help)", file=sys.stderr)
        sys.exit(2)


def _at_least_1(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def _one_line(exc: BaseException) -> str:
    """The first line of an error's message, without terminal colour codes (torch adds some)."""
    text = re.sub(r"\x1b\[[0-9;]*m", "", str(exc)).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def _load_plugins_or_exit(prog: str) -> None:
    """The installed ``rlexp.plugins`` (native tasks, terms, events); a broken one is one line."""
    from rlexp.plugins import PluginError, load_plugins

    try:
        load_plugins()
    except PluginError as exc:
        print(f"{prog}: {exc}", file=sys.stderr)
        sys.exit(2)


def train(argv: list[str], prog: str = "rlexp train") -> None:
    """``rlexp train`` / ``python train.py``, under the entry guard: a deleted working directory,
    Ctrl-C before a run trains, an unwritable path are one line, not a traceback (docs/faults.md)."""
    from rlexp.runtime.entry import entry_guard

    with entry_guard(prog):
        _train(argv, prog)


def _train(argv: list[str], prog: str) -> None:
    """Plugins first (a JSON file may name a plugin's task), then ``--config-json`` /
    ``--distributed`` and Hydra (``rlexp.launch.json_entry``)."""
    from rlexp.common import speedups as _speedups
    from rlexp.runtime.relaunch import record_launch

    record_launch(argv)  # as typed, for the resume command of `rlexp runs`
    with _speedups.startup_gc():  # the GC is back on once the run is built (RunLifecycle.run)
        _load_plugins_or_exit(prog)
        from rlexp.launch.json_entry import main as train_main

        train_main(argv)


def _add_runs_parsers(sub: Any) -> None:
    """``rlexp runs`` and ``rlexp compare`` (docs/runs.md)."""
    runs = sub.add_parser(
        "runs",
        help="list run dirs: status (killed runs show as died), task, steps, evals, provenance",
    )
    runs.add_argument("dirs", nargs="*", help="dirs to search (default: outputs/ and multirun/)")
    runs.add_argument("--metric", default="eval/episode_return", help="the last/best eval metric")
    runs.add_argument(
        "--sort",
        default="start,dir",
        metavar="KEY[,KEY]",
        help="a column (dir status task algo steps total progress last best wall start host git) "
        "or a config key; -KEY sorts descending, e.g. --sort -best",
    )
    runs.add_argument(
        "--where",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="only runs whose config key (or column) has this value (glob ok; KEY!=VALUE too); "
        "repeatable, e.g. --where env.name=hopper",
    )
    runs.add_argument(
        "--status",
        action="append",
        default=[],
        help="only runs with this status (repeatable or comma-separated), e.g. --status died",
    )
    runs.add_argument("--json", action="store_true", help="one JSON list, for scripts")
    cmp = sub.add_parser(
        "compare",
        help="compare runs or sweeps: config differences, git, final/best eval, IQM difference "
        "and probability of improvement between configurations, curves",
    )
    cmp.add_argument(
        "dirs",
        nargs="+",
        metavar="RUN_OR_SWEEP_DIR",
        help="run dirs and sweep dirs (multirun/<date>/<time>: each job is a run), two or more "
        "runs in all; a glob your shell expands works, e.g. outputs/2026-11-2*/*",
    )
    cmp.add_argument("--metric", default="eval/episode_return", help="score and curve metric")
    cmp.add_argument(
        "--threshold",
        type=threshold_arg,
        default=None,
        metavar="[METRIC=]VALUE",
        help="also the steps each run took to first reach VALUE in --metric (or METRIC)",
    )
    cmp.add_argument(
        "--group-by",
        action="append",
        default=[],
        metavar="KEY",
        help="group runs by this config key (repeatable; default: by dir given and config less "
        "the seed)",
    )
    cmp.add_argument("--plot", default=None, metavar="OUT.png", help="write the curves here")
    cmp.add_argument("--json", action="store_true", help="one JSON object, for scripts")


def _sort_values_joined(argv: list[str]) -> list[str]:
    """``--sort -best`` as ``--sort=-best``: argparse takes a value starting with ``-`` for an
    option."""
    out: list[str] = []
    for arg in argv:
        if out and out[-1] == "--sort" and argv[:1] == ["runs"]:
            out[-1] = f"--sort={arg}"
        else:
            out.append(arg)
    return out


def _runs_commands(args: argparse.Namespace) -> None:
    """Run ``rlexp runs`` / ``rlexp compare``; bad input is one line on stderr, exit 2."""
    from rlexp.analysis.runs import RunsError

    try:
        if args.command == "runs":
            from rlexp.analysis.runs import main as runs_main

            runs_main(args.dirs, args.metric, args.sort, args.where, args.status, args.json)
            return
        from rlexp.extras import MissingExtra, require

        try:
            require("report", "rlexp compare", None if args.plot else ("scipy",))
        except MissingExtra as exc:
            raise RunsError(str(exc)) from None
        from rlexp.analysis.compare import main as compare_main

        threshold_metric, threshold = args.threshold or (None, None)
        compare_main(
            args.dirs,
            args.metric,
            threshold=threshold,
            threshold_metric=threshold_metric,
            group_by=args.group_by,
            plot=args.plot,
            as_json=args.json,
        )
    except RunsError as exc:
        print(f"rlexp {args.command}: {_one_line(exc)}", file=sys.stderr)
        sys.exit(2)
    except BrokenPipeError:  # `rlexp runs | head`: the reader left; say nothing more
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())


def _version() -> str:
    from rlexp import __version__

    return f"rlexp {__version__}"


def main(argv: list[str] | None = None) -> None:
    """``rlexp COMMAND ...`` under the entry guard (``rlexp.runtime.entry``)."""
    from rlexp.runtime.entry import entry_guard

    argv = list(sys.argv[1:] if argv is None else argv)
    command = argv[0] if argv and not argv[0].startswith("-") else ""
    with entry_guard(f"rlexp {command}".strip()):
        _main(argv)


def _main(argv: list[str]) -> None:
    if argv and argv[0] == "train":  # exactly `python train.py ...` (--config-json, --distributed)
        train(argv[1:])
        return
    parser = _Parser(
        prog="rlexp",
        description="rlexp: PPO experiments on MuJoCo with Hydra configs",
        epilog="rlexp train --help lists the config groups and their options.",
    )
    parser.add_argument("--version", action="version", version=_version())
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser(
        "train",
        help="train (same as python train.py): [--config-json FILE] [--distributed] [-m] "
        "[group=option ...] [key=value ...]",
        add_help=False,
    )
    ev = sub.add_parser(
        "eval",
        help="evaluate a checkpoint or an exported policy: mean return over N deterministic "
        "episodes [and an mp4 of them]",
    )
    ev.add_argument(
        "path",
        metavar="RUN_DIR_OR_FILE",
        help="a run dir (the checkpoint --checkpoint picks), a checkpoint file, or a file written "
        "by rlexp export (its metadata JSON beside it)",
    )
    _add_checkpoint_option(ev)
    ev.add_argument(
        "--episodes",
        type=_at_least_1,
        default=None,
        help="episodes to run (>= 1; default: the run's trainer.eval_episodes, as its eval rounds)",
    )
    ev.add_argument(
        "--num-envs", type=_at_least_1, default=None, help="eval envs (default: the run's)"
    )
    ev.add_argument(
        "--seed",
        type=int,
        default=None,
        help="eval env seed (default: the run's own eval seed, seed + 1000000, as its eval rounds)",
    )
    ev.add_argument(
        "--video",
        nargs="?",
        const="",
        default=None,
        metavar="PATH.mp4",
        help="also write an mp4 of eval env 0's episodes (default: beside the file, <name>.mp4)",
    )
    _add_export_parser(sub)
    pbt = sub.add_parser("pbt", help="Population Based Training: export a member's schedule")
    pbt.add_argument("action", choices=["export"], help="export: a hooks config (docs/pbt.md)")
    pbt.add_argument("sweep_dir", help="the PBT sweep's dir (multirun/<date>/<time>)")
    pbt.add_argument("--member", default=None, help="the member (job dir name); default: the best")
    pbt.add_argument("-o", "--output", type=Path, default=None, help="write here (default: print)")
    from rlexp.analysis.report_cli import add_report_parser

    add_report_parser(sub)
    _add_runs_parsers(sub)
    args = parser.parse_args(_sort_values_joined(argv))
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    log.setLevel(logging.INFO)  # rlexp's own progress; other libraries' INFO lines stay quiet
    if args.command in ("runs", "compare"):
        _runs_commands(args)
        return
    if args.command == "report":
        from rlexp.analysis.report_cli import report_command

        report_command(args)
        return
    if args.command == "pbt":
        _pbt_export(args)
        return
    if args.command in ("eval", "export"):
        from rlexp.common import speedups as _speedups

        # The cyclic GC off, as train's start-up has it: the imports alone (torch, tensordict,
        # TorchRL, through the plugins too) trigger dozens of full collections; a short command
        # never needs one.
        with _speedups.startup_gc():
            _eval_or_export(args)


def _eval_or_export(args: argparse.Namespace) -> None:
    """``rlexp eval`` / ``rlexp export``: the result printed, or one line and exit 2 (3: NaN)."""
    _check_gl()
    _load_plugins_or_exit(f"rlexp {args.command}")  # the checkpoint's task may be a plugin's
    from rlexp.runtime.user_code import UserCodeExit, user_code_exits

    try:
        with user_code_exits(f"rlexp {args.command}"):  # sys.exit() in the env: exit 1, one line
            print(_eval(args) if args.command == "eval" else _export(args))
    # (FloatingPointError: NonFiniteError, NaN/Inf weights; not imported: slow)
    except (FileNotFoundError, ValueError, UserCodeExit, FloatingPointError) as exc:
        print(f"rlexp {args.command}: {_one_line(exc)}", file=sys.stderr)
        sys.exit(
            1 if isinstance(exc, UserCodeExit) else 3 if isinstance(exc, FloatingPointError) else 2
        )


def _check_gl() -> None:
    """A ``MUJOCO_GL`` that makes ``import mujoco`` fail (an unknown value, egl or osmesa without
    its library): one line naming it now, not PyOpenGL's traceback when the env is built."""
    from rlexp.envs.native.render import GL_FIX, gl_problem
    from rlexp.runtime.entry import EntryError

    problem = gl_problem(rendering=False)
    if problem is not None:
        raise EntryError(f"{problem}; {GL_FIX}")


def _pbt_export(args: argparse.Namespace) -> None:
    """``rlexp pbt export``: a member's schedule as a hooks config; one line and exit 2 if none, or
    if its files cannot give one ``train.py`` accepts (nothing written)."""
    from rlexp.pbt.lineage import best_member, export_schedule, read_population

    sweep = Path(args.sweep_dir)
    skipped: dict[str, str] = {}
    members = read_population(sweep, skipped=skipped) if sweep.is_dir() else []
    if args.member is not None and args.member in skipped:
        print(f"rlexp pbt export: member {args.member} in {sweep} cannot be exported: "
              f"{skipped[args.member]}", file=sys.stderr)  # fmt: skip
        sys.exit(2)
    chosen = (
        best_member(members)
        if args.member is None
        else next((m for m in members if m.name == args.member), None)
    )
    if chosen is None:
        names = ", ".join(m.name for m in members) or "none"
        print(f"rlexp pbt export: no member {args.member or '(best)'} in {sweep} (members with "
              f"pbt/lineage.jsonl: {names})", file=sys.stderr)  # fmt: skip
        sys.exit(2)
    try:
        text = export_schedule(chosen)
    except ValueError as exc:
        print(f"rlexp pbt export: {exc}", file=sys.stderr)
        sys.exit(2)
    if args.output is None:
        print(text, end="")
        return
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(text)
    log.info("wrote member %s's schedule to %s (python train.py hooks=%s)", chosen.name,
             args.output, args.output.stem)  # fmt: skip


def _add_export_parser(sub: Any) -> None:
    """``rlexp export`` (docs/export.md)."""
    exp = sub.add_parser(
        "export",
        help="a checkpoint's deterministic policy (normaliser folded in) as one TorchScript or "
        "ONNX file, with a metadata JSON beside it",
    )
    exp.add_argument(
        "path",
        metavar="RUN_DIR_OR_CHECKPOINT",
        help="a run dir (the checkpoint --checkpoint picks) or a checkpoint file",
    )
    exp.add_argument(
        "--format",
        choices=["torchscript", "onnx"],
        default="torchscript",
        help="torchscript (.pt, plain torch) or onnx (.onnx, onnxruntime; the 'export' extra)",
    )
    exp.add_argument(
        "--out",
        default=None,
        metavar="PATH",
        help="the file to write (default: <run_dir>/exported/<checkpoint name>.pt or .onnx)",
    )
    _add_checkpoint_option(exp)


def _add_checkpoint_option(parser: argparse.ArgumentParser) -> None:
    """``--checkpoint`` of eval and export: one rule (``rlexp.checkpoints.files.select_checkpoint``)."""
    parser.add_argument(
        "--checkpoint",
        default=None,
        metavar="best|last|PATH",
        help="which checkpoint of a run dir: last (the newest that loads: the run's final policy), "
        "best (best.pt, its best evaluation) or a checkpoint file's path (default: last)",
    )


def _eval(args: argparse.Namespace) -> str:
    """``rlexp eval``: its result line (and the video's)."""
    res = evaluate(args.path, args.episodes, args.num_envs, args.seed, args.video, args.checkpoint)
    step = res["global_step"]
    what = f"checkpoint {res['path']} (step {step}; {res['chosen']})"
    if res["kind"] != "checkpoint":
        what = f"exported policy {res['path']} ({res['kind']} of {res['checkpoint']}, step {step})"
    line = (
        f"{what}: mean return {res['mean_return']:.3f} +- "
        f"{res['std_return']:.3f} over {res['episodes']} episodes"
    )
    return line + (f"\nvideo: {res['video']}" if res["video"] else "")


def _export(args: argparse.Namespace) -> str:
    """``rlexp export``: what was written, from which checkpoint and why that one."""
    from rlexp.deploy.export import export_policy

    res = export_policy(args.path, args.format, args.out, args.checkpoint)
    return (
        f"exported {res.checkpoint} (step {res.global_step}; {res.chosen}) as {args.format}: "
        f"{res.path}\nmetadata: {res.metadata}"
        + (f"\nobservation helper (numpy only; docs/export.md): {res.helper}" if res.helper else "")
        + (f"\nrecurrent state (docs/export.md): {res.state}" if res.state else "")
    )


if __name__ == "__main__":
    main()
