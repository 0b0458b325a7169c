"""What a name may import (docs/envs.md, "Security: what a name may import"; rlexp.common.registry.reach):
every name a config or an exported file gives is refused in one line, exit 2, when it reaches past
what it may: an allowed module's own imports (``os``, ``subprocess``, ``importlib``), private and
dunder paths, a submodule reached by attribute, a prefix without its ``.`` boundary, the standard
library, or, from an exported file's metadata, any module outside the allowlist. Each case proves
that nothing ran: the marker file the hostile name would write is not there, the module it would
import is not imported. And a per-task preset is never applied to another env id (#43 item 12).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
import torch

from conftest import CONF_DIR, REPO, compose, rlexp_cli, run_train
from rlexp.config.validate import ConfigError, to_dict, to_root_config

TESTS = Path(__file__).resolve().parent


def _build_check(overrides: list[str]) -> str:
    """The config check of ``python train.py`` on ``overrides`` (env=hopper first): its one line."""
    from rlexp.launch.checks import check_buildable

    config = to_root_config(compose(["env=hopper", *overrides]))
    with pytest.raises(ConfigError) as err:
        check_buildable(config)
    msg = str(err.value)
    assert "\n" not in msg, msg
    return msg


def _evil_module(tmp_path: Path, monkeypatch, dotted: str, marker: Path) -> None:
    """A module ``dotted`` (packages made as needed) that writes ``marker`` when imported and whose
    ``f`` writes it when called; importable from ``tmp_path``; forgotten after the test."""
    parts = dotted.split(".")
    folder = tmp_path
    for pkg in parts[:-1]:
        folder = folder / pkg
        folder.mkdir(exist_ok=True)
        (folder / "__init__.py").write_text(f"open({str(marker)!r}, 'w').write('imported')\n")
    (folder / f"{parts[-1]}.py").write_text(
        f"open({str(marker)!r}, 'w').write('imported')\n"
        f"def f(*args, **kwargs):\n    open({str(marker)!r}, 'w').write('called')\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    for i in range(len(parts)):
        monkeypatch.delitem(sys.modules, ".".join(parts[: i + 1]), raising=False)


# -- #43 item 1: the env gate holds for what the name reaches ----------------------------------------
def _reaching(marker: Path) -> list[tuple[str, str, list[str]]]:
    """(backend, env.name, overrides): each names something that would write ``marker`` (or run
    code) if it were called; the module before ':' is allowed, what the path reaches is not."""
    touch = f"+env.kwargs.command='touch {marker}'"
    argv = f"+env.kwargs.args=[touch,'{marker}']"
    return [
        ("vecenv", "rlexp.envs.batched:os.system", [touch]),  # the issue's own case
        ("torchrl", "rlexp.envs.batched:os.system", [touch]),
        ("vecenv", "torchrl.envs.transforms.vc1:subprocess.call", [argv]),  # vc1 imports subprocess
        ("vecenv", "torchrl.envs.transforms.vc1:subprocess.run", [argv]),
        ("vecenv", "torchrl.envs.transforms.vc1:os.system", [touch]),
        ("vecenv", "rlexp.envs.native:importlib.import_module", ["+env.kwargs.name=this"]),
        ("vecenv", "rlexp.envs:batched.os.system", [touch]),  # a submodule reached by attribute
        ("vecenv", "rlexp.envs:batched", []),
        ("vecenv", "rlexp.envs.batched:os", []),  # a module the allowed one imports
        ("vecenv", "rlexp.envs.batched:__builtins__", []),
        ("torchrl", "rlexp.envs.batched:resolve_env_factory.__globals__", []),
        ("torchrl", "rlexp.envs.batched:EnvBase.__class__", []),
        ("vecenv", "rlexp.envs.batched:_ways_to_allow", []),  # private
        ("vecenv", "rlexp.envs.__init__:x", []),
        ("vecenv", "rlexp.envs.batched:first_line", []),  # defined in rlexp.config.rules
        ("torchrl", "torchrl.envs:VC1Transform.install_vc_models", ["+env.kwargs.auto_exit=true"]),
        ("torchrl", "torchrl.envs:VC1Transform", []),  # a class, but not an env
        (
            "vecenv",
            "rlexp.files.fsutil:atomic_write_text",
            [f"+env.kwargs.path='{marker}'", "+env.kwargs.text=x"],
        ),  # fmt: skip
        ("vecenv", "os:system", [touch]),
        ("vecenv", "subprocess:run", [argv]),
        ("vecenv", "importlib:import_module", ["+env.kwargs.name=this"]),
        ("vecenv", "builtins:eval", ["+env.kwargs.source='print(1)'"]),
    ]


@pytest.mark.parametrize("case", range(len(_reaching(Path("m")))))
def test_a_name_is_refused_for_what_it_reaches_and_nothing_runs(case, tmp_path, monkeypatch):
    monkeypatch.delenv("RLEXP_ENV_MODULES", raising=False)
    marker = tmp_path / "pwned"
    backend, name, extra = _reaching(marker)[case]
    had_this = "this" in sys.modules
    msg = _build_check([f"env.backend={backend}", f"env.name={name}", *extra])
    assert f"env.name={name!r}" in msg, msg
    assert not marker.exists(), f"{name} ran before it was refused"
    assert ("this" in sys.modules) == had_this, f"{name} imported a module"


def test_the_issue_s_command_line_is_one_line_exit_2_and_runs_nothing(tmp_path):
    marker = tmp_path / "X"
    args = [
        "env=hopper",
        "env.backend=vecenv",
        "env.name=rlexp.envs.batched:os.system",
        f"+env.kwargs.command='touch {marker}'",
        f"hydra.run.dir={tmp_path / 'run'}",
    ]
    proc = run_train(args, tmp_path, check=False)
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr
    assert "env.name='rlexp.envs.batched:os.system'" in lines[0] and "os.system" in lines[0]
    assert not marker.exists() and not (tmp_path / "run").exists()


def test_a_function_the_allowed_module_defines_itself_still_resolves(monkeypatch):
    """The gate is no blanket refusal: the module's own function and an EnvBase class pass."""
    from batched_toy import make_vecenv

    from rlexp.envs.batched import resolve_env_factory

    monkeypatch.setenv("RLEXP_ENV_MODULES", "batched_toy")
    assert resolve_env_factory("batched_toy:make_vecenv", "vecenv") is make_vecenv
    from torchrl.envs import GymEnv

    assert resolve_env_factory("torchrl.envs:GymEnv", "torchrl") is GymEnv


# -- #44 item 2: the prefix boundary ------------------------------------------------------------------
@pytest.mark.parametrize(
    "module, shell",
    [
        ("rlexp_evil.mod", ""),  # "rlexp" without its "."
        ("rlexp.envsx.mod", ""),  # "rlexp.envs" without its "."
        ("rlexp.envs_evil", ""),
        ("torchrl.envsx", ""),
        ("torchrl.envs_evil.mod", ""),
        ("batched_toyx", "batched_toy"),  # the shell's prefix without its "."
        ("batched_toy_evil.mod", "batched_toy"),
        ("batched_toy_evil.mod", "batched_toy."),
    ],
)
def test_an_allowed_prefix_admits_only_its_own_modules(module, shell, tmp_path, monkeypatch):
    from rlexp.envs.batched import resolve_env_factory

    monkeypatch.setenv("RLEXP_ENV_MODULES", shell)
    marker = tmp_path / "pwned"
    if not module.startswith("torchrl.") and not module.startswith("rlexp.envs"):
        _evil_module(tmp_path, monkeypatch, module, marker)
    with pytest.raises(ValueError, match="is not allowed") as err:
        resolve_env_factory(f"{module}:f", "vecenv")
    assert "\n" not in str(err.value)
    assert not marker.exists() and module not in sys.modules
    assert module.split(".")[0] in ("rlexp", "torchrl") or module.split(".")[0] not in sys.modules


def test_the_boundary_itself_and_an_exact_shell_prefix(tmp_path, monkeypatch):
    from rlexp.common.registry import under
    from rlexp.envs.batched import resolve_env_factory

    assert under("torchrl.envs", ["torchrl.envs."]) and under("torchrl.envs.libs", ["torchrl.envs"])
    assert not under("torchrl.envsx", ["torchrl.envs"]) and not under("torchrl", ["torchrl.envs."])
    assert not under("rlexp_evil", ["rlexp."]) and not under("rlexp", ["rlexp.envs."])
    marker = tmp_path / "pwned"
    _evil_module(tmp_path, monkeypatch, "lab_envs.mod", marker)
    monkeypatch.setenv("RLEXP_ENV_MODULES", "lab_envs")  # the shell allows exactly this package
    fn = resolve_env_factory("lab_envs.mod:f", "vecenv")
    assert fn.__module__ == "lab_envs.mod" and marker.read_text() == "imported"


@pytest.mark.parametrize(
    "kind, name",
    [
        ("hook", "rlexp.hooks_evil.f"),
        ("hook", "rlexp.hooksx.f"),
        ("hook", "rlexp.hooks.base.resolve"),  # imported there from rlexp.common.registry
        ("hook", "rlexp.hooks.base.__builtins__"),
        ("hook", "rlexp.hooks.__init__.x"),
        ("event", "rlexp.events_evil.f"),
        ("event", "rlexp.eventsx.f"),
        ("event", "rlexp.events.manager.resolve"),
        ("event", "rlexp.events.manager.np"),  # a module it imports
        ("event", "rlexp.events.builtin.os.system"),
        ("event", "rlexp.events.manager._ALLOWED_MODULES"),
    ],
)
def test_events_and_hooks_resolve_through_the_same_gate(kind, name):
    from rlexp.events.manager import resolve_event_func
    from rlexp.hooks.base import resolve_hook_func

    resolve = resolve_hook_func if kind == "hook" else resolve_event_func
    with pytest.raises(ValueError) as err:
        resolve(name, f"{kind}s.x")
    assert f"{kind}s.x.func={name!r}" in str(err.value) and "\n" not in str(err.value)
    assert name.rpartition(".")[0] not in sys.modules or name.count("_evil") + name.count("x.") == 0


@pytest.mark.parametrize(
    "path",
    ["subprocess.run", "os.system", "builtins.eval", "importlib.import_module", "this.s",
     "rlexp.common.registry._IDENT", "rlexp.common.registry.importlib", "rlexp.common.registry.reach.__globals__"],
)  # fmt: skip
def test_the_sweeper_s_custom_search_space_resolves_through_the_same_gate(path):
    from rlexp.launch.optuna_sweeper import check_spec

    had_this = "this" in sys.modules
    with pytest.raises(ValueError, match=r"hydra.sweeper.custom_search_space=") as err:
        check_spec({"custom_search_space": path, "direction": "maximize"}, [])
    assert "\n" not in str(err.value) and ("this" in sys.modules) == had_this


@pytest.mark.parametrize(
    "target",
    ["optuna.samplers._tpe.sampler.np.save", "optuna.samplers.TPESampler.__init__",
     "optuna.samplers.os.system", "optuna.pruners.BasePruner.prune"],
)  # fmt: skip
def test_optuna_sampler_targets_reach_only_optuna_s_own_classes(target, tmp_path):
    """Hydra's instantiate walks attributes: an allowed prefix reached numpy's ``np.save``."""
    from rlexp.launch import optuna_study

    marker = tmp_path / "pwned.npy"
    node = {"_target_": target, "file": str(marker), "arr": [1]}
    with pytest.raises(ValueError, match=r"hydra.sweeper.sampler._target_=") as err:
        optuna_study.build(optuna_study.leaf_config("hydra.sweeper.sampler", node, {}))
    assert "\n" not in str(err.value) and not marker.exists()


@pytest.mark.parametrize(
    "target",
    ["shutil.copyfile", "subprocess.run", "hydra.utils.instantiate", "hydra.utils.os.system",
     "hydra_evil.cb.Callback", "rlexp.common.registry.importlib"],
)  # fmt: skip
def test_hydra_callbacks_resolve_through_the_same_gate(target, tmp_path):
    """Hydra calls each ``hydra.callbacks`` ``_target_`` at start-up: ``shutil.copyfile`` would
    write the marker before the run (Hydra's own blocklist misses it)."""
    from rlexp.launch.precheck import precheck

    marker = tmp_path / "pwned"
    cb = [f"+hydra.callbacks.x._target_={target}", "+hydra.callbacks.x.src=/etc/hostname",
          f"+hydra.callbacks.x.dst={marker}", f"+hydra.callbacks.x.args=[touch,'{marker}']"]  # fmt: skip
    with pytest.raises(ConfigError, match=r"hydra.callbacks.x._target_=") as err:
        precheck(["env=inverted_pendulum", "trainer=smoke", *cb], CONF_DIR)
    assert "\n" not in str(err.value) and not marker.exists() and "hydra_evil" not in sys.modules
    ok = "+hydra.callbacks.x._target_=hydra.experimental.callbacks.LogJobReturnCallback"
    precheck(["env=inverted_pendulum", "trainer=smoke", ok, f"hydra.run.dir={tmp_path / 'r'}"], CONF_DIR)  # fmt: skip


@pytest.mark.parametrize(
    "overrides",
    [
        [
            "+hydra.job_logging.handlers.x.class=tarfile.TarFile",
            "+hydra.job_logging.handlers.x.name={m}",
            "+hydra.job_logging.handlers.x.mode=w",
        ],  # fmt: skip
        [
            "+hydra.hydra_logging.handlers.x.class=shutil.copyfile",
            "+hydra.hydra_logging.handlers.x.src=/etc/hostname",
            "+hydra.hydra_logging.handlers.x.dst={m}",
        ],  # fmt: skip
        [
            "+hydra.job_logging.handlers.x.class=logging.handlers.os.system",
            "+hydra.job_logging.handlers.x.command='touch {m}'",
        ],  # fmt: skip
        ["+hydra.job_logging.handlers.x.class=logging._StderrHandler"],
        ["hydra.job_logging.handlers.console.stream=ext://antigravity.x"],
        [
            "+hydra.job_logging.formatters.x.format=x",
            "+hydra.job_logging.formatters.x.class=pathlib.Path",
        ],  # fmt: skip
    ],
)
def test_hydra_logging_classes_are_logging_s_own(overrides, tmp_path):
    """dictConfig builds each handler ``class`` with the config's keywords at start-up."""
    from rlexp.launch.precheck import precheck

    marker = tmp_path / "pwned"
    args = [o.replace("{m}", str(marker)) for o in overrides]
    with pytest.raises(ConfigError, match=r"hydra\.(job|hydra)_logging\.") as err:
        precheck(["env=inverted_pendulum", "trainer=smoke", *args], CONF_DIR)
    assert "\n" not in str(err.value) and not marker.exists() and "antigravity" not in sys.modules


# -- #43 item 3: Gymnasium's module:EnvId -----------------------------------------------------------
@pytest.mark.parametrize(
    "overrides",
    [
        ["env.name=this:X-v0"],
        ["env.name=antigravity:X-v0"],
        ["env.name=os:X-v0"],
        ["env.backend=gymnasium_async", "env.name=this:X-v0"],
        ["env.backend=torchrl_gym", "env.name=this:X-v0"],
        ["env.backend=torchrl", "env.name=torchrl.envs:GymEnv", "+env.kwargs.env_name=this:X-v0"],
        ["env.name=lab._private:X-v0"],
        ["env.name=lab.__init__:X-v0"],
    ],
)
def test_module_env_ids_never_import_the_standard_library_or_private_modules(overrides):
    before = {m for m in ("this", "antigravity", "lab", "lab._private") if m in sys.modules}
    msg = _build_check(overrides)
    assert "env.name=" in msg or "env.kwargs.env_name" in msg, msg
    assert {m for m in ("this", "antigravity", "lab", "lab._private") if m in sys.modules} == before


def test_a_user_module_on_the_command_line_is_gymnasium_s_own_semantics(tmp_path, monkeypatch):
    """The rule's other half: the user's own module, named on the command line, is imported."""
    from rlexp.launch.checks import check_buildable

    marker = tmp_path / "imported"
    (tmp_path / "lab_gym.py").write_text(
        f"open({str(marker)!r}, 'w').write('yes')\nimport gymnasium as gym\n"
        "gym.register('LabPole-v0', entry_point='gymnasium.envs.classic_control:CartPoleEnv', "
        "max_episode_steps=20)\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, "lab_gym", raising=False)
    check_buildable(to_root_config(compose(["env=gym_cartpole", "env.name=lab_gym:LabPole-v0"])))
    assert marker.read_text() == "yes"


# -- #43 item 2: exported metadata is data ----------------------------------------------------------
#: NoStateWalk-v0's Discrete(3, start=-1), as rlexp export writes it
WALK_SPACE = {
    "kind": "discrete",
    "shape": [],
    "dim": 1,
    "dtype": "int64",
    "nvec": [3],
    "start": [-1],
}


class _Left(torch.nn.Module):
    """Always the env's value -1 (a step left), as an exported categorical policy gives it."""

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        return torch.full((observation.shape[0], 1), -1, dtype=torch.int64)


def _export(tmp_path: Path, overrides: list[str], **fields) -> Path:
    """A TorchScript file and its metadata, as rlexp export writes them, with ``fields`` changed."""
    from rlexp.deploy.policy_eval import EXPORT_SCHEMA

    path = tmp_path / "shared" / "policy.pt"
    path.parent.mkdir(exist_ok=True)
    torch.jit.script(_Left()).save(str(path))
    config = to_dict(to_root_config(compose(["env=hopper", *overrides])))
    meta = {
        "schema": EXPORT_SCHEMA,
        "format": "torchscript",
        "global_step": 512,
        "observation_dim": 1,
        "action_dim": 1,
        "observation_layout": None,
        "action_space": WALK_SPACE,
        "config": config,
        **fields,
    }
    Path(f"{path}.json").write_text(json.dumps(meta))
    return path


WALK = ["env.name=toy_envs:NoStateWalk-v0", "env.num_eval_envs=2"]


def test_an_exported_file_evaluates_with_its_module_allowed_and_not_after_start_changed(
    tmp_path, monkeypatch
):
    monkeypatch.setenv("RLEXP_ENV_MODULES", "toy_envs")  # the user trusts this module
    code, out, err = rlexp_cli("eval", _export(tmp_path, WALK), "--episodes", "2")
    assert code == 0 and "mean return" in out, err
    changed = dict(WALK_SPACE, start=[0])  # the file's outputs would be other actions
    code, out, err = rlexp_cli(
        "eval", _export(tmp_path, WALK, action_space=changed), "--episodes", "2"
    )
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == 2 and len(lines) == 1, err
    assert "another action space" in lines[0] and "'start': [0]" in lines[0], lines[0]


def _hostile_names(marker: Path) -> list[list[str]]:
    touch = f"+env.kwargs.command='touch {marker}'"
    return [
        ["env.name=lab_shared:Walk-v0"],  # a module on the path, not allowed: never imported
        ["env.name=lab_shared.sub:Walk-v0"],
        ["env.name=this:X-v0"],
        ["env.backend=gymnasium_async", "env.name=lab_shared:Walk-v0"],
        ["env.backend=vecenv", "env.name=rlexp.envs.batched:os.system", touch],
        ["env.backend=vecenv", "env.name=lab_shared:f"],
        [
            "env.backend=torchrl",
            "env.name=torchrl.envs:GymEnv",
            "+env.kwargs.env_name=lab_shared:Walk-v0",
        ],  # fmt: skip
    ]


@pytest.mark.parametrize("case", range(len(_hostile_names(Path("m")))))
def test_exported_metadata_never_imports_or_runs_code(case, tmp_path, monkeypatch):
    monkeypatch.delenv("RLEXP_ENV_MODULES", raising=False)
    marker = tmp_path / "pwned"
    _evil_module(tmp_path, monkeypatch, "lab_shared.sub", marker)
    (tmp_path / "lab_shared" / "__init__.py").write_text(
        f"open({str(marker)!r}, 'w').write('imported')\ndef f(**kw):\n"
        f"    open({str(marker)!r}, 'w').write('called')\n"
    )
    had_this = "this" in sys.modules
    path = _export(tmp_path, _hostile_names(marker)[case])
    code, out, err = rlexp_cli("eval", path, "--episodes", "1")
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == 2 and len(lines) == 1, err
    assert "exported policy" in lines[0], lines[0]
    assert not marker.exists() and "lab_shared" not in sys.modules
    assert ("this" in sys.modules) == had_this


@pytest.mark.parametrize(
    "fields, key",
    [
        ({"global_step": None}, "global_step"),
        ({"global_step": -5}, "global_step"),
        ({"observation_dim": "1"}, "observation_dim"),
        ({"action_dim": 0}, "action_dim"),
        ({"action_space": dict(WALK_SPACE, start="abc")}, "action_space"),
        ({"action_space": dict(WALK_SPACE, kind="__import__")}, "action_space"),
        ({"action_space": "box"}, "action_space"),
        ({"observation_layout": [1, 2]}, "observation_layout"),
    ],
)
def test_exported_metadata_fields_are_what_an_export_writes(fields, key, tmp_path, monkeypatch):
    monkeypatch.setenv("RLEXP_ENV_MODULES", "toy_envs")
    code, out, err = rlexp_cli("eval", _export(tmp_path, WALK, **fields), "--episodes", "1")
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == 2 and len(lines) == 1, err
    assert f"{key}=" in lines[0] and "policy.pt.json" in lines[0], lines[0]


# -- #43 item 12: a per-task preset is for its own env id -------------------------------------------
@pytest.mark.parametrize(
    "overrides, preset",
    [
        (["+experiment=tuned", "env=hopper", "env.name=Walker2d-v5"], "+experiment=tuned"),
        (["+experiment=rl_zoo", "env=hopper", "env.name=Walker2d-v5"], "+experiment=rl_zoo"),
        (["env=walker2d", "+experiment=tuned", "env.name=Hopper-v5"], "+experiment=tuned"),
        (["+experiment=tuned", "env=gym_cartpole", "env.name=Acrobot-v1"], "+experiment=tuned"),
        (["+experiment=pendulum_ppo", "env.name=Acrobot-v1"], "+experiment=pendulum_ppo"),
        (["+experiment=cart_pole_grpo", "env.name=push_cube"], "+experiment=cart_pole_grpo"),
        (["env=hopper", "tuned=walker2d"], "tuned=walker2d"),
        (["-m", "+experiment=tuned", "env=hopper", "env.name=Hopper-v5,Walker2d-v5"], "job 1"),
        (["-m", "+experiment=rl_zoo", "env=hopper,ant", "env.name=Ant-v5"], "job 0"),
    ],
)
def test_a_preset_applied_to_another_env_id_is_refused(overrides, preset):
    from rlexp.launch.precheck import precheck

    with pytest.raises(ConfigError) as err:
        precheck([*overrides, "trainer.total_frames=256"], CONF_DIR)
    msg = str(err.value)
    assert "\n" not in msg and preset in msg and "env.name=" in msg, msg


@pytest.mark.parametrize(
    "overrides",
    [
        ["+experiment=tuned", "env=hopper"],
        ["+experiment=tuned", "env=hopper", "env.name=Hopper-v5"],
        ["env=hopper", "env.name=Walker2d-v5"],  # no preset: any id
        ["+experiment=pendulum_ppo"],
        ["-m", "+experiment=tuned", "env=hopper,walker2d"],
    ],
)
def test_a_preset_on_its_own_env_id_passes(overrides, tmp_path):
    from rlexp.launch.precheck import precheck

    precheck([*overrides, "trainer.total_frames=256", f"hydra.run.dir={tmp_path / 'r'}",
              f"hydra.sweep.dir={tmp_path / 's'}"], CONF_DIR)  # fmt: skip


def test_a_preset_on_another_env_id_is_exit_2_from_the_command_line(tmp_path):
    args = ["+experiment=tuned", "env=hopper", "env.name=Walker2d-v5", f"hydra.run.dir={tmp_path / 'r'}"]  # fmt: skip
    proc = run_train(args, tmp_path, check=False)
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr
    assert "Hopper-v5" in lines[0] and "env.name='Walker2d-v5'" in lines[0], lines[0]
    assert not (tmp_path / "r").exists()


def test_docs_state_the_rule_once():
    envs = (REPO / "docs" / "envs.md").read_text()
    assert envs.count("## Security: what a name may import") == 1
    assert "what-a-name-may-import" in (REPO / "docs" / "faults.md").read_text()
