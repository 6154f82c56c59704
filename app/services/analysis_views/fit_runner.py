"""Fits run in the background, once per result, and the pages wait for them only briefly.

A page asks :meth:`FitRunner.get` for a result. Stored (app.services.analysis_views.fit_cache),
it is there at once. Otherwise the fit starts (or, when one for the same key is running, the
request joins it) and the request waits at most ``wait`` seconds: a fit done by then is shown;
a longer one gives :class:`Fitting`, which the page shows as "fitting… started N s ago" and
polls (htmx) until the result swaps in. Exports and the report wait for the result
(:meth:`FitRunner.result`): a download is expected to take the time its fits take, and it takes
it from no other request.

Where fits run. The statistics are CPU-bound Python and NumPy: in a thread of the server
they hold the GIL for most of their time and slow every other request of the process (measured
in docs/performance.md, "Staff pages at 100 participants"). So they run in worker processes
(``processes``, spawned at the first fit, each at a lower priority than the server, so a
study's robots keep theirs); the server keeps one thread per fit in flight, which
only waits for the process and then stores the result. ``processes=0`` runs fits in those
threads instead (tests inject a fitter there).

What a request waits for holds no snapshot: the caller's read transaction ends before the wait
(``db.commit()`` of a read session), so a long fit keeps no SQLite snapshot or PostgreSQL
connection.
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import importlib
import json
import logging
import multiprocessing
import os
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from datetime import timedelta
from typing import Any

from sqlalchemy.orm import Session

from analysis.dataset import StudyDataset
from app.db import Database
from app.services.analysis_views import fit_cache, fitted
from app.services.analysis_views.fit_cache import FitCache, FitKey
from app.tables import utcnow

log = logging.getLogger(__name__)

Fitter = Callable[[fitted.Kind, StudyDataset, Mapping[str, Any]], bytes]
"""Computes one result and returns it as stored bytes (:func:`fit_cache.dumps`)."""

ERASURE_MARGIN = timedelta(seconds=10)
"""A fit's data count as read this much before it started: an erasure that was committing
while they were read refuses the result (:meth:`FitCache.store`)."""

PRELOADED = ("app.services.analysis_views.fitted", "analysis.lmm", "analysis.ordinal")
"""Imported by each worker process as it starts, so the first fit does not wait for them."""


def run_fit(kind: fitted.Kind, dataset: StudyDataset, settings: Mapping[str, Any]) -> bytes:
    """The default fitter: :func:`fitted.fit`, pickled in the worker (only bytes come back)."""
    return fit_cache.dumps(fitted.fit(kind, dataset, settings))


def _prepare_worker() -> None:
    """A worker process's initialiser: below the server, so a fit never slows a robot; the
    statistics imported."""
    with contextlib.suppress(OSError):  # not permitted here: run as we are
        os.nice(10)
    for name in PRELOADED:
        importlib.import_module(name)


@dataclass(frozen=True)
class Fitting:
    """A fit still running: when it started (the runner's clock) and how long ago."""

    kind: fitted.Kind
    seconds: float

    @property
    def started(self) -> str:
        """``started 3 s ago`` / ``started just now``."""
        whole = int(self.seconds)
        return "started just now" if whole < 1 else f"started {whole} s ago"


@dataclass(frozen=True)
class StudyFits:
    """What one request asks of the runner about one dataset."""

    runner: FitRunner
    db: Session
    study_id: int
    dataset: StudyDataset
    started: dict[FitKey, _Running] = field(default_factory=dict)
    """The fits this request started: it gets their results even when they were not stored."""

    def key(self, kind: fitted.Kind, **settings: Any) -> FitKey:
        """The key of ``kind`` with ``settings`` (defaults filled in) for this dataset."""
        return FitKey.of(
            study_id=self.study_id,
            kind=kind,
            dataset=self.dataset,
            settings=fitted.settings_of(kind, **settings),
        )

    def get(self, kind: fitted.Kind, **settings: Any) -> Any:
        """The result, or :class:`Fitting` when its fit takes longer than the runner's
        ``wait``. A ``study`` result comes without its dataset (:func:`fitted.attached`)."""
        return self._get(self.key(kind, **settings), self.runner.wait)

    def result(self, kind: fitted.Kind, **settings: Any) -> Any:
        """The result, waiting for its fit however long it takes (exports, the report)."""
        return self._get(self.key(kind, **settings), None)

    def start(self, kind: fitted.Kind, **settings: Any) -> None:
        """Start the fit now unless it is stored or running (to wait for several at once:
        start each, then ask for each). Stored results are found by the ``get`` that follows."""
        key = self.key(kind, **settings)
        found, _ = self.runner.cache.lookup(self.db, key)
        if not found:
            self.started[key] = self.runner._start(key, self.dataset)

    def _get(self, key: FitKey, wait: float | None) -> Any:
        running = self.started.get(key)
        if running is None:
            found, value = self.runner.cache.lookup(self.db, key)
            if found:
                return value
            running = self.started[key] = self.runner._start(key, self.dataset)
        self.db.commit()  # end the read snapshot: the wait holds nothing of the database
        try:
            return running.future.result(timeout=wait)
        except cf.TimeoutError:
            return Fitting(key.kind, max(0.0, self.runner._clock() - running.started))


@dataclass
class _Running:
    future: cf.Future[Any]
    started: float


class FitRunner:
    """The fits of one server process."""

    def __init__(
        self,
        database: Database,
        *,
        processes: int,
        wait: float,
        fitter: Fitter = run_fit,
        clock: Callable[[], float] = time.monotonic,
        cache: FitCache | None = None,
    ) -> None:
        self.database = database
        self.cache = cache or FitCache()
        self.wait = wait
        self._processes = processes
        self._fitter = fitter
        self._clock = clock
        self._lock = threading.Lock()
        self._running: dict[FitKey, _Running] = {}
        self._pool: cf.ProcessPoolExecutor | None = None
        self._threads = cf.ThreadPoolExecutor(
            max_workers=max(4, 2 * processes), thread_name_prefix="trustlab-fit"
        )
        self.fits = 0
        """How many fits this runner started (for tests and benchmarks)."""

    def for_study(self, db: Session, *, study_id: int, dataset: StudyDataset) -> StudyFits:
        """The fits of ``dataset`` (the study's data as a request read them in ``db``)."""
        return StudyFits(self, db, study_id, dataset)

    def _start(self, key: FitKey, dataset: StudyDataset) -> _Running:
        with self._lock:
            running = self._running.get(key)
            if running is None:
                future: cf.Future[Any] = cf.Future()
                running = self._running[key] = _Running(future, self._clock())
                self.fits += 1
                since = utcnow() - ERASURE_MARGIN
                self._threads.submit(self._supervise, key, dataset, running, since)
            return running

    def _supervise(self, key: FitKey, dataset: StudyDataset, running: _Running, since: Any) -> None:
        """In a thread of the server: the fit (in a worker process, or here), then its storing."""
        try:
            begun = time.perf_counter()
            settings = json.loads(key.settings)
            if self._processes > 0:
                payload = (
                    self._process_pool().submit(self._fitter, key.kind, dataset, settings).result()
                )
            else:
                payload = self._fitter(key.kind, dataset, settings)
            seconds = time.perf_counter() - begun
            value = fit_cache.loads(payload)
            try:
                self.cache.store(self.database, key, payload, seconds=seconds, since=since)
            except Exception:  # the result still serves its requests; the next one fits again
                log.exception("a fitted %s analysis could not be stored", key.kind)
        except BaseException as exc:  # the waiting requests raise it; a later one fits again
            with self._lock:
                self._running.pop(key, None)
            running.future.set_exception(exc)
            return
        with self._lock:
            self._running.pop(key, None)
        running.future.set_result(value)

    def _process_pool(self) -> cf.ProcessPoolExecutor:
        with self._lock:
            if self._pool is None:
                # Spawned: a fresh interpreter, not a fork of a server that runs threads (a
                # child forked while another thread holds a lock, the BLAS's included, can hang
                # on it); the statistics are imported once per process, as it starts.
                self._pool = cf.ProcessPoolExecutor(
                    max_workers=self._processes,
                    mp_context=multiprocessing.get_context("spawn"),
                    initializer=_prepare_worker,
                )
            return self._pool

    def settle(self, timeout: float | None = None) -> None:
        """Wait until no fit is running (tests and benchmarks); a fit's error is not raised."""
        while True:
            with self._lock:
                running = list(self._running.values())
            if not running:
                return
            cf.wait([r.future for r in running], timeout=timeout)
            if timeout is not None and not all(r.future.done() for r in running):
                raise TimeoutError("fits still running")

    def close(self) -> None:
        """Stop: fits not started are dropped, running ones end with their process."""
        self._threads.shutdown(wait=False, cancel_futures=True)
        with self._lock:
            pool, self._pool = self._pool, None
        if pool is not None:
            pool.shutdown(wait=False, cancel_futures=True)
