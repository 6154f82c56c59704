"""FreshnessCache: shared within the window and while no change is newer, recomputed otherwise,
one computation at a time however many requests ask."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import pytest

from app.services.analysis_views.freshness import FreshnessCache


class FakeClock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_values_are_shared_within_the_window_and_recomputed_after() -> None:
    clock = FakeClock()
    cache: FreshnessCache[int] = FreshnessCache(max_age=0.25, clock=clock)
    calls = iter(range(100))
    assert cache.get("a", lambda: next(calls)) == 0
    clock.now += 0.25
    assert cache.get("a", lambda: next(calls)) == 0  # still within the window
    assert cache.get("b", lambda: next(calls)) == 1  # another key computes its own
    clock.now += 0.01
    assert cache.get("a", lambda: next(calls)) == 2  # 0.26 s after the computation started
    assert cache.computed == 3


def test_the_window_starts_before_computing() -> None:
    clock = FakeClock()
    cache: FreshnessCache[str] = FreshnessCache(max_age=0.25, clock=clock)

    def slow() -> str:
        clock.now += 0.2  # the snapshot is taken at the start, the result arrives later
        return "v1"

    cache.get("a", slow)
    clock.now += 0.06  # 0.26 s after the snapshot: too old, although computed 0.06 s ago
    assert cache.get("a", lambda: "v2") == "v2"


def test_a_burst_of_concurrent_requests_computes_once() -> None:
    cache: FreshnessCache[int] = FreshnessCache(max_age=5.0)
    started = threading.Barrier(8)
    results: list[int] = []

    def compute() -> int:
        time.sleep(0.2)
        return 42

    def request() -> None:
        started.wait()
        results.append(cache.get("study", compute))

    threads = [threading.Thread(target=request) for _ in range(8)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert results == [42] * 8
    assert cache.computed == 1


def test_a_change_counted_before_the_request_is_never_hidden() -> None:
    clock = FakeClock()
    cache: FreshnessCache[int] = FreshnessCache(max_age=0.25, clock=clock)
    changes = 0
    calls = iter(range(100))
    assert cache.get("a", lambda: next(calls), version=lambda: changes) == 0
    assert cache.get("a", lambda: next(calls), version=lambda: changes) == 0  # nothing new
    changes += 1  # e.g. the reader's own write, or the answer whose event it follows
    assert cache.get("a", lambda: next(calls), version=lambda: changes) == 1
    assert cache.get("a", lambda: next(calls), version=lambda: changes) == 1
    assert cache.computed == 2


def _in_threads(count: int, target: Callable[[], None]) -> list[threading.Thread]:
    threads = [threading.Thread(target=target) for _ in range(count)]
    for thread in threads:
        thread.start()
    return threads


def test_requests_behind_a_running_computation_share_the_next_one() -> None:
    """A computation that began before a request's change cannot serve it; everyone who arrives
    while it runs waits for it and then shares a single next computation."""
    cache: FreshnessCache[int] = FreshnessCache(max_age=5.0)
    changes = 0
    arrived: set[int] = set()
    running, release = threading.Event(), threading.Event()
    computations = iter(range(100))

    def version() -> int:
        arrived.add(threading.get_ident())
        return changes

    def compute() -> int:
        value = next(computations)
        if value == 0:
            running.set()
            release.wait(5)
        return value

    first: list[int] = []
    threads = _in_threads(1, lambda: first.append(cache.get("s", compute, version=version)))
    running.wait(5)
    changes += 1  # committed while the first computation runs: it may not include it
    later: list[int] = []
    threads += _in_threads(4, lambda: later.append(cache.get("s", compute, version=version)))
    while len(arrived) < 5:  # all four have read the count and are waiting
        time.sleep(0.001)
    release.set()
    for thread in threads:
        thread.join()
    assert first == [0]
    assert later == [1] * 4
    assert cache.computed == 2


def test_requests_join_a_computation_that_began_after_their_changes() -> None:
    cache: FreshnessCache[str] = FreshnessCache(max_age=5.0)
    arrived: set[int] = set()
    release = threading.Event()

    def version() -> int:
        arrived.add(threading.get_ident())
        return 7

    def compute() -> str:
        release.wait(5)
        return "v"

    results: list[str] = []
    threads = _in_threads(5, lambda: results.append(cache.get("s", compute, version=version)))
    while len(arrived) < 5:
        time.sleep(0.001)
    release.set()
    for thread in threads:
        thread.join()
    assert results == ["v"] * 5
    assert cache.computed == 1


def test_a_failed_computation_is_not_shared() -> None:
    cache: FreshnessCache[int] = FreshnessCache(max_age=5.0)

    def broken() -> int:
        raise RuntimeError("database unavailable")

    with pytest.raises(RuntimeError):
        cache.get("s", broken)
    assert cache.get("s", lambda: 3) == 3
    assert cache.computed == 1


def test_computations_start_at_most_once_per_min_interval_and_waiters_share_them() -> None:
    read = threading.local()

    def clock() -> float:
        """The real clock, remembering per thread what it last said: the cache stamps a
        computation's start right before computing, so ``compute`` sees the cache's own stamp
        (a second reading of the clock could be later and make the interval look shorter)."""
        read.now = time.monotonic()
        return float(read.now)

    cache: FreshnessCache[int] = FreshnessCache(max_age=5.0, min_interval=0.1, clock=clock)
    changes = 0
    starts: list[float] = []

    def compute() -> int:
        starts.append(read.now)
        return len(starts)

    assert cache.get("s", compute, version=lambda: changes) == 1
    changes += 1  # a newer computation is needed, but not before its turn
    results: list[int] = []
    threads = _in_threads(4, lambda: results.append(cache.get("s", compute, version=lambda: 1)))
    for thread in threads:
        thread.join()
    assert results == [2] * 4
    assert cache.computed == 2
    assert starts[1] - starts[0] >= 0.1
    assert cache.get("s", compute, version=lambda: changes) == 2  # nothing newer: no wait
