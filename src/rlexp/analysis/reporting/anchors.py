"""Published results that a sweep's results are shown next to (``rlexp report``'s results per env):
a small table of numbers, each with the source it was read from and exactly what it measures.

Only numbers copied from a source named here: an env a source has no number for has no entry
(its cell stays empty), never an estimate. The numbers were measured on other versions of the
tasks than rlexp's (Gymnasium MuJoCo v4 or gym's v3, rlexp runs v5) and with other
hyperparameters, so each cell names its env id: a reference point, not a like-for-like comparison.
docs/results.md lists the same table with its sources. One more source is rlexp's own: its
defaults' IQMs on the MuJoCo v5 suite (docs/results.md), shown next to a tuned suite's.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

#: Which of a sweep's two result metrics an anchor measures the same way.
TRAIN = "train"  # the mean return of the last 100 training episodes at the end of training
EVAL = "eval"  # the mean return of a final evaluation of the deterministic policy


@dataclass(frozen=True)
class Source:
    """Where a set of anchors comes from and what its numbers are."""

    key: str  # a column name in results.csv
    name: str  # the column header in report.md
    measures: str  # TRAIN or EVAL: the metric of ours it sits next to
    what: str  # one line: the metric, env version, seeds, steps, what the ± is
    where: str  # the file (repository, commit) or page the numbers were copied from
    #: whether the time to its number is a column (env steps and wall until our metric first
    #: reached it: the published references, not rlexp's own earlier results)
    time_to: bool = True
    short: str = ""  # its name in the time-to columns ("steps to CleanRL mean")


@dataclass(frozen=True)
class Anchor:
    """One published number: ``mean ± std`` on ``env_id`` (the id the source ran)."""

    source: str  # Source.key
    env_id: str  # e.g. "Hopper-v4"
    mean: float  # the number: a mean over seeds or episodes, or an IQM over seeds (``ci``)
    std: float  # NaN for an IQM
    ci: tuple[float, float] | None = None  # an IQM's 95% bootstrap interval (rlexp's own results)


CLEANRL = Source(
    key="cleanrl_ppo",
    name="CleanRL PPO",
    short="CleanRL",
    measures=TRAIN,
    what=(
        "`ppo_continuous_action.py`, MuJoCo v4, 1M env steps, 3 seeds: per seed the mean return "
        "of its last 100 training episodes (`charts/episodic_return`, openrlbenchmark's "
        "`metric_last_n_average_window=100`), then mean ± std over the seeds (numpy, ddof 0). "
        "No Ant at 1M steps (CleanRL's only PPO Ant-v4 number is from 8M steps)"
    ),
    where=(
        "vwxyzjn/cleanrl `docs/benchmark/ppo_continuous_action.md` (commit 35896b1, PR #424, "
        "tag pr-424), shown at https://docs.cleanrl.dev/rl-algorithms/ppo/#ppo_continuous_actionpy"
    ),
)
RL_ZOO = Source(
    key="rl_zoo_ppo",
    name="rl-zoo PPO",
    short="rl-zoo",
    measures=EVAL,
    what=(
        "Stable-Baselines3 PPO with rl-baselines3-zoo's hyperparameters (tuned per env; Ant-v3: "
        "SB3 defaults with normalisation; Swimmer-v3: the same with gamma 0.9999), gym MuJoCo v3, 1M env steps, one trained agent (one "
        "seed): the mean return of its deterministic policy over ~150k evaluation steps (150-175 "
        "episodes), ± the std over those episodes, not over seeds"
    ),
    where=(
        "DLR-RM/rl-baselines3-zoo `benchmark.md` (added in commit 8e2b0c0, PR #183), "
        "https://github.com/DLR-RM/rl-baselines3-zoo/blob/master/benchmark.md"
    ),
)
TIANSHOU = Source(
    key="tianshou_ppo",
    name="Tianshou PPO",
    short="Tianshou",
    measures=EVAL,
    what=(
        "Tianshou's `examples/mujoco/mujoco_ppo.py` (64x64 tanh, 10 envs, 2048 steps per collect, "
        "lr 3e-4 decayed, advantages recomputed each epoch), gym 0.17.3 MuJoCo v3 (Reacher and "
        "the pendulums v2), 10 seeds: the maximum over the first 1M env steps of the mean test "
        "return (10 test episodes), ± the std over the seeds. A maximum over the curve, where the "
        "others are final values: the most favourable of these numbers"
    ),
    where=(
        'thu-ml/tianshou `examples/mujoco/README.md`, section PPO, table "Tianshou (1M)" (read '
        "at commit 1da9b86)"
    ),
    time_to=False,
)
_DEFAULTS_WHAT = (
    "rlexp's default PPO (conf/config.yaml: 1 env x 2048 steps, 10 epochs of 64, 64x64 tanh, "
    "lr 3e-4 annealed, observation and reward normalisation; `+sweep=mujoco_1m`), Gymnasium "
    "MuJoCo v5, 1M env steps, 5 seeds: the IQM [95% bootstrap CI] over seeds of {metric}, as "
    "this table computes it (rounded to integers as docs/results.md prints them)"
)
_DEFAULTS_WHERE = (
    'docs/results.md, "Results (1M steps, 5 seeds)" (rlexp commit ebe04ef, 2026-11-23, the 2-core '
    "Xeon dev machine)"
)


def _defaults(key: str, measures: str, metric: str) -> Source:
    """The defaults' own 5-seed IQM of ``metric``, as docs/results.md prints it."""
    what = _DEFAULTS_WHAT.format(metric=metric)
    return Source(key, "rlexp defaults", measures, what, _DEFAULTS_WHERE, time_to=False)


DEFAULTS_TRAIN = _defaults(
    "rlexp_defaults_train", TRAIN, "the final train return (last 100 training episodes)"
)
DEFAULTS_EVAL = _defaults(
    "rlexp_defaults_eval", EVAL, "the final deterministic eval return (10 episodes)"
)

SOURCES = (CLEANRL, RL_ZOO, TIANSHOU, DEFAULTS_TRAIN, DEFAULTS_EVAL)
NAN = float("nan")  # the std of an IQM anchor

ANCHORS = (
    Anchor(CLEANRL.key, "Hopper-v4", 2382.86, 271.74),
    Anchor(CLEANRL.key, "Walker2d-v4", 2287.95, 571.78),
    Anchor(CLEANRL.key, "HalfCheetah-v4", 1442.64, 46.03),
    Anchor(CLEANRL.key, "InvertedPendulum-v4", 963.09, 22.20),
    Anchor(CLEANRL.key, "Humanoid-v4", 716.11, 49.08),
    Anchor(RL_ZOO.key, "Hopper-v3", 2410.435, 10.026),
    Anchor(RL_ZOO.key, "Walker2d-v3", 3478.798, 821.708),
    Anchor(RL_ZOO.key, "HalfCheetah-v3", 5819.099, 663.530),
    Anchor(RL_ZOO.key, "Ant-v3", 1327.158, 451.577),
    # benchmark.md's row `ppo Swimmer-v3 281.561 9.671 1M` (150 episodes; the Swimmer-v3 entry
    # of that commit: gamma 0.9999 and SB3's defaults, before the zoo tuned it in PR #335)
    Anchor(RL_ZOO.key, "Swimmer-v3", 281.561, 9.671),
    # Tianshou's PPO table "Tianshou (1M)": Ant, HalfCheetah, Hopper, Walker2d, Swimmer, Humanoid
    # are gym's v3, Reacher and the pendulums v2 (the README's footnote 1)
    Anchor(TIANSHOU.key, "Ant-v3", 3258.4, 1079.3),
    Anchor(TIANSHOU.key, "HalfCheetah-v3", 5783.9, 1244.0),
    Anchor(TIANSHOU.key, "Hopper-v3", 2609.3, 700.8),
    Anchor(TIANSHOU.key, "Walker2d-v3", 3588.5, 756.6),
    Anchor(TIANSHOU.key, "Swimmer-v3", 66.7, 99.1),
    Anchor(TIANSHOU.key, "Humanoid-v3", 787.1, 193.5),
    Anchor(TIANSHOU.key, "Reacher-v2", -4.1, 0.3),
    Anchor(TIANSHOU.key, "InvertedPendulum-v2", 1000.0, 0.0),
    Anchor(TIANSHOU.key, "InvertedDoublePendulum-v2", 9231.3, 270.4),
    # rlexp's defaults, docs/results.md's table: IQM [95% CI] of the train and the eval return
    Anchor(DEFAULTS_TRAIN.key, "Hopper-v5", 2504, NAN, (2401, 2629)),
    Anchor(DEFAULTS_TRAIN.key, "Walker2d-v5", 3555, NAN, (2302, 3978)),
    Anchor(DEFAULTS_TRAIN.key, "HalfCheetah-v5", 1711, NAN, (1680, 1765)),
    Anchor(DEFAULTS_TRAIN.key, "Ant-v5", 652, NAN, (455, 785)),
    Anchor(DEFAULTS_EVAL.key, "Hopper-v5", 3303, NAN, (3090, 3376)),
    Anchor(DEFAULTS_EVAL.key, "Walker2d-v5", 4277, NAN, (3146, 4808)),
    Anchor(DEFAULTS_EVAL.key, "HalfCheetah-v5", 1829, NAN, (1769, 1883)),
    Anchor(DEFAULTS_EVAL.key, "Ant-v5", 1112, NAN, (649, 1476)),
)


def task_of(env_id: str) -> str:
    """The task an env id names, without its version: ``Hopper-v5`` -> ``Hopper``."""
    return re.sub(r"-v\d+$", "", env_id)


def anchors_for(env_id: str | None) -> dict[str, Anchor]:
    """The anchors of the task ``env_id`` names (any version), by source key; {} when none."""
    if not env_id:
        return {}
    return {a.source: a for a in ANCHORS if task_of(a.env_id) == task_of(env_id)}
