"""One computation shared by every request it can serve without hiding a change from it.

Five experimenters watching the same live dashboard receive the same change event and ask for the
same data about 300 ms later (static/js/dashboard.js); computing it five times is wasted work that
competes with the robots' answers. :class:`FreshnessCache` hands them one result instead.

Each value is stored with the change count (``version``, e.g. app/events.py ``EventHub.version``)
and the clock, both read *before* its computation took its snapshot of the data. A request that
arrives at time *t* knowing ``v`` changes is given a value only if

- its version is at least ``v``: every change this process had counted when the request arrived
  is in the value (a reader never misses its own write, nor the change whose event it follows);
- it was started no earlier than *t − max_age*: what the count cannot know (another worker's
  change whose notification is still on its way) is hidden for at most ``max_age``. With
  ``max_age`` below the dashboard's refetch delay, the refetch that an answer's event triggers
  always sees that answer.

At most one computation per key runs at a time, and with ``min_interval`` one starts at most that
often. A request that finds one running (or waiting for its turn) waits for it: if it started
after the request's changes (or has yet to start), it shares it; otherwise it waits for the
*next* one, which it shares with everyone else who arrived meanwhile. So a study that changes many
times a second costs at most one computation per ``min_interval``, however many dashboards ask;
a request waits for at most ``min_interval`` and two computations. Waiting never weakens the
guarantee: a computation that starts later only includes more.

The caller's ``compute`` must take its snapshot after it is called (app/web/dashboard.py ends the
request's read transaction first).
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Hashable
from dataclasses import dataclass
from typing import Generic, TypeVar, cast

T = TypeVar("T")


def _unversioned() -> int:
    return 0


@dataclass
class _Computation(Generic[T]):
    """A value waiting for its turn, being computed (``done`` False) or computed, with what its
    snapshot includes (read when it starts)."""

    version: int = -1
    started: float = math.inf
    done: bool = False
    failed: bool = False
    value: T | None = None


class FreshnessCache(Generic[T]):
    """Values by key, shared while their version and age let them serve a request."""

    def __init__(
        self,
        max_age: float,
        clock: Callable[[], float] = time.monotonic,
        *,
        min_interval: float = 0.0,
    ) -> None:
        self.max_age = max_age
        self.min_interval = min_interval
        self._clock = clock
        self._latest: dict[Hashable, _Computation[T]] = {}
        self._running: dict[Hashable, _Computation[T]] = {}
        self._changed = threading.Condition()
        self.computed = 0
        """How many times a value was computed (for tests and benchmarks)."""

    def _serves(self, computation: _Computation[T], version: int, arrived: float) -> bool:
        return computation.version >= version and arrived - computation.started <= self.max_age

    def get(
        self,
        key: Hashable,
        compute: Callable[[], T],
        *,
        version: Callable[[], int] = _unversioned,
    ) -> T:
        """The value for ``key``: a shared one that can serve this request, or ``compute()``.

        ``version`` returns how many changes of the data this process has counted so far; it is
        read when the request arrives and again just before a computation starts.
        """
        with self._changed:
            wanted, arrived = version(), self._clock()
            while True:
                latest = self._latest.get(key)
                if latest is not None and self._serves(latest, wanted, arrived):
                    return cast(T, latest.value)
                running = self._running.get(key)
                if running is None:
                    break
                while not running.done:
                    self._changed.wait()
                if not running.failed and self._serves(running, wanted, arrived):
                    return cast(T, running.value)
                # It began before this request's changes (or failed): look again, joining the
                # next computation if another waiter has started it already.
            mine: _Computation[T] = _Computation()
            self._running[key] = mine  # from now on, whoever arrives joins this one
        try:
            with self._changed:
                turn = -math.inf if latest is None else latest.started + self.min_interval
                while (delay := turn - self._clock()) > 0:
                    self._changed.wait(delay)
                mine.version, mine.started = version(), self._clock()
            value = compute()
        except BaseException:
            with self._changed:
                mine.done = mine.failed = True
                del self._running[key]
                self._changed.notify_all()
            raise
        with self._changed:
            mine.value, mine.done = value, True
            del self._running[key]
            self._latest[key] = mine
            self.computed += 1
            self._changed.notify_all()
        return value
