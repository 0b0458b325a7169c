"""Name -> function registries for task terms, with errors that name the key and suggest a fix."""

from __future__ import annotations

import difflib
from collections.abc import Callable, Iterator
from typing import Any, Generic, TypeVar

T = TypeVar("T")


class Registry(Generic[T]):
    """A dict of named entries (term functions, action terms, tasks) of one kind."""

    def __init__(self, kind: str) -> None:
        self.kind = kind  # e.g. "reward func", used in error messages
        self._entries: dict[str, T] = {}

    def register(
        self, name: str | None = None, params: dict[str, Any] | None = None
    ) -> Callable[[T], T]:
        """Decorator: add the function or class under ``name`` (default: its ``__name__``).

        ``params``: a ``ParamRule`` (rlexp.config.native_task) per parameter, stored as ``PARAMS``;
        the env checks a term's params against them when it is built (a term without rules is
        checked against its signature only)."""

        def add(obj: T) -> T:
            key = name or obj.__name__  # type: ignore[attr-defined]
            if key in self._entries:
                raise ValueError(f"{self.kind} {key!r} is registered twice")
            if params is not None:
                obj.PARAMS = dict(params)  # type: ignore[attr-defined]
            self._entries[key] = obj
            return obj

        return add

    def get(self, name: str, where: str = "") -> T:
        """The entry called ``name``; ``where`` is the dotted config key, named in the error."""
        try:
            return self._entries[name]
        except KeyError:
            raise KeyError(unknown_name_message(self.kind, name, self._entries, where)) from None

    def names(self) -> list[str]:
        return sorted(self._entries)

    def __contains__(self, name: object) -> bool:
        return name in self._entries

    def __iter__(self) -> Iterator[str]:
        return iter(self.names())

    def __len__(self) -> int:
        return len(self._entries)


def unknown_name_message(kind: str, name: object, choices: object, where: str = "") -> str:
    """ "unknown reward func 'x' in rewards.y; choose from [...]; did you mean 'z'?"."""
    names = sorted(str(c) for c in choices)  # type: ignore[union-attr]
    msg = f"unknown {kind} {name!r}"
    if where:
        msg += f" in {where}"
    msg += f"; choose from {names}"
    close = difflib.get_close_matches(str(name), names, n=1)
    if close:
        msg += f"; did you mean {close[0]!r}?"
    return msg
