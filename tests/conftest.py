"""Shared test fixtures: Hydra composition of the real conf/, the repository's paths, and the
processes a test starts (ended on teardown, pass or fail)."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("WANDB_MODE", "offline")

REPO = Path(__file__).resolve().parents[1]
CONF_DIR = REPO / "conf"
SHARED = REPO.parent / "shared"
sys.path.insert(0, str(REPO / "src"))


def compose(overrides: list[str] | None = None):
    """Compose conf/config.yaml with ``overrides`` exactly as ``python train.py`` would."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from rlexp.config.schema import register_configs

    register_configs()
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return hydra_compose(config_name="config", overrides=list(overrides or []))


def train_here(overrides: list[str], run_dir: Path) -> dict:
    """Compose ``overrides`` and train in this process (``rlexp.app.train``: no Hydra run, no
    subprocess); torch's thread count, which a run sets from ``trainer.torch_threads``, is put
    back however the run ends. Returns the run's final metrics."""
    import torch

    from rlexp.app import train
    from rlexp.config.validate import to_root_config

    config = to_root_config(compose(overrides))
    before = torch.get_num_threads()
    try:
        return train(config, run_dir)
    finally:
        torch.set_num_threads(before)


def run_train(
    args: list[str],
    cwd: Path,
    timeout: float = 300,
    check: bool = True,
    env_extra: dict[str, str | None] | None = None,
    **kw,
) -> subprocess.CompletedProcess:
    """``python train.py ARGS`` in a subprocess, in ``cwd`` (``env_extra``: None removes a variable)."""
    env = {**os.environ, "PYTHONPATH": str(REPO / "src")}
    for key, value in (env_extra or {}).items():
        if value is None:
            env.pop(key, None)
        else:
            env[key] = value
    proc = subprocess.run(
        [sys.executable, str(REPO / "train.py"), *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=timeout,
        env=env,
        **kw,
    )
    if check and proc.returncode != 0:
        raise AssertionError(
            f"train.py {args} exited {proc.returncode}\nSTDOUT:\n{proc.stdout}\nSTDERR:\n{proc.stderr}"
        )
    return proc


def rlexp_cli(*args) -> tuple[int, str, str]:
    """``rlexp ARGS`` in this process (the imports paid once; a traceback fails the test):
    (exit code, stdout, stderr)."""
    import io

    from rlexp import cli

    out, err = io.StringIO(), io.StringIO()
    code = 0
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            cli.main([str(a) for a in args])
        except SystemExit as exc:
            code = int(exc.code or 0)
    return code, out.getvalue(), err.getvalue()


#: What rlexp stops on (rlexp.runtime.signals.STOP_SIGNALS).
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


def _default_stop_signals() -> None:
    """In the child, before exec: the stop signals as a terminal delivers them. An ignored signal
    survives exec, and a test runner started by a shell's ``&`` ignores SIGINT, under ``nohup``
    SIGHUP; rlexp rightly keeps an ignored signal ignored, so a test that sends one must not
    depend on what the runner inherited."""
    for sig in STOP_SIGNALS:
        signal.signal(sig, signal.SIG_DFL)


class Children:
    """The processes a test starts: each leads a process group of its own (its own children
    included: eval workers, sweep jobs) and starts with the default stop-signal dispositions."""

    def __init__(self) -> None:
        self.started: list[subprocess.Popen] = []

    def popen(self, args: list[str], **kw) -> subprocess.Popen:
        """``subprocess.Popen(args, **kw)``, recorded, so that teardown kills its group."""
        proc = subprocess.Popen(
            args, start_new_session=True, preexec_fn=_default_stop_signals, **kw
        )
        self.started.append(proc)
        return proc

    def train(
        self, args: list[str], cwd: Path, console: Path, env_extra: dict[str, str] | None = None
    ) -> subprocess.Popen:
        """``python train.py ARGS`` in the background, stdout and stderr to the file ``console``
        (a file, not a pipe: a full pipe would block the child)."""
        env = {**os.environ, "PYTHONPATH": str(REPO / "src"), **(env_extra or {})}
        with open(console, "w") as out:
            return self.popen(
                [sys.executable, str(REPO / "train.py"), *args],
                cwd=cwd, env=env, stdout=out, stderr=subprocess.STDOUT,
            )  # fmt: skip

    def kill_all(self) -> None:
        """SIGKILL every recorded process group (a no-op for groups already gone) and reap."""
        for proc in self.started:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(proc.pid, signal.SIGKILL)
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.wait(timeout=30)

    def __enter__(self) -> Children:
        """``with Children() as children:`` in a helper or a module fixture that waits for what
        it starts: the groups are killed when the block ends, however it ends."""
        return self

    def __exit__(self, *exc) -> None:
        self.kill_all()


@pytest.fixture
def children() -> Iterator[Children]:
    """Start background processes through this; teardown kills their process groups, pass or
    fail (a failed test once left a 100M-frame train.py running for half an hour)."""
    with Children() as started:
        yield started


def _live_descendants(root: int) -> dict[int, list[str]]:
    """The processes below ``root`` that still run (zombies excluded): PID -> argv. Linux only."""
    parents: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            state, ppid = stat.read_text().rsplit(")", 1)[1].split()[:2]
        except (OSError, ValueError):  # gone meanwhile
            continue
        if state != "Z":
            parents.setdefault(int(ppid), []).append(int(stat.parent.name))
    found: dict[int, list[str]] = {}
    todo = list(parents.get(root, []))
    while todo:
        pid = todo.pop()
        try:
            argv = Path(f"/proc/{pid}/cmdline").read_bytes().rstrip(b"\0").split(b"\0")
        except OSError:
            continue
        found[pid] = [arg.decode(errors="replace") for arg in argv]
        todo += parents.get(pid, [])
    return found


def _leftover_train_runs() -> dict[int, list[str]]:
    """``train.py`` processes below this one (a sweep's, a torchrun's, a test's own) still running."""
    return {
        pid: argv
        for pid, argv in _live_descendants(os.getpid()).items()
        if any(Path(arg).name == "train.py" for arg in argv)
    }


@pytest.fixture(scope="session", autouse=True)
def no_train_run_outlives_the_session() -> Iterator[None]:
    """At the end of the session, a ``train.py`` started by this pytest and still running is an
    error (a test that does not end what it starts: use ``children``); it is killed, its group too
    where it leads one. Orphans (their parent gone) are no longer below this process: not seen."""
    yield
    if not Path("/proc/self/stat").exists():
        return
    left = _leftover_train_runs()
    if not left:
        return
    own_group = os.getpgrp()
    for pid in left:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            if os.getpgid(pid) == pid != own_group:
                os.killpg(pid, signal.SIGKILL)
            else:
                os.kill(pid, signal.SIGKILL)
    lines = "\n".join(f"  PID {pid}: {' '.join(argv)[:400]}" for pid, argv in sorted(left.items()))
    pytest.fail(
        f"{len(left)} train.py process(es) started by this test session still ran at its end "
        f"(killed now; start background processes through the `children` fixture):\n{lines}",
        pytrace=False,
    )


def train_side_by_side(
    runs: dict[str, list[str]], dirs: dict[str, Path], root: Path, env_extra: dict[str, str]
) -> None:
    """``python train.py`` for each of ``runs`` (its overrides) at once, into ``dirs[name]``,
    logs in ``root``; each must exit 0 (its log otherwise); every process ended on return."""
    with Children() as children:
        procs = {
            name: children.train(
                [*args, f"hydra.run.dir={dirs[name]}"], root, root / f"{name}.log", env_extra
            )
            for name, args in runs.items()
        }
        for name, proc in procs.items():
            assert proc.wait(timeout=300) == 0, (root / f"{name}.log").read_text()


def only_run_dir(root: Path) -> Path:
    """The single run dir Hydra created under ``root/outputs``."""
    dirs = [p.parent for p in root.glob("outputs/*/*/config.yaml")]
    assert len(dirs) == 1, f"expected one run dir under {root}/outputs, found {dirs}"
    return dirs[0]


#: Overrides that make a full training run take a few seconds.
TINY = [
    "env=inverted_pendulum",
    "trainer.total_frames=512",
    "trainer.frames_per_batch=256",
    "trainer.eval_every=256",
    "trainer.eval_episodes=2",
    "trainer.save_every=256",
    "algorithm.num_epochs=2",
]


#: A sweep job: TINY with one PPO epoch, 512 env steps in about a second.
SWEEP_TINY = [
    "env=inverted_pendulum",
    "trainer.total_frames=512",
    "trainer.frames_per_batch=256",
    "algorithm.num_epochs=1",
    "trainer.eval_every=256",
    "trainer.eval_episodes=2",
    "trainer.save_every=256",
]


#: Two iterations, a checkpoint after each, no evaluation: for tests about what a run dir holds.
SHORT = [
    "env=inverted_pendulum",
    "trainer.total_frames=512",
    "trainer.frames_per_batch=256",
    "trainer.save_every=256",
    "trainer.eval_every=0",
    "algorithm.num_epochs=1",
]


@pytest.fixture
def one_torch_thread() -> Iterator[None]:
    """Tiny tensors: one torch thread (OpenMP threads waiting on a loaded machine cost 100x the
    work); the previous count restored after the test."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture
def tiny_overrides() -> list[str]:
    return list(TINY)


def _compile_problem() -> str | None:
    import torch

    from rlexp.algorithms.ppo import compile_unavailable

    return compile_unavailable(torch.device("cpu"))


#: For tests that really run torch.compile: inductor needs a C++ compiler for CPU code.
needs_compiler = pytest.mark.skipif(
    _compile_problem() is not None, reason=f"torch.compile cannot run here: {_compile_problem()}"
)


#: PPO without the MuJoCo references' extras that rlexp turns on by default (reward scaling and
#: clipping, LR annealing): the plain update the hand-written references in the tests implement.
PLAIN_PPO = {"anneal_lr": False, "normalize_rewards": False, "clip_rewards": None}


def clipped_adam_step(params, grads, m, v, step: int, cfg, betas=(0.9, 0.999)) -> None:
    """A hand-written reference optimiser step: clip the gradients to ``cfg.max_grad_norm`` as
    ``clip_grad_norm_`` does, then Adam (bias-corrected, ``cfg.lr``, ``cfg.adam_eps``) in place;
    ``m`` / ``v``: the moment tensors, ``step``: 1 for the first step."""
    import torch

    beta1, beta2 = betas
    norm = torch.sqrt(sum(g.pow(2).sum() for g in grads))
    coef = min(1.0, cfg.max_grad_norm / (float(norm) + 1e-6))
    with torch.no_grad():
        for p, g, mi, vi in zip(params, grads, m, v, strict=True):
            g = g * coef
            mi.mul_(beta1).add_((1 - beta1) * g)
            vi.mul_(beta2).add_((1 - beta2) * g * g)
            m_hat = mi / (1 - beta1**step)
            v_hat = vi / (1 - beta2**step)
            p.sub_(cfg.lr * m_hat / (v_hat.sqrt() + cfg.adam_eps))


def journal_order(sweep: Path) -> tuple[dict[int, int], dict[int, int]]:
    """({trial id: index of its creation}, {trial id: index of its finishing state}) among the
    operations of the sweep's journal file, in the order they were written."""
    from optuna.storages.journal._storage import JournalOperation
    from optuna.trial import TrialState

    created: dict[int, int] = {}
    finished: dict[int, int] = {}
    lines = [line for line in (sweep / "optuna.journal").read_text().splitlines() if line.strip()]
    if lines and not lines[-1].endswith("}"):  # a sweep SIGKILLed mid-write: Optuna skips it too
        lines.pop()
    for i, op in enumerate(map(json.loads, lines)):
        if op["op_code"] == JournalOperation.CREATE_TRIAL:
            created[len(created)] = i
        elif op["op_code"] == JournalOperation.SET_TRIAL_STATE_VALUES:
            if TrialState(op["state"]).is_finished():
                finished.setdefault(op["trial_id"], i)
    return created, finished
