"""Live learners kept between answers, one cache per database (app.db.Database).

Restoring a learner from its stored state on every answer is the hot path; a small cache keyed by
``(row id, version)`` skips it. An entry is *taken out* before the learner is mutated and put back
(under the new version) only after the transaction commits, so a rolled-back update can never
leave a learner in the cache that is ahead of the database.

The cache belongs to the database it mirrors, not to the process: row ids are only unique within
one database, and a process that opens a second one (the test suite, a server pointed at a restored
copy) must never be handed the other database's learner for the same id and version.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable
from typing import TYPE_CHECKING

from sqlalchemy.orm import Session

if TYPE_CHECKING:
    from models.learners.base import Learner

SESSION_KEY = "trustlab.learner_cache"
"""Where a database's sessions carry its cache (``Session.info``, set by app.db.Database)."""


class LearnerCache:
    """Live learners keyed by (row id, version)."""

    def __init__(self, capacity: int = 2048) -> None:
        self._entries: OrderedDict[tuple[int, int], Learner] = OrderedDict()
        self._capacity = capacity
        self._lock = threading.Lock()

    def take(self, row_id: int, version: int, rebuild: Callable[[], Learner]) -> Learner:
        """The learner of row ``row_id`` at ``version``, removed from the cache (``rebuild()``
        when absent)."""
        with self._lock:
            learner = self._entries.pop((row_id, version), None)
        return learner if learner is not None else rebuild()

    def forget(self, row_id: int) -> None:
        """Drop every version of a row that was deleted (its id may be given to a new row)."""
        with self._lock:
            for key in [key for key in self._entries if key[0] == row_id]:
                del self._entries[key]

    def put(self, row_id: int, version: int, learner: Learner) -> None:
        """Keep a learner known to match the committed row at ``version``."""
        with self._lock:
            self._entries[(row_id, version)] = learner
            self._entries.move_to_end((row_id, version))
            while len(self._entries) > self._capacity:
                self._entries.popitem(last=False)


def of(db: Session) -> LearnerCache:
    """The cache of the database ``db`` talks to; a session made outside app.db.Database gets
    one of its own (correct, only slower)."""
    cache = db.info.get(SESSION_KEY)
    if cache is None:
        cache = db.info[SESSION_KEY] = LearnerCache()
    assert isinstance(cache, LearnerCache)
    return cache
