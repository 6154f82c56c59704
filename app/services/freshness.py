"""One computation shared by every request that arrives within a short freshness window.

Five experimenters watching the same live dashboard receive the same change event and ask for the
same data about 300 ms later (static/js/dashboard.js); computing it five times is wasted work that
competes with the robots' answers. :class:`FreshnessCache` hands them one result instead.

The guarantee callers rely on: a value returned at time *t* was computed from a snapshot taken no
earlier than *t − max_age* (the clock starts *before* computing). With ``max_age`` below the
dashboard's refetch delay, the refetch that an answer's event triggers always sees that answer.
Concurrent misses for one key wait for a single computation rather than each starting their own.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Hashable
from dataclasses import dataclass
from typing import Generic, TypeVar

T = TypeVar("T")


@dataclass(frozen=True)
class _Entry(Generic[T]):
    started: float
    value: T


class FreshnessCache(Generic[T]):
    """Values by key, reused for ``max_age`` seconds after their computation started."""

    def __init__(self, max_age: float, clock: Callable[[], float] = time.monotonic) -> None:
        self.max_age = max_age
        self._clock = clock
        self._entries: dict[Hashable, _Entry[T]] = {}
        self._flights: dict[Hashable, threading.Lock] = {}
        self._guard = threading.Lock()
        self.computed = 0
        """How many times a value was computed (for tests and benchmarks)."""

    def _fresh(self, key: Hashable) -> _Entry[T] | None:
        entry = self._entries.get(key)
        if entry is not None and self._clock() - entry.started <= self.max_age:
            return entry
        return None

    def get(self, key: Hashable, compute: Callable[[], T]) -> T:
        """The value for ``key``: a fresh shared one, or ``compute()`` once for all waiters."""
        with self._guard:
            entry = self._fresh(key)
            if entry is not None:
                return entry.value
            flight = self._flights.setdefault(key, threading.Lock())
        with flight:
            with self._guard:
                entry = self._fresh(key)  # computed by the request we waited for
            if entry is not None:
                return entry.value
            started = self._clock()
            value = compute()
            with self._guard:
                self._entries[key] = _Entry(started, value)
                self.computed += 1
            return value
