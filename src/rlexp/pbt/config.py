"""Population Based Training's settings: the typed schema of ``hooks.pbt.params`` (conf/sweep/pbt.yaml)
and the checks of a PBT sweep's command line (launcher, population size), each one line naming
the key, the value and the file (exit 2 through ``rlexp.launch.precheck``)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from rlexp.config.native_task import Flag, Number, OrNull, ParamRule, Text, check_params

#: The modes: members never wait (DexPBT, Ray) or wait for each other at every ready point.
MODES = ("async", "sync")
#: How members start: the config's values (all alike, seeds differ) or drawn within the bounds.
INITS = ("config", "sample")
#: Where the sweep yaml lives: errors name it.
SWEEP_FILE = "conf/sweep/pbt.yaml"


@dataclass(frozen=True)
class HyperparameterRange:
    """Bounds of one mutable hyperparameter: perturbations are clipped to them, resamples drawn in
    them (``log``: log-uniformly, for rates)."""

    low: float
    high: float
    log: bool = False


@dataclass(frozen=True)
class PBTConfig:
    """``hooks.pbt.params``; defaults from Jaderberg et al. 2017 and Ray Tune's PBT."""

    population_size: int = 4  # members: the sweep's jobs (one per seed)
    ready_every: int = 50_000  # env steps between ready points (exploit/explore decisions)
    mode: str = "async"  # async: never wait | sync: generations, each waits for its siblings
    score: str = "train/episode_return"  # the member's own recent returns (mean of the last 100)
    quantile: float = 0.25  # bottom / top fraction (Ray's quantile_fraction; Jaderberg 20%)
    perturb_factors: tuple[float, ...] = (0.8, 1.2)  # explore: multiply by one of these
    resample_probability: float = 0.25  # explore: draw afresh within the bounds instead
    hyperparameters: dict[str, HyperparameterRange] = field(default_factory=dict)
    init: str = "config"  # config: every member starts at the config's values | sample
    sync_timeout_s: float = 600.0  # sync: a sibling not at the ready point by then is dropped
    keep_ready: int = 2  # ready snapshots a member keeps for its siblings (>= 2 for sync)
    seed: int = 0  # the population's decisions (selection, explore) draw from this seed
    min_improvement: float = 0.0  # exploit only a source whose score beats this one's by more

    @classmethod
    def from_params(cls, params: dict[str, Any], where: str = "hooks.pbt") -> PBTConfig:
        """The checked params as a PBTConfig (ValueError / TypeError naming ``where``)."""
        params = check_params("pbt", params, PARAMS, f"{where}.params")
        ranges = {
            name: HyperparameterRange(float(r["low"]), float(r["high"]), bool(r.get("log", False)))
            for name, r in (params.get("hyperparameters") or DEFAULT_RANGES).items()
        }
        kw = {k: v for k, v in params.items() if k != "hyperparameters"}
        if "perturb_factors" in kw:
            kw["perturb_factors"] = tuple(float(f) for f in kw["perturb_factors"])
        return cls(**kw, hyperparameters=ranges)


#: PPO's usual ranges (CleanRL's defaults inside them): the rate log-uniform.
DEFAULT_RANGES: dict[str, dict[str, Any]] = {
    "lr": {"low": 1e-5, "high": 1e-3, "log": True},
    "entropy_coeff": {"low": 0.0, "high": 0.01},
    "clip_epsilon": {"low": 0.1, "high": 0.3},
}


class Ranges(ParamRule):
    """``{name: {low, high, log}}``: finite bounds, low < high, log ones above 0."""

    text = "a mapping of hyperparameter names to {low, high, log}"

    def check(self, value: Any, where: str, env: Any = None) -> None:
        if not isinstance(value, dict) or not value:
            raise TypeError(f"{where}={value!r} must be {self.text}")
        for name, r in value.items():
            at = f"{where}.{name}"
            if (
                not isinstance(r, dict)
                or set(r) - {"low", "high", "log"}
                or not {"low", "high"} <= set(r)
            ):
                raise TypeError(f"{at}={r!r} must be {{low: ..., high: ..., log: false}}")
            Number().check(r["low"], f"{at}.low")
            Number().check(r["high"], f"{at}.high")
            Flag().check(r.get("log", False), f"{at}.log")
            if not float(r["low"]) < float(r["high"]):
                raise ValueError(f"{at}: low={r['low']} must be below high={r['high']}")
            if r.get("log") and float(r["low"]) <= 0:
                raise ValueError(f"{at}.low={r['low']} must be above 0 with log: true")


class Factors(ParamRule):
    """A non-empty list of positive factors, none of them 1."""

    text = "a list of positive numbers other than 1 (e.g. [0.8, 1.2])"

    def check(self, value: Any, where: str, env: Any = None) -> None:
        if not isinstance(value, (list, tuple)) or not value:
            raise TypeError(f"{where}={value!r} must be {self.text}")
        for i, f in enumerate(value):
            Number(gt=0).check(f, f"{where}[{i}]")
            if float(f) == 1.0:
                raise ValueError(f"{where}[{i}]=1 must be {self.text}: 1 explores nothing")


PARAMS: dict[str, ParamRule] = {
    "population_size": Number(ge=2, integer=True),
    "ready_every": Number(gt=0, integer=True),
    "mode": Text(choices=MODES),
    "score": Text(),
    "quantile": Number(gt=0, le=0.5),
    "perturb_factors": Factors(),
    "resample_probability": Number(ge=0, le=1),
    "hyperparameters": OrNull(Ranges(), "PPO's lr, entropy_coeff and clip_epsilon"),
    "init": Text(choices=INITS),
    "sync_timeout_s": Number(gt=0),
    "keep_ready": Number(ge=2, integer=True),
    "seed": Number(ge=0, integer=True),
    "min_improvement": Number(ge=0),
}


def pbt_hooks(hooks: Any) -> list[tuple[str, Any]]:
    """``(name, params)`` of the configured hooks that are PBT (``func: pbt``)."""
    found = []
    for name, hook in (hooks or {}).items():
        func = hook.get("func") if isinstance(hook, dict) else getattr(hook, "func", None)
        if func == "pbt":
            params = hook.get("params") if isinstance(hook, dict) else getattr(hook, "params", None)
            found.append((str(name), params or {}))
    return found


#: Launchers that run a sweep's jobs one after another: a population needs them side by side.
SEQUENTIAL_LAUNCHERS = ("hydra._internal.core_plugins.basic_launcher.BasicLauncher",)


def check_pbt_sweep(launcher: dict[str, Any], n_jobs: int | None, hooks: Any) -> None:
    """A PBT sweep (a ``func: pbt`` hook) must run its members side by side, as many as
    ``population_size``: ValueError (one line) for a sequential launcher or a sweep of another size (``n_jobs``: the sweep's jobs, None where the sweeper picks them)."""
    found = pbt_hooks(hooks)
    if not found:
        return
    name, params = found[0]
    where = f"hooks.{name}.params"
    size = int(params.get("population_size", PBTConfig.population_size))
    target = str(launcher.get("_target_", ""))
    if target in SEQUENTIAL_LAUNCHERS or target.endswith("BasicLauncher"):
        raise ValueError(
            f"hydra/launcher=basic ({target}) runs a sweep's jobs one after another; a PBT "
            f"population ({where} in {SWEEP_FILE}) needs its {size} members side by side: use "
            "hydra/launcher=local or hydra/launcher=slurm"
        )
    if n_jobs is not None and n_jobs != size:
        raise ValueError(
            f"{where}.population_size={size} ({SWEEP_FILE}) but the sweep launches {n_jobs} "
            f"jobs: sweep the seed over exactly {size} values (seed=range(0,{size}))"
        )


#: How a PBT sweep names its job dirs: by job number (``rlexp.pbt.population.job_names``).
JOB_NUM = "${hydra.job.num}"


def check_pbt_subdir(subdir: Any, hooks: Any) -> None:
    """A PBT population's members are known by their dirs: ``hydra.sweep.subdir`` must name each
    job dir after its job number alone (``${hydra.job.num}``, or with a fixed prefix/suffix), one
    level below the sweep dir; ValueError (one line) otherwise."""
    if not pbt_hooks(hooks) or subdir is None:
        return
    text = str(subdir)
    if text.count(JOB_NUM) != 1 or "/" in text or "${" in text.replace(JOB_NUM, ""):
        raise ValueError(
            f"hydra.sweep.subdir={text}: a PBT population ({SWEEP_FILE}) knows its members by "
            f"their job dirs, named by job number: leave hydra.sweep.subdir at {JOB_NUM} (a fixed "
            f"prefix such as member_{JOB_NUM} is fine)"
        )


def log_uniform(rng: Any, low: float, high: float) -> float:
    """A draw between ``low`` and ``high``, uniform in log space."""
    return float(math.exp(rng.uniform(math.log(low), math.log(high))))


#: The launcher keys that say how many jobs run at once (joblib, submitit).
PARALLEL_KEYS = ("n_jobs", "array_parallelism")


def population_size(hooks: Any) -> int | None:
    """The PBT population's size, None when no hook is PBT."""
    found = pbt_hooks(hooks)
    if not found:
        return None
    return int(found[0][1].get("population_size", PBTConfig.population_size))


def widen_launcher(launcher: Any, size: int) -> list[str]:
    """Let ``launcher`` (Hydra's launcher node, edited in place) run ``size`` jobs at once; returns
    what changed, as ``key old -> new``."""
    changed = []
    for key in PARALLEL_KEYS:
        value = launcher.get(key) if key in launcher else None
        if isinstance(value, int) and 0 < value < size:
            launcher[key] = size
            changed.append(f"hydra.launcher.{key} {value} -> {size}")
    return changed
