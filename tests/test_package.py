"""rlexp as a package: the wheel carries the configs, commands work from any directory, and a user's
project (examples/user_project) extends rlexp with its own task, reward term, event and configs.

``test_fresh_venv_user_project`` is the whole story on a clean machine: build rlexp's wheel and the
example's, install both into a new virtualenv (not the editable one), train the example's task from
the example's directory, and check its reward term is logged and its event fired (~1 min, the venv
included). ``test_fresh_venv_own_gymnasium_env``, in the same venv, does the same for the example's
own Gymnasium env (GridReach-v0): trained, resumed exactly, exported and run without rlexp (~40 s).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap
import zipfile
from importlib import metadata
from pathlib import Path

import numpy as np
import pytest
import torch

from conftest import CONF_DIR, REPO
from rlexp import plugins
from rlexp.config import paths
from rlexp.config.validate import ConfigError

pytestmark = pytest.mark.package  # in the default suite; alone: make test-package

EXAMPLE = REPO / "examples" / "user_project"
#: Not part of a build: the venv, caches, outputs, earlier in-tree builds.
_NOT_SOURCE = shutil.ignore_patterns(
    ".venv", ".git", "outputs", "multirun", "build", "dist", "*.egg-info", "__pycache__",
    ".pytest_cache", ".ruff_cache", "wandb", "*.pt", "MUJOCO_LOG.TXT",
)  # fmt: skip


def _clean_env(**extra: str) -> dict[str, str]:
    """The environment of a fresh shell: nothing points Python at this checkout."""
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
    env.pop("VIRTUAL_ENV", None)
    # the fresh venv (installed --no-compile) keeps the bytecode its first process compiles: each
    # later process then starts in ~4 s instead of ~12 s recompiling torch
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    env.setdefault("MUJOCO_GL", "egl")
    return {**env, **extra}


def _run(cmd: list[str], cwd: Path, timeout: float = 600) -> subprocess.CompletedProcess:
    proc = subprocess.run(
        [str(c) for c in cmd], cwd=cwd, capture_output=True, text=True, timeout=timeout,
        env=_clean_env(),
    )  # fmt: skip
    if proc.returncode != 0:
        raise AssertionError(
            f"{' '.join(map(str, cmd))} exited {proc.returncode}\n"
            f"STDOUT:\n{proc.stdout[-4000:]}\nSTDERR:\n{proc.stderr[-4000:]}"
        )
    return proc


@pytest.fixture(scope="module")
def wheels(tmp_path_factory) -> dict[str, Path]:
    """rlexp's and the example's wheels, built as a user builds them (``pip wheel``, isolated build
    environment) from copies of the sources, so that nothing is written into the checkout."""
    root = tmp_path_factory.mktemp("wheels")
    src = {"rlexp": root / "rlexp-src", "reach_lab": root / "user_project"}
    shutil.copytree(REPO, src["rlexp"], ignore=_NOT_SOURCE)
    shutil.copytree(EXAMPLE, src["reach_lab"], ignore=_NOT_SOURCE)
    dist = root / "dist"
    for path in src.values():
        _run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "-w", dist, path], root)
    built = {name: next(dist.glob(f"{name}-*.whl")) for name in src}
    return {**built, "user_project": src["reach_lab"]}


def test_wheel_ships_every_config_and_the_launcher_plugin(wheels):
    names = set(zipfile.ZipFile(wheels["rlexp"]).namelist())
    conf = {f"rlexp/conf/{p.relative_to(CONF_DIR).as_posix()}" for p in CONF_DIR.rglob("*.yaml")}
    assert conf and conf <= names, sorted(conf - names)
    assert "hydra_plugins/rlexp_launcher/slurm_launcher.py" in names
    assert "rlexp/envs/native/assets/push_cube.xml" in names
    meta = zipfile.ZipFile(wheels["rlexp"]).read(
        next(n for n in names if n.endswith(".dist-info/METADATA"))
    )
    extras = {line.split(b":", 1)[1].strip().decode() for line in meta.splitlines() if line.startswith(b"Provides-Extra:")}  # fmt: skip
    assert {"wandb", "slurm", "optuna", "video", "report", "all", "dev"} <= extras
    entry = (
        zipfile.ZipFile(wheels["reach_lab"])
        .read("reach_lab-0.1.0.dist-info/entry_points.txt")
        .decode()
    )
    assert "[rlexp.plugins]" in entry and "reach_lab.plugin:register" in entry


@pytest.fixture(scope="module")
def user_venv(wheels, tmp_path_factory) -> Path:
    """A new venv holding only the two wheels (and their dependencies)."""
    venv = tmp_path_factory.mktemp("fresh") / "venv"
    _run([sys.executable, "-m", "venv", venv], venv.parent)
    pip = [venv / "bin" / "python", "-m", "pip", "install", "-q", "--no-compile"]
    _run([*pip, "torch==2.13.0"], venv.parent)  # first: the CPU wheel, never the CUDA build
    _run([*pip, wheels["rlexp"], wheels["reach_lab"]], venv.parent)
    return venv


@pytest.fixture
def user_project(wheels, tmp_path) -> Path:
    """The example's directory, a git repository of its own (as a user's project is)."""
    project = tmp_path / "user_project"
    shutil.copytree(wheels["user_project"], project, ignore=_NOT_SOURCE)
    git = ["git", "-c", "user.name=t", "-c", "user.email=t@example.invalid"]
    _run([*git, "init", "-q"], project)
    _run([*git, "add", "."], project)
    _run([*git, "commit", "-q", "-m", "example"], project)
    return project


def test_fresh_venv_user_project(user_venv, user_project):
    """Only the two wheels (and their dependencies) in a new venv; the example's directory as the
    working directory; its task trained, its reward term logged, its event fired."""
    venv, project = user_venv, user_project
    rlexp = venv / "bin" / "rlexp"
    where = _run([venv / "bin" / "python", "-c", "import rlexp, reach_lab; print(rlexp.__file__, reach_lab.__file__)"], project)  # fmt: skip
    assert str(REPO) not in where.stdout and where.stdout.count(str(venv)) == 2, where.stdout
    assert (
        _run([rlexp, "--version"], project).stdout.strip() == f"rlexp {metadata.version('rlexp')}"
    )
    helped = _run([venv / "bin" / "python", "-m", "rlexp", "train", "--help"], project).stdout
    experiments = next(ln for ln in helped.splitlines() if ln.startswith("experiment: "))
    assert {"point_reach_ppo", "grid_reach_ppo", "push_cube_ppo"} <= set(
        experiments[12:].split(", ")
    ), experiments
    envs = next(ln for ln in helped.splitlines() if ln.startswith("env: "))
    assert {"ant", "point_reach", "grid_reach"} <= set(envs[5:].split(", ")), envs

    _run(
        [
            rlexp, "train", "+experiment=point_reach_ppo", "trainer.total_frames=2048",
            "trainer.frames_per_batch=1024", "trainer.eval_every=1024", "trainer.eval_episodes=4",
            "trainer.progress=false", "logger=none", "hydra.run.dir=run",
        ],
        project,
    )  # fmt: skip
    run = project / "run"
    lines = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
    proximity = [m["rewards/proximity"] for m in lines if "rewards/proximity" in m]
    assert len(proximity) == 2 and all(0 < v <= 1 for v in proximity), lines
    history = (run / "eval_history.csv").read_text().splitlines()
    assert history[0].startswith("step,eval/episode_return") and len(history) == 3, history
    assert [row.split(",")[0] for row in history[1:]] == ["1024", "2048"]
    prov = json.loads((run / "provenance.json").read_text())
    assert prov["plugins"] == {"reach_lab": "reach-lab 0.1.0"}
    assert prov["git_commit"] is None and prov["project"]["git_commit"]  # the project's commit
    assert prov["rlexp_conf"].startswith(str(venv))

    evaluated = _run([rlexp, "eval", "run", "--episodes", "2"], project).stdout  # the plugin's task
    assert (
        "point_reach_ppo_step_000002048.pt (step 2048; the last checkpoint): mean return"
        in evaluated
    )

    # the core install names the extra an option needs, before anything runs
    refused = subprocess.run(
        [rlexp, "train", "+experiment=point_reach_ppo", "logger=wandb", "hydra.run.dir=run2"],
        cwd=project, capture_output=True, text=True, timeout=300, env=_clean_env(),
    )  # fmt: skip
    assert refused.returncode == 2, refused.stderr
    assert "pip install 'wandb" in refused.stderr and not (project / "run2").exists()
    report = subprocess.run(
        [rlexp, "report", "run"], cwd=project, capture_output=True, text=True, timeout=60,
        env=_clean_env(),
    )  # fmt: skip
    assert report.returncode == 2 and "pip install 'scipy" in report.stderr, report.stderr


#: Runs in the venv without importing rlexp: the exported TorchScript policy plays GridReach-v0
#: episodes, its input flattened by hand as the metadata's observation_layout says.
_DEPLOY = textwrap.dedent(
    """
    import json, sys
    import gymnasium as gym
    import numpy as np
    import torch
    import reach_lab.gridworld  # registers GridReach-v0 (imports gymnasium and numpy only)

    path, out = sys.argv[1], sys.argv[2]
    meta = json.load(open(path + ".json"))
    layout = meta["observation_layout"]
    policy = torch.jit.load(path)

    def flatten(obs):
        vec = np.empty(layout["dim"], dtype=np.float32)
        for part in layout["parts"]:
            assert part["kind"] == "box", part  # GridReach: two Box entries of a Dict
            start = part["offset"]
            vec[start : start + part["size"]] = np.asarray(obs[part["key"]]).reshape(-1)
        return vec

    env = gym.make(meta["env_id"], **meta["config"]["env"]["kwargs"])
    seen, actions, returns = [], [], []
    for episode in range(8):
        obs, _ = env.reset(seed=100 + episode)
        done, total = False, 0.0
        while not done:
            vec = flatten(obs)
            action = int(policy(torch.from_numpy(vec[None]))[0, 0])
            seen.append(vec)
            actions.append(action)
            obs, reward, terminated, truncated, _ = env.step(action)
            total += reward
            done = terminated or truncated
        returns.append(total)
    np.savez(out, obs=np.stack(seen), actions=np.array(actions), returns=np.array(returns))
    assert "rlexp" not in sys.modules, sorted(m for m in sys.modules if m.startswith("rlexp"))
    print("episodes", len(returns))
    """
)

#: Runs in the venv with rlexp: the checkpoint's deterministic policy (what ``rlexp eval`` runs)
#: on the observations the exported file saw.
_REFERENCE = textwrap.dedent(
    """
    import sys
    import numpy as np
    import torch
    from tensordict import TensorDict
    from rlexp.config.validate import to_root_config
    from rlexp.envs.factory import make_env
    from rlexp.plugins import load_plugins
    from rlexp.deploy.policy_eval import eval_config, open_source

    checkpoint, data, out = sys.argv[1:4]
    load_plugins()  # GridReach-v0 is the plugin's id
    source = open_source(checkpoint)
    config = to_root_config(eval_config(source.config))
    env = make_env(config.env, 1, seed=0)
    policy = source.build(config, env)
    obs = torch.from_numpy(np.load(data)["obs"])
    with torch.no_grad():
        action = policy(TensorDict({"observation": obs}, batch_size=[len(obs)]))["action"]
    np.save(out, action.reshape(len(obs), -1)[:, 0].numpy())
    """
)


def _grid_run(rlexp: Path, project: Path, run_dir: str, *extra: str) -> Path:
    _run(
        [
            rlexp, "train", "+experiment=grid_reach_ppo", "trainer.progress=false", "logger=none",
            "seed=1", f"hydra.run.dir={run_dir}", *extra,
        ],
        project,
    )  # fmt: skip
    return project / run_dir


def _metric_rows(run: Path, after: int) -> list[dict]:
    """metrics.jsonl rows past ``after``, without wall-clock fields (time, perf/*)."""
    rows = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
    return [
        {k: v for k, v in row.items() if k != "time" and not k.startswith("perf/")}
        for row in rows
        if row["step"] > after
    ]


def test_fresh_venv_own_gymnasium_env(user_venv, user_project):
    """The example's own Gymnasium env (GridReach-v0, Dict observations, Discrete actions, its own
    get_state/set_state) from the installed packages: learned under the plugin's id; resumed from
    a mid-run checkpoint with the same result as the uninterrupted run; exported to TorchScript
    that acts as the checkpoint in a process without rlexp; and named as module:EnvId."""
    venv, project = user_venv, user_project
    rlexp, python = venv / "bin" / "rlexp", venv / "bin" / "python"

    # (1) the plugin's id (conf/env/grid_reach.yaml: env.name=GridReach-v0): 16k steps learn it
    whole = _grid_run(rlexp, project, "grid_whole")
    status = json.loads((whole / "status.json").read_text())
    assert status["state"] == "finished" and status["env_resume"] is None, status
    assert status["final_eval"]["eval/episode_return"] > 0.9, status  # the optimum is ~0.98
    log = (whole / "train.log").read_text()
    assert "env GridReach-v0 x8: obs 4, action 1" in log, log[:2000]

    # (2) resumed from the uninterrupted run's mid-run checkpoint into a new dir: the envs are put
    # back mid-episode through GridReach.get_state/set_state, and the run ends where it did
    half = whole / "checkpoints" / "grid_reach_ppo_step_000008192.pt"
    mid = torch.load(half, map_location="cpu", weights_only=False)["envs"]["train"]
    assert mid["kind"] == "state" and any(c["elapsed_steps"] > 0 for c in mid["copies"]), mid
    resumed = _grid_run(rlexp, project, "grid_resumed", f"trainer.resume={half}")
    status = json.loads((resumed / "status.json").read_text())
    assert status["env_resume"] == "restored (the env's get_state)", status
    last = "checkpoints/grid_reach_ppo_step_000016384.pt"
    a, b = (torch.load(r / last, map_location="cpu", weights_only=False) for r in (whole, resumed))
    assert a["global_step"] == b["global_step"] == 16384
    for key, value in a["policy"].items():
        assert torch.equal(value, b["policy"][key]), f"policy.{key} differs after resume"
    assert a["windows"]["returns"] == b["windows"]["returns"]
    assert _metric_rows(whole, 8192) == _metric_rows(resumed, 8192)

    # (3) exported; played by plain torch + gymnasium; the same actions as the checkpoint's policy
    out = _run(
        [rlexp, "export", "grid_whole", "--checkpoint", "best", "--format", "torchscript"], project
    ).stdout
    exported = whole / "exported" / "best.pt"
    assert "as torchscript: grid_whole/exported/best.pt" in out, out
    (project / "deploy.py").write_text(_DEPLOY)
    (project / "reference.py").write_text(_REFERENCE)
    played = _run([python, "deploy.py", exported, "played.npz"], project, timeout=120)
    assert "episodes 8" in played.stdout, played.stdout
    data = np.load(project / "played.npz")
    assert data["returns"].mean() > 0.9, data["returns"]  # every goal reached, near the shortest
    _run([python, "reference.py", whole / "checkpoints" / "best.pt", "played.npz", "ref.npy"], project, timeout=120)  # fmt: skip
    np.testing.assert_array_equal(np.load(project / "ref.npy"), data["actions"])

    # (4) Gymnasium's module:EnvId syntax: the module registers the id as it is imported
    named = _grid_run(
        rlexp, project, "grid_module", "env.name=reach_lab.gridworld:GridReach-v0",
        "trainer.total_frames=2048", "trainer.eval_every=2048", "trainer.save_every=2048",
    )  # fmt: skip
    log = (named / "train.log").read_text()
    assert "env reach_lab.gridworld:GridReach-v0 x8: obs 4, action 1" in log, log[:2000]
    assert json.loads((named / "status.json").read_text())["global_step"] == 2048


# -- configs: rlexp's own and the user's ----------------------------------------------------------


def test_conf_dir_is_the_checkouts_in_an_editable_install():
    assert paths.find_conf_dir() == CONF_DIR.resolve()


def test_a_conf_dir_in_the_working_directory_is_added(tmp_path):
    (tmp_path / "conf").mkdir()
    argv = paths.with_user_config_dir(["trainer=smoke"], cwd=tmp_path)
    assert argv == [f"--config-dir={(tmp_path / 'conf').resolve()}", "trainer=smoke"]
    # an explicit one wins; rlexp's own conf/ (running in the checkout) is not added twice
    assert paths.with_user_config_dir(["-cd", "x", "a=1"], cwd=tmp_path) == ["-cd", "x", "a=1"]
    assert paths.with_user_config_dir(["a=1"], cwd=REPO) == ["a=1"]
    assert paths.with_user_config_dir(["a=1"], cwd=tmp_path / "conf") == ["a=1"]


def _user_conf(root: Path) -> Path:
    conf = root / "conf"
    (conf / "experiment").mkdir(parents=True)
    (conf / "experiment" / "tiny_pendulum.yaml").write_text(
        "# @package _global_\ndefaults:\n  - override /env: inverted_pendulum\n  - _self_\n"
        "trainer:\n  total_frames: 512\n  frames_per_batch: 256\n  exp_name: mine\n"
    )
    return conf


def test_precheck_honours_the_users_config_dir(tmp_path):
    from rlexp.launch.precheck import precheck

    conf = _user_conf(tmp_path)
    run_dir = f"hydra.run.dir={tmp_path / 'run'}"
    config = precheck(["--config-dir", str(conf), "+experiment=tiny_pendulum", run_dir], CONF_DIR)
    assert config is not None and config.trainer.exp_name == "mine"
    assert config.env.name == "InvertedPendulum-v5"
    with pytest.raises(ConfigError, match=r"did you mean experiment=tiny_pendulum\?"):
        precheck(["--config-dir", str(conf), "+experiment=tiny_pendulm", run_dir], CONF_DIR)
    with pytest.raises(ConfigError, match="--config-dir nowhere: no such directory"):
        precheck(["--config-dir", "nowhere", "trainer=smoke", run_dir], CONF_DIR)


# -- plugins --------------------------------------------------------------------------------------


@pytest.fixture
def fake_plugins(monkeypatch, tmp_path):
    """``rlexp.plugins`` entry points of our own (none of the installed ones), loaded afresh."""
    found: list[metadata.EntryPoint] = []
    monkeypatch.setattr(plugins, "_done", False)
    monkeypatch.setattr(plugins, "LOADED", {})
    monkeypatch.setattr(
        plugins.metadata, "entry_points", lambda group: [e for e in found if e.group == group]
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    return found


def test_plugins_are_loaded_once_and_called(fake_plugins, tmp_path):
    (tmp_path / "my_lab_plugin.py").write_text("CALLS = []\ndef register():\n    CALLS.append(1)\n")
    fake_plugins.append(
        metadata.EntryPoint(name="my_lab", value="my_lab_plugin:register", group=plugins.GROUP)
    )
    assert plugins.load_plugins() == {"my_lab": "unknown package"}
    plugins.load_plugins()
    import my_lab_plugin

    assert my_lab_plugin.CALLS == [1]


@pytest.mark.parametrize(
    ("value", "error"),
    [
        ("no_such_module_for_rlexp:register", "ModuleNotFoundError: No module named"),
        ("broken_lab_plugin:register", "RuntimeError: no scene file"),
    ],
)
def test_a_plugin_that_fails_is_named(fake_plugins, tmp_path, value, error):
    (tmp_path / "broken_lab_plugin.py").write_text(
        "def register():\n    raise RuntimeError('no scene file')\n"
    )
    fake_plugins.append(metadata.EntryPoint(name="broken_lab", value=value, group=plugins.GROUP))
    with pytest.raises(plugins.PluginError) as err:
        plugins.load_plugins()
    msg = str(err.value)
    assert msg.startswith(f"rlexp plugin 'broken_lab' ({value}, from unknown package) failed")
    assert error in msg and "uninstall" in msg


def test_a_broken_plugin_stops_rlexp_train_in_one_line(tmp_path):
    """Through the real entry-point machinery: a dist-info on the path declares the plugin."""
    site = tmp_path / "site"
    info = site / "broken_lab-1.0.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: broken-lab\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text(
        "[rlexp.plugins]\nbroken_lab = broken_lab_mod:register\n"
    )
    (site / "broken_lab_mod.py").write_text("import no_such_dependency_of_broken_lab\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO / "src"), str(site)])}
    proc = subprocess.run(
        [sys.executable, "-m", "rlexp", "train", "trainer=smoke"], cwd=tmp_path,
        capture_output=True, text=True, timeout=120, env=env,
    )  # fmt: skip
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.strip().splitlines() == [
        "rlexp train: rlexp plugin 'broken_lab' (broken_lab_mod:register, from broken-lab 1.0) "
        "failed to load: ModuleNotFoundError: No module named 'no_such_dependency_of_broken_lab'; "
        "fix the package or uninstall it"
    ]
    assert not (tmp_path / "outputs").exists()


# -- extras and the command line ------------------------------------------------------------------


def test_a_missing_extra_is_named(monkeypatch):
    from conftest import compose
    from rlexp import extras
    from rlexp.config.paths import CONF_DIR
    from rlexp.config.validate import to_root_config
    from rlexp.launch.precheck import precheck

    missing = ("wandb", "optuna", "hydra_plugins.hydra_submitit_launcher")
    monkeypatch.setattr(extras, "_installed", lambda module: module not in missing)
    config = to_root_config(compose(["logger=wandb"]))
    with pytest.raises(
        extras.MissingExtra, match=r"logger.wandb.enabled=true .*pip install 'wandb"
    ):
        extras.check_config(config)
    msg = "In 'hydra/config': Could not find 'hydra/launcher/submitit'"
    assert extras.hint(msg).endswith(f"(rlexp's 'slurm' extra is not installed: {extras.install_hint('slurm')})")  # fmt: skip
    # rlexp ships hydra/sweeper=optuna itself: a sweep with it names the extra before Hydra starts
    with pytest.raises(extras.MissingExtra, match=r"hydra/sweeper=optuna .*pip install 'optuna"):
        precheck(["-m", "hydra/sweeper=optuna", "seed=0"], CONF_DIR)
    assert extras.hint("No module named 'optuna'").endswith(f"{extras.install_hint('optuna')})")
    assert "hydra-optuna-sweeper" not in extras.install_hint("optuna")
    assert extras.hint("ModuleNotFoundError: No module named 'wandb.sdk'").endswith(
        f"{extras.install_hint('wandb')})"
    )
    assert extras.hint("No module named 'scipy'") == "No module named 'scipy'"  # installed here


def test_version_and_train_help():
    env = {**os.environ, "PYTHONPATH": str(REPO / "src")}
    out = subprocess.run(
        [sys.executable, "-m", "rlexp", "--version"], capture_output=True, text=True, env=env
    )
    assert out.stdout.strip() == f"rlexp {metadata.version('rlexp')}"
    helped = subprocess.run(
        [sys.executable, "-m", "rlexp", "train", "--help"], capture_output=True, text=True,
        env=env, cwd=REPO,
    ).stdout  # fmt: skip
    assert helped.startswith("rlexp train [--config-json FILE]")
    for group in ("algorithm:", "env:", "events:", "experiment:", "logger:", "policy:", "trainer:"):
        assert f"\n{group} " in helped, group
