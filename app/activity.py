"""Last-seen times of logins and devices, recorded off the request path.

Requests only note who was active (a dict update); a background thread writes the notes in one
small transaction every couple of seconds. A read request therefore never writes, and no request
needs a second database connection — under load that second connection is what exhausts the pool.
Idle-timeout checks read ``last_seen_at``, which may lag by one flush interval; harmless against
timeouts measured in minutes.
"""

from __future__ import annotations

import logging
import threading

from sqlalchemy import update
from sqlalchemy.exc import OperationalError

from app.db import Database
from app.tables import Device, LoginSession, utcnow

log = logging.getLogger(__name__)


class ActivityRecorder:
    """Collects activity notes and flushes them periodically from one thread."""

    def __init__(self, database: Database, interval: float = 2.0) -> None:
        self._database = database
        self._interval = interval
        self._lock = threading.Lock()
        self._logins: set[int] = set()
        self._devices: set[int] = set()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def note_login(self, login_id: int) -> None:
        """A signed-in browser was active."""
        with self._lock:
            self._logins.add(login_id)

    def note_device(self, device_id: int) -> None:
        """A robot client was active."""
        with self._lock:
            self._devices.add(device_id)

    def flush(self) -> None:
        """Write what was noted since the last flush (in one transaction)."""
        with self._lock:
            logins, self._logins = self._logins, set()
            devices, self._devices = self._devices, set()
        if not logins and not devices:
            return
        now = utcnow()
        try:
            with self._database.write_session() as db:
                if logins:
                    db.execute(
                        update(LoginSession)
                        .where(LoginSession.id.in_(logins))
                        .values(last_seen_at=now)
                    )
                if devices:
                    db.execute(
                        update(Device).where(Device.id.in_(devices)).values(last_seen_at=now)
                    )
                db.commit()
        except OperationalError as exc:  # the database is down: keep the notes for next time
            log.warning("could not record activity: %s", exc.orig)
            with self._lock:
                self._logins |= logins
                self._devices |= devices

    def start(self) -> None:
        """Flush every interval until stopped."""
        self._thread = threading.Thread(target=self._run, name="trustlab-activity", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(self._interval):
            self.flush()

    def stop(self) -> None:
        """Stop and flush one last time."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=10)
        self.flush()
