"""Live events: published inside a transaction, delivered only if it commits, to every worker.

Services call :func:`publish` with the request's database session. The event waits on the
session until the transaction ends:

- PostgreSQL: just before COMMIT the events become ``pg_notify('trustlab', …)`` calls in the same
  transaction, so PostgreSQL delivers them exactly when (and only if) the data is visible, to every
  worker process LISTENing, including this one. One path, whatever the number of workers.
- SQLite (one process by design): after COMMIT the events go straight to this process's hub.

A rolled-back transaction drops its events. Each process has one :class:`EventHub` that fans events
out to asyncio subscribers (robot WebSockets, dashboard streams) by topic, e.g. ``station:3``,
``study:1``, ``participant:42``. Events are small hints ("something changed, here is what"); a
subscriber that falls behind is told to resynchronise rather than fed an unbounded queue.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import json
import logging
import secrets
import threading
import time
from collections import Counter, deque
from collections.abc import AsyncIterator, Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

from sqlalchemy import event
from sqlalchemy.engine import make_url
from sqlalchemy.orm import Session, sessionmaker

from app.sql import Cursor, Statement

log = logging.getLogger(__name__)

CHANNEL = "trustlab"
PENDING_KEY = "trustlab_pending_events"
NOTIFIED_KEY = "trustlab_notified_topics"
MAX_PAYLOAD_BYTES = 7900  # PostgreSQL refuses NOTIFY payloads of 8000 bytes or more
QUEUE_SIZE = 256
MAX_ECHOES = 100_000
RECENT_SECONDS = 60.0
RECENT_EVENTS = 4096
"""How long, and how many, of its latest events a hub remembers for :meth:`EventHub.since`."""


@dataclass(frozen=True)
class Event:
    """Something that changed: on which topic, what kind of change, and its small payload.

    ``id`` is set on the events a process NOTIFYs (PostgreSQL), so that it recognises its own
    when they come back through LISTEN: it counted them at commit already (:class:`EventHub`)."""

    topic: str
    type: str
    data: dict[str, Any] = field(default_factory=dict)
    id: str = field(default="", compare=False)

    def to_json(self) -> str:
        """The wire form (also the NOTIFY payload)."""
        value: dict[str, Any] = {"topic": self.topic, "type": self.type, "data": self.data}
        if self.id:
            value["id"] = self.id
        return json.dumps(value, default=str)

    @classmethod
    def from_json(cls, raw: str) -> Event:
        """Parse the wire form; ValueError when ``raw`` is not one."""
        try:
            value = json.loads(raw)
            topic, kind, data = value["topic"], value["type"], value.get("data", {})
            event_id = value.get("id", "")
        except (ValueError, KeyError, TypeError, AttributeError) as exc:
            raise ValueError(f"not a trustlab event: {raw[:80]!r}") from exc
        texts = (topic, kind, event_id)
        if not all(isinstance(text, str) for text in texts) or not isinstance(data, dict):
            raise ValueError(f"not a trustlab event: {raw[:80]!r}")
        return cls(topic=topic, type=kind, data=data, id=event_id)


RESYNC = Event(topic="*", type="resync")
"""Sent to a subscriber that missed events: it should fetch the current state again."""


def publish(db: Session, *, topics: Iterable[str], type: str, **data: Any) -> None:
    """Queue an event on ``db``'s transaction for each topic; delivered only on commit."""
    if db.get_transaction() is None:
        db.connection()  # a transaction must exist, so that its rollback discards the events
    pending: list[Event] = db.info.setdefault(PENDING_KEY, [])
    for topic in topics:
        pending.append(Event(topic=topic, type=type, data=data))


class Subscription:
    """A subscriber's queue, living on the event loop it subscribed from."""

    def __init__(self, topics: frozenset[str]) -> None:
        self.topics = topics
        self.loop = asyncio.get_running_loop()
        self.queue: asyncio.Queue[Event] = asyncio.Queue(maxsize=QUEUE_SIZE)
        self.lagged = False

    def wants(self, event: Event) -> bool:
        """Whether this subscriber listens to the event's topic (resyncs go to everyone)."""
        return event.topic == "*" or event.topic in self.topics

    def offer(self, event: Event) -> None:
        """Called on the subscriber's loop: enqueue, or flag it to resynchronise."""
        if self.lagged:
            return
        try:
            self.queue.put_nowait(event)
        except asyncio.QueueFull:
            self.lagged = True
            with contextlib.suppress(asyncio.QueueEmpty):
                while True:
                    self.queue.get_nowait()
            self.queue.put_nowait(RESYNC)

    async def next(self) -> Event:
        """The next event (a :data:`RESYNC` after falling behind)."""
        event = await self.queue.get()
        if event is RESYNC:
            self.lagged = False
        return event

    def drain(self) -> list[Event]:
        """The events already queued, without waiting (a :data:`RESYNC` among them clears lag)."""
        events = []
        with contextlib.suppress(asyncio.QueueEmpty):
            while True:
                events.append(self.queue.get_nowait())
        if RESYNC in events:
            self.lagged = False
        return events


class EventHub:
    """One process's fan-out of events to its asyncio subscribers, whatever loop they run on."""

    def __init__(self, clock: Callable[[], float] = time.time) -> None:
        self._subscriptions: set[Subscription] = set()
        self._lock = threading.Lock()
        self._versions: Counter[str] = Counter()
        self._echoes: set[str] = set()
        """Ids of events this process committed and counted, whose NOTIFY has not come back."""
        self._clock = clock
        self.heard_from = clock()
        """Since when this hub has heard every event: its start."""
        self._recent: deque[tuple[float, Event]] = deque(maxlen=RECENT_EVENTS)
        """The latest events delivered, with when they arrived (wall clock: a page rendered by
        one worker opens its stream on another, and both read the same machine's clock)."""

    def since(self, topics: Iterable[str], moment: float) -> list[Event] | None:
        """The events of ``topics`` (and resyncs) that arrived at ``moment`` or later, or
        ``None`` when this hub cannot tell (it started later, or has forgotten that far back).

        A page renders what it read after ``moment`` and then opens its stream: an event that
        arrived in between is one the page may not show and the stream would never send.
        Arrival is never before commit, so an event committed after the page's read began
        is found; one committed just before may be found too (a needless refresh, no miss)."""
        wanted = frozenset(topics)
        with self._lock:
            now = self._clock()
            while self._recent and self._recent[0][0] < now - RECENT_SECONDS:
                self._recent.popleft()
            known_from = max(self.heard_from, now - RECENT_SECONDS)
            if len(self._recent) == self._recent.maxlen:
                known_from = max(known_from, self._recent[0][0])
            if moment < known_from:
                return None
            return [
                event
                for arrived, event in self._recent
                if arrived >= moment and (event.topic == "*" or event.topic in wanted)
            ]

    def version(self, topic: str) -> int:
        """How many changes of ``topic`` (or resyncs) this process has seen: equal numbers mean
        nothing this process knows of has changed, so data computed in between is still current."""
        with self._lock:
            return self._versions[topic] + self._versions["*"]

    def expect_echoes(self, notified: Iterable[tuple[str, str]]) -> None:
        """Before a commit: these (topic, event id)s are NOTIFYed by this process, so when they
        come back through LISTEN they are not counted again (:meth:`note_changes` counts them).
        Said before the commit, since the echo may arrive before the committing thread goes on
        (a second count made every cache that shares by version compute twice)."""
        with self._lock:
            if len(self._echoes) > MAX_ECHOES:  # rolled back, or a listener that lost them:
                self._echoes.clear()  # counting twice is safe
            self._echoes.update(event_id for _, event_id in notified)

    def note_changes(self, notified: Iterable[tuple[str, str]]) -> None:
        """After a commit: count this process's own changes at once, so a reader sees them
        (their events arrive later, through LISTEN, and are then not counted again)."""
        with self._lock:
            self._versions.update(topic for topic, _ in notified)

    def open(self, topics: Iterable[str]) -> Subscription:
        """Start receiving events of these topics (call from the loop that will read them)."""
        subscription = Subscription(frozenset(topics))
        with self._lock:
            self._subscriptions.add(subscription)
        return subscription

    def close(self, subscription: Subscription) -> None:
        """Stop a subscription (idempotent)."""
        with self._lock:
            self._subscriptions.discard(subscription)

    @contextlib.asynccontextmanager
    async def subscribe(self, topics: Iterable[str]) -> AsyncIterator[Subscription]:
        """Receive events of these topics while the context is open."""
        subscription = self.open(topics)
        try:
            yield subscription
        finally:
            self.close(subscription)

    def deliver(self, events: Iterable[Event]) -> None:
        """Hand events to matching subscribers; safe to call from any thread."""
        batch = list(events)
        if not batch:
            return
        with self._lock:
            arrived = self._clock()
            for item in batch:
                self._recent.append((arrived, item))
                if item.id in self._echoes:
                    self._echoes.discard(item.id)  # counted when this process committed it
                else:
                    self._versions[item.topic] += 1
            subscriptions = list(self._subscriptions)
        for subscription in subscriptions:
            for item in batch:
                if subscription.wants(item):
                    with contextlib.suppress(RuntimeError):  # its loop has closed
                        subscription.loop.call_soon_threadsafe(subscription.offer, item)

    @property
    def subscriber_count(self) -> int:
        """How many subscriptions are open (for tests and the health page)."""
        with self._lock:
            return len(self._subscriptions)


_NOTIFY_ALL = Statement(
    "SELECT pg_notify(:c, payload) FROM json_array_elements_text(CAST(:payloads AS json)) payload"
)
"""Every event of a transaction in one statement (one round trip, however many events), in order:
an answer that ends a run and a session has six. The payloads travel as one JSON array of
strings: as a text-array parameter the driver escaped each payload with a regular expression,
a measurable share of an answer's CPU (docs/performance.md)."""


def _notify_payload(pending: Event) -> str:
    """The NOTIFY payload of an event; too large ones say only that they were truncated."""
    payload = pending.to_json()
    if len(payload.encode()) > MAX_PAYLOAD_BYTES:
        payload = Event(pending.topic, pending.type, {"truncated": True}, pending.id).to_json()
    return payload


def send_pending(db: Session) -> None:
    """PostgreSQL: send the transaction's pending events now, as ``pg_notify`` calls in it, so
    they can travel with the transaction's other statements (a write batch, app.sql); PostgreSQL
    still delivers them only when, and if, the transaction commits. Commit sends whatever is left
    pending; on SQLite events wait for the commit in any case."""
    if db.get_bind().dialect.name != "postgresql":
        return
    pending_events = [
        dataclasses.replace(pending, id=secrets.token_hex(8))
        for pending in db.info.pop(PENDING_KEY, [])
    ]
    if not pending_events:
        return
    db.info.setdefault(NOTIFIED_KEY, []).extend((e.topic, e.id) for e in pending_events)
    payloads = [_notify_payload(pending) for pending in pending_events]
    Cursor.of(db).send(_NOTIFY_ALL, {"c": CHANNEL, "payloads": json.dumps(payloads)})


def attach_publishing(factory: sessionmaker[Session], hub: EventHub, *, postgres: bool) -> None:
    """Make sessions from ``factory`` deliver their pending events on commit."""

    def _drop(session: Session, *_: Any) -> None:
        session.info.pop(PENDING_KEY, None)
        session.info.pop(NOTIFIED_KEY, None)

    if postgres:

        @event.listens_for(factory, "before_commit")
        def _notify(session: Session) -> None:
            send_pending(session)
            hub.expect_echoes(session.info.get(NOTIFIED_KEY, []))

        @event.listens_for(factory, "after_commit")
        def _count(session: Session) -> None:
            # This process's own writes count at once; their events come back through LISTEN.
            hub.note_changes(session.info.pop(NOTIFIED_KEY, []))

    else:

        @event.listens_for(factory, "after_commit")
        def _deliver(session: Session) -> None:
            hub.deliver(session.info.pop(PENDING_KEY, []))

    event.listen(factory, "after_rollback", _drop)
    event.listen(factory, "after_soft_rollback", _drop)


class PostgresListener:
    """A worker thread that LISTENs on PostgreSQL and feeds this process's hub, reconnecting."""

    def __init__(self, database_url: str, hub: EventHub) -> None:
        url = make_url(database_url).set(drivername="postgresql")
        self._conninfo = url.render_as_string(hide_password=False)
        self._hub = hub
        self._stop = threading.Event()
        self._ready = threading.Event()
        self._thread = threading.Thread(target=self._run, name="trustlab-listen", daemon=True)

    def start(self, timeout: float = 5.0) -> None:
        """Start listening; waits briefly so that events of the next request are not missed."""
        self._thread.start()
        self._ready.wait(timeout)

    def stop(self) -> None:
        """Stop and join the thread."""
        self._stop.set()
        self._thread.join(timeout=5)

    def _deliver(self, payload: str) -> None:
        # Anyone connected to the database may NOTIFY this channel: a payload that is not an
        # event is logged and dropped, and the listener goes on (it used to die with it).
        try:
            received = Event.from_json(payload)
        except ValueError as exc:
            log.warning("event listener ignored a notification on %r: %s", CHANNEL, exc)
            return
        self._hub.deliver([received])

    def _run(self) -> None:
        import psycopg  # here: a process on SQLite (a command, most labs) never loads the driver

        delay = 0.5
        while not self._stop.is_set():
            try:
                with psycopg.connect(self._conninfo, autocommit=True, connect_timeout=5) as conn:
                    conn.execute(f"LISTEN {CHANNEL}")
                    # anything may have happened while disconnected; said before start() returns,
                    # so a computation made after the start is not counted stale by this resync
                    self._hub.deliver([RESYNC])
                    self._ready.set()
                    delay = 0.5
                    while not self._stop.is_set():
                        for notice in conn.notifies(timeout=0.5):
                            self._deliver(notice.payload)
            except psycopg.Error as exc:
                log.warning("event listener lost PostgreSQL (%s); retrying in %.1fs", exc, delay)
                self._stop.wait(delay)
                delay = min(delay * 2, 10.0)
