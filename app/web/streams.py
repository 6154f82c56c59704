"""Server-sent events for pages: 'something changed on these topics'.

Pages listen with EventSource (or htmx's SSE extension) and fetch what they show again; events
carry only their type, so a page never renders from a push it could not have fetched itself.
Nor does a page hear *when* something it could not fetch happened: every stream takes the
reader's scope (app.services.privacy.sites.Scope, required), and an event about a participant of a
site out of scope never reaches it, not even as a bare "changed".
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator, Iterable, Iterator, Mapping

from fastapi.responses import StreamingResponse

from app.events import Event, EventHub
from app.services.privacy.sites import Scope, reaches

KEEPALIVE_SECONDS = 15.0
CLOCK_MARGIN_SECONDS = 0.2
"""A page's ``since`` is moved this much earlier: the page and the stream may be served by
different processes, whose readings of the wall clock a slewing clock can set a little apart.
Kept short: each change within it of the page's start refreshes the page once more."""
COALESCE_SECONDS = 0.1
"""Changes within this window after the first go out as one message: a busy study changes many
times a second, and a page refetches on each message, so at most ten a second reach it."""


CHANGED = "changed"


def event_stream(
    hub: EventHub,
    topics: Iterable[str],
    *,
    scope: Scope,
    ends_with: str | None = None,
    named: Mapping[str, str] | None = None,
    since: float | None = None,
) -> StreamingResponse:
    """An endless ``text/event-stream`` of ``changed`` events for ``topics`` (with keep-alives),
    which ends as soon as an event arrives on the topic ``ends_with``: a signed-in page's stream
    ends with its login (app.services.staff.users.login_topic), so a browser signed out, or whose
    account is disabled, hears nothing more (the EventSource's reconnection is refused).

    ``named`` maps further topics to an SSE event name of their own, so that a part of the page
    that changes often (the console's room panel) refreshes alone instead of the whole page.

    ``scope``: whose activity the reader may hear of (app.services.privacy.sites.reaches); the
    events of other sites' participants are dropped before they are counted, so a burst of them
    sends nothing at all.

    ``since``: when the page that opens the stream began to read what it shows (the ``since``
    it was rendered with, app.web.templating). A change that came between then and the stream's
    opening is sent at once, as it would have been live; when the hub cannot tell (it started
    later, or the page is older than it remembers), every event name is sent once."""
    named = dict(named or {})
    watched = [*topics, *named]
    subscribed = [*watched, *([ends_with] if ends_with else [])]

    def names_of(batch: Iterable[Event]) -> Iterator[str]:
        batch = [item for item in batch if reaches(scope, item)]
        for name in sorted({named.get(item.topic, CHANGED) for item in batch}):
            types = sorted({i.type for i in batch if named.get(i.topic, CHANGED) == name})
            yield f"event: {name}\ndata: {json.dumps({'types': types})}\n\n"

    def missed() -> Iterator[str]:
        if since is None:
            return
        events = hub.since(watched, since - CLOCK_MARGIN_SECONDS)
        if events is None:  # cannot tell: refresh everything once
            for name in sorted({CHANGED, *named.values()}):
                yield f"event: {name}\ndata: {json.dumps({'types': ['unknown']})}\n\n"
        else:
            yield from names_of(events)

    async def stream() -> AsyncIterator[str]:
        # Registered and released explicitly: a context manager nested in an async generator
        # breaks when the generator is finalised on an event loop that is shutting down.
        subscription = hub.open(subscribed)
        try:
            caught_up = list(missed())  # after subscribing: a change from now on is queued
            yield "retry: 3000\n\n"
            for message in caught_up:
                yield message
            while True:
                try:
                    event = await asyncio.wait_for(subscription.next(), KEEPALIVE_SECONDS)
                except TimeoutError:
                    yield ": keepalive\n\n"
                    continue
                if event.topic != ends_with:
                    await asyncio.sleep(COALESCE_SECONDS)
                batch = [event, *subscription.drain()]
                if any(item.topic == ends_with for item in batch):
                    return
                for message in names_of(batch):
                    yield message
        finally:
            hub.close(subscription)

    return StreamingResponse(
        stream(),
        media_type="text/event-stream",
        headers={"Cache-Control": "no-store", "X-Accel-Buffering": "no"},
    )
