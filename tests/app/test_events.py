"""Events are delivered after commit only, to matching subscribers, without unbounded queues."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable

import pytest
from sqlalchemy import text

from app import events
from app.db import Database
from app.events import RESYNC, Event, EventHub
from app.services.privacy.sites import Scope


def _deliver(
    database: Database, topic: str, publish: Callable[[], None], count: int
) -> list[Event]:
    """Subscribe to ``topic`` (through a LISTEN connection on PostgreSQL), run ``publish`` in a
    thread as a request would, and collect the first ``count`` events (resyncs skipped)."""

    async def scenario() -> list[Event]:
        listener = None
        if not database.is_sqlite:
            listener = events.PostgresListener(database.url, database.hub)
            listener.start()
        received: list[Event] = []
        try:
            async with database.hub.subscribe([topic]) as subscription:
                await asyncio.to_thread(publish)
                while len(received) < count:
                    event = await asyncio.wait_for(subscription.next(), 5)
                    if event is not RESYNC:
                        received.append(event)
        finally:
            if listener is not None:
                listener.stop()
        return received

    return asyncio.run(scenario())


def test_committed_events_reach_subscribers_and_rolled_back_ones_do_not(
    database: Database,
) -> None:
    def publish_twice() -> None:
        with database.write_session() as db:
            events.publish(db, topics=["study:1"], type="dropped", n=1)
            db.rollback()
            events.publish(db, topics=["study:1", "study:2"], type="kept", n=2)
            db.commit()

    received = _deliver(database, "study:1", publish_twice, 1)
    assert received == [Event(topic="study:1", type="kept", data={"n": 2})]


def test_a_transactions_events_arrive_in_order_from_one_notify(database: Database) -> None:
    """PostgreSQL: all of a transaction's events go out in one statement, in publication order
    (large ones truncated); SQLite: straight to the hub."""
    from sqlalchemy import event as sa_event

    notifies: list[str] = []

    def count(_conn: object, _cursor: object, statement: str, *_: object) -> None:
        if "pg_notify" in statement:
            notifies.append(statement)

    def publish() -> None:
        with database.write_session() as db:
            for n in range(3):
                events.publish(db, topics=["study:7"], type="step", n=n)
            events.publish(db, topics=["study:7"], type="big", text="x" * 9000)
            db.commit()

    sa_event.listen(database.engine, "before_cursor_execute", count)
    try:
        received = _deliver(database, "study:7", publish, 4)
    finally:
        sa_event.remove(database.engine, "before_cursor_execute", count)
    assert [(e.type, e.data.get("n")) for e in received[:3]] == [("step", n) for n in range(3)]
    assert received[3].type == "big"
    assert len(notifies) == (0 if database.is_sqlite else 1)
    if not database.is_sqlite:
        assert received[3].data == {"truncated": True}


def test_a_foreign_notification_is_dropped_and_the_listener_goes_on(
    database: Database, caplog: pytest.LogCaptureFixture
) -> None:
    """Anyone connected to the database can NOTIFY the channel; what is not an event must not
    stop the events after it (on SQLite there is no channel: the event arrives as always)."""

    def publish() -> None:
        with database.write_session() as db:
            if not database.is_sqlite:
                for junk in (
                    "not json",
                    '{"topic": "study:9"}',
                    "[1, 2]",
                    '{"topic": 1, "type": 2}',
                ):
                    db.execute(text("SELECT pg_notify(:c, :p)"), {"c": events.CHANNEL, "p": junk})
            events.publish(db, topics=["study:9"], type="after_junk")
            db.commit()

    with caplog.at_level(logging.WARNING, logger="app.events"):
        received = _deliver(database, "study:9", publish, 1)
    assert received == [Event(topic="study:9", type="after_junk")]
    ignored = [r for r in caplog.records if "ignored a notification" in r.getMessage()]
    assert len(ignored) == (0 if database.is_sqlite else 4)


def test_the_wire_form_is_parsed_or_refused() -> None:
    event = Event(topic="study:1", type="kept", data={"n": 2})
    assert Event.from_json(event.to_json()) == event
    for junk in ("", "not json", "[]", '{"type": "x"}', '{"topic": "t", "type": "x", "data": 3}'):
        with pytest.raises(ValueError, match="not a trustlab event"):
            Event.from_json(junk)


def test_a_slow_subscriber_is_told_to_resync() -> None:
    async def scenario() -> list[Event]:
        hub = EventHub()
        async with hub.subscribe(["t"]) as subscription:
            hub.deliver([Event("t", "x", {"i": i}) for i in range(events.QUEUE_SIZE + 10)])
            await asyncio.sleep(0.05)
            first = await subscription.next()
            hub.deliver([Event("t", "after")])
            await asyncio.sleep(0.05)
            second = await subscription.next()
            return [first, second]

    first, second = asyncio.run(scenario())
    assert first is RESYNC
    assert second.type == "after"


def test_topics_are_filtered() -> None:
    async def scenario() -> int:
        hub = EventHub()
        async with hub.subscribe(["a"]) as subscription:
            hub.deliver([Event("b", "x"), Event("a", "y")])
            await asyncio.sleep(0.05)
            assert hub.subscriber_count == 1
            return subscription.queue.qsize()

    assert asyncio.run(scenario()) == 1


def test_a_page_stream_sends_one_message_per_burst_of_changes() -> None:
    from app.web.streams import event_stream

    async def scenario() -> list[str]:
        hub = EventHub()
        body = event_stream(hub, ["study:1"], scope=Scope.every_site()).body_iterator
        chunks = [await anext(body)]  # the retry hint; the subscription is open now
        hub.deliver(Event(topic="study:1", type=kind) for kind in ("prompt", "answer", "answer"))
        chunks.append(await asyncio.wait_for(anext(body), 5))
        hub.deliver([Event(topic="study:1", type="questionnaire")])
        chunks.append(await asyncio.wait_for(anext(body), 5))
        await body.aclose()  # type: ignore[attr-defined]
        return [str(chunk) for chunk in chunks]

    retry, burst, single = asyncio.run(scenario())
    assert retry.startswith("retry:")
    assert burst == 'event: changed\ndata: {"types": ["answer", "prompt"]}\n\n'
    assert single == 'event: changed\ndata: {"types": ["questionnaire"]}\n\n'


def test_the_hub_counts_changes_per_topic() -> None:
    hub = EventHub()
    assert hub.version("study:1") == 0
    hub.deliver([Event(topic="study:1", type="answer"), Event(topic="study:2", type="answer")])
    hub.expect_echoes([("study:1", "e1")])  # before the commit
    hub.note_changes([("study:1", "e1")])  # committed here, its NOTIFY still on the way
    assert (hub.version("study:1"), hub.version("study:2")) == (2, 1)
    hub.deliver([Event(topic="study:1", type="answer", id="e1")])  # it arrives: counted already
    assert (hub.version("study:1"), hub.version("study:2")) == (2, 1)
    hub.deliver([Event(topic="study:1", type="answer", id="e2")])  # another process's change
    assert (hub.version("study:1"), hub.version("study:2")) == (3, 1)
    hub.deliver([RESYNC])  # anything may have changed
    assert (hub.version("study:1"), hub.version("study:2")) == (4, 2)
    hub.expect_echoes([("study:3", "e3")])
    hub.deliver([Event(topic="study:3", type="answer", id="e3")])  # the echo beat the commit's end
    hub.note_changes([("study:3", "e3")])
    assert hub.version("study:3") - hub.version("study:unused") == 1


def test_a_process_counts_its_own_notified_change_once(database: Database) -> None:
    """A commit counts its events at once (a reader sees its own change) and never again, when on
    PostgreSQL their NOTIFY comes back (a second count made the dashboards' shared computation
    run twice per change, and a test that counted computations flaky)."""
    topic = "study:77"
    counted: list[int] = []

    def changes() -> int:
        # version() adds the resyncs to a topic's changes; the listener's first resync may
        # arrive at any moment, so count the topic's own changes (an unused topic has none)
        return database.hub.version(topic) - database.hub.version("study:unused")

    def publish_one() -> None:
        counted.append(changes())
        with database.writing() as db:
            events.publish(db, topics=[topic], type="answer")
            db.commit()
        counted.append(changes())

    received = _deliver(database, topic, publish_one, 1)
    assert [event.type for event in received] == ["answer"]  # the NOTIFY has come back
    assert counted == [0, 1]  # counted at commit
    assert changes() == 1  # and not again when it came back


class _Clock:
    """A wall clock the test moves."""

    def __init__(self, now: float) -> None:
        self.now = now

    def __call__(self) -> float:
        return self.now


def test_the_hub_tells_what_came_since_a_moment_or_that_it_cannot_tell() -> None:
    clock = _Clock(1000.0)
    hub = EventHub(clock=clock)
    hub.deliver([Event("study:1", "answer")])
    clock.now = 1002.0
    hub.deliver([Event("study:1", "prompt"), Event("study:2", "answer")])
    assert [e.type for e in hub.since(["study:1"], 1001.0) or []] == ["prompt"]
    assert [e.type for e in hub.since(["study:1"], 1000.0) or []] == ["answer", "prompt"]
    assert hub.since(["study:3"], 1000.0) == []
    assert hub.since(["study:1"], 999.0) is None  # before the hub started: it cannot tell
    clock.now = 1002.0 + events.RECENT_SECONDS + 1
    assert hub.since(["study:1"], 1001.5) is None  # forgotten
    assert hub.since(["study:1"], clock.now - 1) == []
    hub.deliver([RESYNC])  # anything may have changed
    assert hub.since(["study:3"], clock.now) == [RESYNC]


def test_the_hub_cannot_tell_past_the_events_it_remembers() -> None:
    clock = _Clock(1000.0)
    hub = EventHub(clock=clock)
    clock.now = 1001.0
    hub.deliver(Event("study:2", "answer") for _ in range(events.RECENT_EVENTS))
    assert hub.since(["study:1"], 1000.5) is None  # the oldest remembered came later
    assert hub.since(["study:1"], 1001.0) == []


def _stream_messages(
    hub: EventHub, since: float | None, *, scope: Scope, then: list[Event]
) -> list[str]:
    """Open a study's page stream with ``since``, deliver ``then`` and return the messages up
    to and including the one those make (the retry hint left out)."""
    from app.web.streams import event_stream

    async def scenario() -> list[str]:
        body = event_stream(
            hub, ["study:1"], scope=scope, named={"room:1": "room"}, since=since
        ).body_iterator
        assert str(await anext(body)).startswith("retry:")
        hub.deliver(then)
        marker = then[-1].type
        messages = []
        while not messages or marker not in messages[-1]:
            messages.append(str(await asyncio.wait_for(anext(body), 5)))
        await body.aclose()  # type: ignore[attr-defined]
        return messages

    return asyncio.run(scenario())


def test_a_page_stream_sends_first_what_changed_since_the_page_began_to_read() -> None:
    clock = _Clock(1000.0)
    hub = EventHub(clock=clock)
    hub.deliver([Event("study:1", "before")])
    clock.now = 1010.0
    read_began = clock.now
    clock.now = 1010.5
    hub.deliver([Event("study:1", "missed"), Event("room:1", "moved"), Event("study:9", "other")])
    later = [Event("study:1", "later")]
    missed = _stream_messages(hub, read_began, scope=Scope.every_site(), then=later)
    assert missed == [
        'event: changed\ndata: {"types": ["missed"]}\n\n',
        'event: room\ndata: {"types": ["moved"]}\n\n',
        'event: changed\ndata: {"types": ["later"]}\n\n',
    ]
    clock.now = 1020.0  # nothing since the page began: the first message is the next change
    quiet = _stream_messages(hub, 1019.0, scope=Scope.every_site(), then=later)
    assert quiet == ['event: changed\ndata: {"types": ["later"]}\n\n']
    assert _stream_messages(hub, None, scope=Scope.every_site(), then=later) == quiet
    # A page older than the hub remembers: each of its regions refreshes once.
    unknown = _stream_messages(hub, 900.0, scope=Scope.every_site(), then=later)
    assert unknown[:2] == [
        'event: changed\ndata: {"types": ["unknown"]}\n\n',
        'event: room\ndata: {"types": ["unknown"]}\n\n',
    ]


def test_a_missed_change_of_a_hidden_site_is_not_sent() -> None:
    clock = _Clock(1000.0)
    hub = EventHub(clock=clock)
    clock.now = 1001.0
    hub.deliver([Event("study:1", "answer", {"site": "oslo"})])
    later = [Event("study:1", "later", {"site": "uppsala"})]
    limited = Scope(sites=frozenset({"uppsala"}))
    assert _stream_messages(hub, 1000.5, scope=limited, then=later) == [
        'event: changed\ndata: {"types": ["later"]}\n\n'
    ]
