"""The search space of an Optuna sweep: Hydra's sweep overrides as Optuna distributions.

The syntax is hydra-optuna-sweeper's, in ``hydra.sweeper.params`` or on the command line:

==============================================  ==================================================
``choice(0.1, 0.2)``, ``0.1,0.2``               ``CategoricalDistribution([0.1, 0.2])``
``range(1, 10)``, ``range(1, 10, 3)``           ``IntDistribution(1, 9)``, ``(1, 7, step=3)``: the
                                                values ``range`` lists, its end excluded as Hydra's
                                                grid does
``range(0.1, 0.5, 0.1)``                        ``FloatDistribution(0.1, 0.4, step=0.1)``
``shuffle(range(...))``                         a ``CategoricalDistribution`` of its values
``interval(0, 1)``                              ``FloatDistribution(0.0, 1.0)``
``tag(log, interval(1e-5, 1e-3))``              ``FloatDistribution(1e-5, 1e-3, log=True)``
``tag(int, interval(1, 64))``                   ``IntDistribution(1, 64)`` (``log`` may join ``int``)
anything else (``seed=3``, ``+sweep=x``)        a fixed override every trial gets, as written
==============================================  ==================================================

Hydra's parser reads ``interval``'s ends as floats, so ``int`` is the way to an integer interval.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from typing import Any

from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.override_parser.types import (
    ChoiceSweep,
    IntervalSweep,
    Override,
    RangeSweep,
    Transformer,
)
from optuna.distributions import (
    BaseDistribution,
    CategoricalDistribution,
    FloatDistribution,
    IntDistribution,
)

#: The tags ``tag(..., interval(...))`` may carry.
TAGS = ("log", "int")


class SearchSpaceError(ValueError):
    """A sweep override Optuna cannot sample; the message names the key and the fix."""


def distribution(override: Override) -> BaseDistribution | None:
    """The Optuna distribution of one parsed override; None for a plain (fixed) value."""
    if not override.is_sweep_override():
        return None
    key, value = override.get_key_element(), override.value()
    if isinstance(value, ChoiceSweep) or (isinstance(value, RangeSweep) and value.shuffle):
        return CategoricalDistribution(_values(override))
    if isinstance(value, RangeSweep):
        values = _values(override)
        if not values:
            raise SearchSpaceError(f"{override.input_line}: the range is empty")
        step = abs(value.step)
        low, high = min(values), max(values)
        if all(isinstance(v, int) for v in (value.start, value.stop, value.step)):
            return IntDistribution(int(low), int(high), step=int(step))
        return FloatDistribution(float(low), float(high), step=float(step))
    if isinstance(value, IntervalSweep):
        unknown = sorted(set(value.tags) - set(TAGS))
        if unknown:
            raise SearchSpaceError(
                f"{override.input_line}: unknown tag(s) {unknown}; an interval takes {list(TAGS)}"
            )
        log = "log" in value.tags
        if "int" in value.tags:
            return IntDistribution(int(value.start), int(value.end), log=log)
        return FloatDistribution(float(value.start), float(value.end), log=log)
    raise SearchSpaceError(
        f"{override.input_line}: {type(value).__name__} cannot be sampled by Optuna; write "
        f"{key}=choice(...), range(...) or interval(...)"
    )


def _values(override: Override) -> list[Any]:
    """A choice's or range's values as Optuna stores them (lists and dicts as override text)."""
    values = list(override.sweep_iterator(transformer=Transformer.encode))
    for v in values:
        if not isinstance(v, (str, int, float, bool)):
            raise SearchSpaceError(f"{override.input_line}: {v!r} cannot be a choice")
    return values


def search_space(lines: Sequence[str]) -> tuple[dict[str, BaseDistribution], dict[str, str]]:
    """(distributions by key, fixed overrides by key as written) of override ``lines``; a later
    line for the same key wins (the command line over ``hydra.sweeper.params``)."""
    from hydra.errors import HydraException

    parser = OverridesParser.create()
    dists: dict[str, BaseDistribution] = {}
    fixed: dict[str, str] = {}
    for line in lines:
        try:
            override = parser.parse_override(line)
        except HydraException as exc:
            raise SearchSpaceError(f"{line}: {str(exc).strip().splitlines()[0]}") from None
        key = override.get_key_element()
        dists.pop(key, None)
        fixed.pop(key, None)
        dist = distribution(override)
        if dist is None:
            fixed[key] = override.input_line or f"{key}={override.get_value_element_as_str()}"
        else:
            dists[key] = dist
    return dists, fixed


def from_dict(key: str, spec: Mapping[str, Any]) -> BaseDistribution:
    """One entry of the deprecated ``hydra.sweeper.search_space`` (``type``: int, float or
    categorical; ``low``, ``high``, ``log``, ``step``, ``choices``)."""
    kind = str(spec.get("type", ""))
    if kind not in ("int", "float", "categorical"):
        raise SearchSpaceError(
            f"hydra.sweeper.search_space.{key}.type={kind!r}: choose from int, float, categorical "
            f"(or write hydra.sweeper.params.{key}: interval(...), range(...) or choice(...))"
        )
    try:
        if kind == "categorical":
            return CategoricalDistribution(list(spec["choices"]))
        low, high, log, step = spec["low"], spec["high"], bool(spec.get("log")), spec.get("step")
        if kind == "int":
            return IntDistribution(int(low), int(high), log=log, step=int(step or 1))
        return FloatDistribution(float(low), float(high), log=log, step=step)
    except KeyError as exc:
        raise SearchSpaceError(f"hydra.sweeper.search_space.{key}: {exc} is missing") from None
    except (TypeError, ValueError) as exc:
        raise SearchSpaceError(f"hydra.sweeper.search_space.{key}: {exc}") from None


def grid_choices(key: str, dist: BaseDistribution) -> list[Any]:
    """The values a GridSampler walks for ``dist``: a choice's, or a stepped range's."""
    if isinstance(dist, CategoricalDistribution):
        return list(dist.choices)
    if isinstance(dist, IntDistribution):
        return list(range(dist.low, dist.high + 1, dist.step))
    if isinstance(dist, FloatDistribution) and dist.step is not None:
        n = round((dist.high - dist.low) / dist.step)
        return [dist.low + i * dist.step for i in range(n + 1)]
    raise SearchSpaceError(
        f"{key}: the grid sampler needs choice(...), range(...) or an int interval, not a "
        "continuous interval"
    )


def trial_overrides(
    params: Mapping[str, Any], order: Iterable[str], fixed: Mapping[str, str]
) -> tuple[str, ...]:
    """A trial's job overrides: its parameters in the search space's ``order`` (a trial re-run
    from the storage lists them as its first attempt did), then the fixed ones as written."""
    rank = {name: i for i, name in enumerate(order)}
    names = sorted(params, key=lambda n: rank.get(n, len(rank)))
    return (*(f"{n}={params[n]}" for n in names), *fixed.values())
