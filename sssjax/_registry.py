"""Named choices (profiles, strategies, transports, losses, solvers, weightings): one
`Registry` per choice, one error message for a name that is not in it.

An entry is any object, or a lazy reference `"package.module:attribute"` that is imported
the first time the entry is used: a registry can then sit below the modules that implement
its entries (the scene loader checks a transport's name without importing the transport).
"""

from __future__ import annotations

import difflib
import importlib
from collections.abc import Iterator, Mapping
from typing import Any

__all__ = ["Registry", "did_you_mean"]


def did_you_mean(word: str, options) -> str:
    """`"; did you mean 'x'?"` for the closest of `options` to `word`, or `""`."""
    close = difflib.get_close_matches(str(word), list(options), n=1)
    return f"; did you mean '{close[0]}'?" if close else ""


class Registry:
    """The entries of one choice by name, in registration order.

    **Arguments:** `what`, the choice's name in messages (`"profile"`); `entries`, a mapping
    of names to objects or lazy references `"module:attribute"`.

    `registry[name]` (or `get_entry`) raises `ValueError` with `message(name)` for an
    unknown name; `check(name)` validates a name without resolving its entry.
    """

    def __init__(self, what: str, entries: Mapping[str, Any] | None = None):
        self.what = what
        self._entries: dict[str, Any] = dict(entries or {})

    def message(self, name) -> str:
        """The one-line complaint about `name`: `unknown profile 'pdb'; did you mean 'pbd'?
        (known: dipole, better_dipole, pbd)`."""
        hint = did_you_mean(str(name), self._entries)
        return f"unknown {self.what} {name!r}{hint} (known: {', '.join(self._entries)})"

    def check(self, name, error: type[Exception] = ValueError) -> str:
        """`name` if it is registered, else `error(message(name))`."""
        if not isinstance(name, str) or name not in self._entries:
            raise error(self.message(name))
        return name

    def register(self, name: str, entry: Any) -> Any:
        """Add (or replace) an entry; returns it."""
        self._entries[name] = entry
        return entry

    def get_entry(self, name, error: type[Exception] = ValueError) -> Any:
        """The entry of `name`, imported if it is a lazy reference."""
        entry = self._entries[self.check(name, error)]
        if isinstance(entry, str) and ":" in entry:
            module, _, attr = entry.partition(":")
            try:
                entry = getattr(importlib.import_module(module), attr)
            except ModuleNotFoundError as e:
                if e.name != module:
                    raise
                raise error(f"{self.what} {name!r} is not available yet ({module})") from None
            self._entries[name] = entry
        return entry

    def __getitem__(self, name) -> Any:
        return self.get_entry(name)

    def __contains__(self, name) -> bool:
        return isinstance(name, str) and name in self._entries

    @property
    def names(self) -> tuple[str, ...]:
        """The registered names, in order."""
        return tuple(self._entries)

    def __iter__(self) -> Iterator[str]:
        return iter(self._entries)

    def __len__(self) -> int:
        return len(self._entries)

    def __repr__(self) -> str:
        return f"Registry({self.what!r}, {list(self._entries)})"
