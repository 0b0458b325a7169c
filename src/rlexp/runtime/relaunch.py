"""How a run was launched, and the command that resumes exactly that run (``rlexp runs``).

``record_launch`` runs first thing in ``rlexp train`` / ``python train.py``: before anything
rewrites ``sys.argv`` (``--config-json`` and ``--distributed`` are taken out, Hydra's arguments
added), it keeps the working dir, the interpreter, the entry (``train.py``, ``-m rlexp train``, the
``rlexp`` script) and the arguments as typed, in the environment variable RLEXP_LAUNCH, so that the
processes a launcher starts (a joblib sweep's workers) know it too. ``launch_info`` adds how the
ranks were started (torchrun's own command line, or SLURM's task counts) and goes into
``provenance.json`` as ``launch``.

``resume_command`` builds from it ``cd CWD && [LAUNCHER] PYTHON ENTRY [FLAGS] OVERRIDES
hydra.run.dir=DIR``: the run's own Hydra overrides (``.hydra/overrides.yaml``), the run dir quoted
for Hydra's override grammar (``hydra_quote``) and the whole for the shell. Runs from before
``launch`` was recorded get the older ``python train.py ...`` form.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

ENV_VAR = "RLEXP_LAUNCH"
#: Hydra options that take a value (the next argument unless written ``--opt=value``).
_VALUE_OPTIONS = frozenset(
    "--config-dir -cd --config-name -cn --config-path -cp --package -p".split()
)
#: Hydra options that make a run a sweep or only print: never part of a single run's resume.
_DROP_OPTIONS = frozenset(["-m", "--multirun"])
#: Hydra overrides of the original command line that a resume must not repeat: where the run or
#: sweep went, and how a sweep launched its jobs (the resume is one run in one dir).
_DROP_HYDRA = ("hydra.run.", "hydra.sweep.", "hydra.mode", "hydra/launcher", "hydra.launcher.",
               "hydra/sweeper", "hydra.sweeper.", "hydra.output_subdir", "hydra.job.name")  # fmt: skip
_CONFIG_FLAGS = ("--config-json", "--config")
_DISTRIBUTED = "--distributed"
_SAFE_UNQUOTED = re.compile(r"/[A-Za-z0-9_/.+%@-]*")


# -- recording ----------------------------------------------------------------------------------
def record_launch(argv: Sequence[str]) -> None:
    """Keep how this command was typed (``argv``: the arguments after the entry) for the run's
    ``provenance.json`` and for the processes it starts."""
    args = [str(a) for a in argv]
    orig = [str(a) for a in getattr(sys, "orig_argv", sys.argv)]
    tail = len(orig) - len(args)
    if tail < 1 or orig[tail:] != args:  # not called from the command line (a test, a script)
        entry = [str(sys.argv[0])] if sys.argv and sys.argv[0] else []
    else:
        entry = orig[1:tail]
    info = {"cwd": os.getcwd(), "python": sys.executable, "entry": entry, "args": args}
    os.environ[ENV_VAR] = json.dumps(info)


def _parent_argv() -> list[str]:
    try:
        raw = Path(f"/proc/{os.getppid()}/cmdline").read_bytes()
    except OSError:
        return []
    return [a.decode(errors="surrogateescape") for a in raw.rstrip(b"\0").split(b"\0") if raw]


def _ranks() -> dict[str, Any] | None:
    """How this process's ranks were started: torchrun (its own command line, read from the
    parent process), SLURM tasks, or only the counts; None for a single process."""
    env = os.environ
    world = int(env.get("WORLD_SIZE", "1") or 1)
    if world <= 1 and "SLURM_NTASKS" not in env:
        return None
    local = int(env.get("LOCAL_WORLD_SIZE") or env.get("SLURM_NTASKS_PER_NODE", "0") or 0) or world
    out: dict[str, Any] = {"world_size": world, "local_world_size": local,
                           "nnodes": max(1, world // max(local, 1))}  # fmt: skip
    if "TORCHELASTIC_RUN_ID" in env or "LOCAL_WORLD_SIZE" in env:
        out["launcher"] = "torchrun"
        out["launcher_argv"] = _parent_argv()
    elif "SLURM_PROCID" in env:
        out["launcher"] = "slurm"
    return out


def launch_info() -> dict[str, Any] | None:
    """What ``provenance.json`` records as ``launch`` (None: not started through the command line)."""
    try:
        info = json.loads(os.environ.get(ENV_VAR, ""))
    except ValueError:
        return None
    if not isinstance(info, dict):
        return None
    info["ranks"] = _ranks()
    return info


# -- quoting ----------------------------------------------------------------------------------------
def omegaconf_escape(text: str) -> str:
    """``text`` as an OmegaConf string whose value is ``text``: each ``${`` escaped as ``\\${``
    (the backslashes before it doubled, OmegaConf's rule), nothing else changed."""
    return re.sub(r"(\\*)\$\{", lambda m: m.group(1) * 2 + "\\${", text)


def hydra_quote(value: str) -> str:
    """``value`` as a Hydra override value that reads back as exactly ``value``: plain when it is
    a simple absolute path, else single-quoted (quotes and the backslashes before one escaped,
    Hydra's grammar) with ``${`` escaped for OmegaConf."""
    if _SAFE_UNQUOTED.fullmatch(value):
        return value
    from hydra.core.override_parser.types import Quote, QuotedString

    return QuotedString(text=omegaconf_escape(value), quote=Quote.single).with_quotes()


# -- the resume command -----------------------------------------------------------------------------
def _key(override: str) -> str:
    return override.partition("=")[0].lstrip("+~")


def _flags(args: Sequence[str]) -> tuple[list[str], list[str], bool]:
    """(rlexp's and Hydra's options to repeat, the Hydra-namespace overrides to repeat, whether the
    run was ``--distributed``) from the arguments as typed."""
    flags: list[str] = []
    hydra: list[str] = []
    distributed = False
    i = 0
    while i < len(args):
        arg = args[i]
        name = arg.partition("=")[0]
        takes_value = arg in (*_CONFIG_FLAGS, *_VALUE_OPTIONS) and i + 1 < len(args)
        if arg == _DISTRIBUTED:
            distributed = True
        elif name in _CONFIG_FLAGS or arg in _VALUE_OPTIONS or name in _VALUE_OPTIONS:
            flags += args[i : i + 2] if takes_value else [arg]
            i += 1 if takes_value else 0
        elif arg.startswith("-"):
            if arg not in _DROP_OPTIONS:
                flags.append(arg)
        elif _key(arg).startswith(("hydra.", "hydra/")) and not _key(arg).startswith(_DROP_HYDRA):
            hydra.append(arg)
        i += 1
    return flags, hydra, distributed


def _launcher(ranks: dict[str, Any] | None, tail: list[str], python: str) -> list[str]:
    """What starts the ranks again: torchrun's own command line up to the script (``tail``: the
    rank's entry and arguments as torchrun passed them), else one built from the counts."""
    if not ranks:
        return [python]
    argv = [str(a) for a in ranks.get("launcher_argv") or []]
    for i in range(len(argv)):
        if tail and argv[i:] == tail:
            return argv[:i]
    nnodes, local = int(ranks.get("nnodes", 1)), int(ranks.get("local_world_size", 1))
    if ranks.get("launcher") == "slurm":
        return ["srun", f"--nodes={nnodes}", f"--ntasks-per-node={local}", python]
    where = ["--standalone"] if nnodes == 1 else [f"--nnodes={nnodes}"]
    return [python, "-m", "torch.distributed.run", *where, f"--nproc_per_node={local}"]


def _entry(launch: dict[str, Any]) -> list[str]:
    """The entry as typed, less the interpreter's ``-u`` that torchrun adds to each rank."""
    entry = [str(e) for e in launch.get("entry") or []]
    return [e for e in entry if e != "-u"] or ["train.py"]


def resume_command(run_dir: Path, overrides: list[str], provenance: dict[str, Any]) -> str:
    """The shell command that resumes the run in ``run_dir`` from its newest good checkpoint
    (``trainer.resume=auto``): the same working dir, entry, launch of the ranks, options and
    overrides, and ``hydra.run.dir`` quoted for Hydra and the shell."""
    launch = provenance.get("launch")
    if not isinstance(launch, dict) or not isinstance(launch.get("args"), list):
        return legacy_resume_command(run_dir, overrides, provenance.get("argv"))
    args = [str(a) for a in launch["args"]]
    flags, hydra, distributed = _flags(args)
    json_file = any(f.partition("=")[0] in _CONFIG_FLAGS for f in flags)
    keep = [o for o in overrides if _key(o) not in ("trainer.resume", "hydra.run.dir")
            and not (json_file and o == "+experiment=json_experiment")]  # fmt: skip
    changed = any(_key(o) == "trainer.resume" for o in overrides)
    entry = _entry(launch)
    python = str(launch.get("python") or "python")
    ranks = launch.get("ranks") if distributed else None
    if ranks:  # torchrun started each rank as `python -u ENTRY ARGS`
        start = [*_launcher(ranks, [*entry, *args], python), *entry, _DISTRIBUTED]
    else:
        start = [python, *entry, *([_DISTRIBUTED] if distributed else [])]
    tail = ["trainer.resume=auto"] if changed else []
    run = f"hydra.run.dir={hydra_quote(str(run_dir))}"
    command = shlex.join([*start, *flags, *keep, *hydra, *tail, run])
    cwd = launch.get("cwd")
    return f"cd {shlex.quote(str(cwd))} && {command}" if cwd else command


def legacy_resume_command(run_dir: Path, overrides: list[str], argv: Any) -> str:
    """A run from before ``launch`` was recorded: ``python train.py [--config-json F]
    [--distributed] OVERRIDES hydra.run.dir=DIR`` from ``provenance.json``'s argv."""
    args = [str(a) for a in argv[1:]] if isinstance(argv, list) else []
    flags: list[str] = []
    for i, arg in enumerate(args):  # the JSON file and --distributed are not Hydra overrides
        if arg in _CONFIG_FLAGS and i + 1 < len(args):
            flags += [arg, args[i + 1]]
        elif arg.startswith(("--config-json=", "--config=")) or arg == _DISTRIBUTED:
            flags.append(arg)
    keep = []
    for o in overrides:
        if _key(o) in ("trainer.resume", "hydra.run.dir") or (
            flags and o == "+experiment=json_experiment"
        ):
            continue  # json_entry adds +experiment itself
        keep.append(o)
    changed = any(_key(o) == "trainer.resume" for o in overrides)
    tail = ["trainer.resume=auto"] if changed else []
    run = f"hydra.run.dir={hydra_quote(str(run_dir))}"
    return shlex.join(["python", "train.py", *flags, *keep, *tail, run])
