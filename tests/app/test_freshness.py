"""FreshnessCache: shared within the window, recomputed after it, one computation per burst."""

from __future__ import annotations

import threading
import time

from app.services.freshness import FreshnessCache


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
