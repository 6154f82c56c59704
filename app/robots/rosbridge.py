"""A ROS 2 robot reached through rosbridge (rosbridge_server's v2 JSON protocol over a WebSocket),
with the vendor's client roslibpy.

ROS 2 has no standard speech interface, so trustlab defines a small one of ``std_msgs/msg/String``
topics; a robot joins by running a node that implements the robot's side (every name is an
option of :class:`RosbridgeOptions`):

============================  =======  ============================================================
topic (default)               who      ``data`` of the String
============================  =======  ============================================================
``/trustlab/gesture``         bridge   a gesture name, published just before the line it goes with
``/trustlab/say``             bridge   a line to say with the robot's text-to-speech
``/trustlab/said``            robot    the same line once it has been said (or empty: "done")
``/trustlab/listen``          bridge   JSON ``{"id": "5f0c9a1e2b7d-3", "phrases": ["yes", "no"],
                                       "language": "en-US", "seconds": 8.0}``: listen now
``/trustlab/listen_cancel``   bridge   JSON ``{"id": "5f0c9a1e2b7d-3"}``: stop that listen (the
                                       bridge gave up on it, or a new listen supersedes it)
``/trustlab/heard``           robot    JSON ``{"id": "5f0c9a1e2b7d-3", "words": "yes",
                                       "confidence": 0.8}``, or plain words (confidence 1);
                                       empty words mean silence. ``id`` (optional) echoes the
                                       request's, so a late result of an earlier request is not
                                       taken for this one
``/trustlab/cue``             robot    the robot's cue to ask: empty for the next expected
                                       category, or a category's name
============================  =======  ============================================================

A request's ``id`` is an opaque string for the node to echo unchanged: a random prefix of the
bridge process and a counter of that process (:func:`new_listen_id`), so no two listen requests
share one, across reconnections and restarts of the bridge alike. A node that keeps a result of
an earlier request (the connection dropped before it arrived) cannot have it taken as the answer
to a later question. ``confidence`` is a fraction from 0 to 1: anything else (85 for 85 %) is
passed on as it is and the bridge refuses it (not taken as an answer).

One topic is not a String: ``/trustlab/led`` (``std_msgs/msg/ColorRGBA``, published by the bridge
when the protocol gives a reply's level an LED colour) carries that colour (``r``, ``g``, ``b`` in
0-1, ``a`` = 1) just before the reply is said, and ``a`` = 0 once it has been said: back to the
robot's own colours.

A robot that reports nothing on the heard topic is silence once ``seconds`` (plus
``listen_grace`` for the result to travel) are over: the bridge then gives up on that request
and publishes its cancel. A listen request that never got its result because the connection
dropped is cancelled on the next connection, just before the next listen request. A cue that
comes while the bridge is busy is kept for its next :meth:`~RosbridgeRobot.wait_cue` (only the
latest one).

At connect the adapter checks, through rosbridge's rosapi services, that the topics the robot must
provide (said and heard; the cue topic when ``require_cue_topic``) exist and carry Strings; the
topics it publishes itself it advertises, then and there: a ROS 2 subscriber can miss what a
just-created publisher sends before discovery matched them, so the first line is never the first
message of a new publisher.

roslibpy runs Twisted's reactor on a thread of its own, and a reactor cannot be started again once
stopped. So the adapter never stops it (never ``Ros.terminate``): closing only closes the WebSocket
and stops the client's automatic reconnection, and every later connection reuses the running
reactor. Reconnecting is the bridge's decision (on :class:`RobotLost` it closes and connects
again), so roslibpy's own endless retries are switched off on every connection.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import math
import socket
import threading
import time
import uuid
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from app.robots.robot import Colour, Cue, Heard, RobotLost, RobotUnreachable

STRING = "std_msgs/msg/String"
STRING_TYPES = {STRING, "std_msgs/String"}
COLOUR = "std_msgs/msg/ColorRGBA"
MAX_UNFINISHED = 5
"""Listen requests of lost connections remembered for a cancel (a robot lost again and again
while listening leaves no more than this many to cancel)."""
CLOSE_BOUND = 5.0
"""Seconds closing may take before the adapter lets the socket go (autobahn's own bound)."""

_REACTOR_START = threading.Lock()
"""roslibpy starts the reactor thread on the first ``Ros.run``; two at once could start two."""

_PROCESS_PREFIX = uuid.uuid4().hex[:12]
"""Random for each bridge process: a restarted bridge never repeats an earlier one's ids."""
_LISTEN_COUNT = itertools.count(1)
_LISTEN_COUNT_LOCK = threading.Lock()


def new_listen_id() -> str:
    """A listen request's id, unique across connections and processes: this process's random
    prefix and its own count of requests (``"5f0c9a1e2b7d-3"``). Numbering from 1 on every
    connection would give the first listen after a reconnection the id of the one the drop cut
    off, and the node's late result of that one would be taken as the answer to the new
    question."""
    with _LISTEN_COUNT_LOCK:
        return f"{_PROCESS_PREFIX}-{next(_LISTEN_COUNT)}"


@dataclass(frozen=True)
class RosbridgeOptions:
    """Where rosbridge is, the topics of trustlab's speech interface, and the bounds."""

    host: str = "localhost"
    port: int = 9090
    say_topic: str = "/trustlab/say"
    said_topic: str = "/trustlab/said"
    gesture_topic: str | None = "/trustlab/gesture"
    """None: gestures are not sent."""
    led_topic: str | None = "/trustlab/led"
    """A ``std_msgs/msg/ColorRGBA`` topic for the reply's LED colour; None: none is sent."""
    listen_topic: str = "/trustlab/listen"
    cancel_topic: str | None = "/trustlab/listen_cancel"
    """Where the bridge cancels a listen request it gave up on or superseded; None: not sent."""
    heard_topic: str = "/trustlab/heard"
    cue_topic: str = "/trustlab/cue"
    require_cue_topic: bool = False
    """Check at connect that the cue topic exists (set when the bridge's trigger is the cue)."""
    language: str = "en-US"
    """Passed along in every listen request, for the robot's recogniser."""
    listen_grace: float = 2.0
    """Seconds a recognition result may take to arrive after the listening time is over."""
    say_timeout: float = 30.0
    """Seconds the robot may take to report a line said before it counts as lost."""
    connect_timeout: float = 10.0
    """Bound of the TCP connection, the WebSocket handshake and each rosapi call."""


class _Refused(Exception):
    """Why a connection could not be made, as one line."""


class RosbridgeRobot:
    """A robot behind rosbridge; one connection at a time, opened by :meth:`connect`."""

    def __init__(self, options: RosbridgeOptions | None = None) -> None:
        self.options = options or RosbridgeOptions()
        self.description = f"rosbridge at ws://{self.options.host}:{self.options.port}"
        self._link: _Link | None = None
        self._reached_before = False
        self._unfinished: list[str] = []
        """Ids of listen requests whose result never came because their connection was lost:
        cancelled on the next connection before the next request (the node may still listen)."""

    def connect(self) -> None:
        self.close()
        try:
            self._link = _Link.open(self.options, self.description)
        except _Refused as refusal:
            error = RobotLost if self._reached_before else RobotUnreachable
            raise error(f"{self.description}: {refusal}") from None
        self._reached_before = True

    def say(self, text: str, gesture: str | None = None, leds: Colour | None = None) -> None:
        self._current().say(text, gesture, leds)

    def listen(self, phrases: Sequence[str], seconds: float) -> Heard | None:
        link = self._current()
        request_id = new_listen_id()
        superseded = list(self._unfinished)
        self._unfinished = [*superseded[-(MAX_UNFINISHED - 1) :], request_id]
        heard = link.listen(request_id, phrases, seconds, superseded)
        self._unfinished = []  # heard, or given up on and cancelled; the superseded cancelled
        return heard

    def wait_cue(self, seconds: float) -> Cue | None:
        return self._current().wait_cue(seconds)

    def close(self) -> None:
        link, self._link = self._link, None
        if link is not None:
            link.close()

    def _current(self) -> _Link:
        link = self._link
        if link is None:
            raise RobotLost(f"{self.description}: not connected")
        return link


class _Link:
    """One rosbridge connection: its topics, and what the robot sent that nobody took yet.

    roslibpy calls the handlers on the reactor thread; they only queue and notify. A lost
    connection or a close wakes every waiter, which then raises :class:`RobotLost`."""

    def __init__(self, options: RosbridgeOptions, description: str, roslibpy: Any) -> None:
        self.options = options
        self.description = description
        self._roslibpy = roslibpy
        self._ros = roslibpy.Ros(options.host, options.port, transport="twisted")
        self._changed = threading.Condition()
        self._said: deque[str] = deque()
        self._heard: deque[str] = deque()
        self._cues: deque[str] = deque(maxlen=1)
        """Only the latest cue is kept: one touch, however it bounced, asks one question."""
        self._ready = False
        self._lost = False
        self._closed = False
        self._ros.on("close", self._on_close)

    @classmethod
    def open(cls, options: RosbridgeOptions, description: str) -> _Link:
        roslibpy = _import_roslibpy()
        _probe(options)
        try:
            link = cls(options, description, roslibpy)
        except RuntimeError as error:  # txaio already bound to asyncio by someone else
            raise _Refused(str(error).split(". ")[0]) from None
        try:
            link._start()
        except BaseException:
            link.close()
            raise
        return link

    def _start(self) -> None:
        timeout = self.options.connect_timeout
        try:
            with _REACTOR_START:
                self._ros.run(timeout)
        except self._roslibpy.core.RosTimeoutError:
            raise _Refused(
                f"the port answers, but no rosbridge WebSocket within {timeout:g} s "
                "(is it rosbridge_server's port?)"
            ) from None
        self._ready = True
        topic = self._topic
        topic(self.options.said_topic).subscribe(self._queue(self._said))
        topic(self.options.heard_topic).subscribe(self._queue(self._heard))
        topic(self.options.cue_topic).subscribe(self._queue(self._cues))
        self._say = topic(self.options.say_topic)
        self._listen = topic(self.options.listen_topic)
        cancel_topic = self.options.cancel_topic
        self._cancel = topic(cancel_topic) if cancel_topic else None
        self._gesture = topic(self.options.gesture_topic) if self.options.gesture_topic else None
        led_topic = self.options.led_topic
        self._led = (
            self._roslibpy.Topic(self._ros, led_topic, COLOUR, reconnect_on_close=False)
            if led_topic
            else None
        )
        for advertised in (self._say, self._listen, self._cancel, self._gesture, self._led):
            if advertised is not None:
                advertised.advertise()
        # rosbridge handles a connection's operations in order, so the subscriptions are in place
        # once the rosapi answers below: nothing the robot publishes after connect() is missed.
        self._check_topics()

    def _topic(self, name: str) -> Any:
        return self._roslibpy.Topic(self._ros, name, STRING, reconnect_on_close=False)

    def _check_topics(self) -> None:
        """The topics the robot must publish exist, as Strings (rosbridge's rosapi says)."""
        required = {
            self.options.said_topic: "where the robot reports each line said",
            self.options.heard_topic: "where the robot's recogniser reports",
        }
        if self.options.require_cue_topic:
            required[self.options.cue_topic] = "where the robot cues a question"
        topics = self._rosapi("/rosapi/topics", "rosapi_msgs/srv/Topics", {}).get("topics", [])
        for name, role in required.items():
            if name not in topics:
                raise _Refused(f"no topic {name} ({role}); is the robot's trustlab node running?")
            typed = self._rosapi("/rosapi/topic_type", "rosapi_msgs/srv/TopicType", {"topic": name})
            kind = typed.get("type", "")
            if kind and kind not in STRING_TYPES:
                raise _Refused(f"topic {name} carries {kind}, not {STRING}")

    def _rosapi(self, name: str, kind: str, request: dict[str, str]) -> Any:
        roslibpy = self._roslibpy
        service = roslibpy.Service(self._ros, name, kind, reconnect_on_close=False)
        try:
            return service.call(
                roslibpy.ServiceRequest(request), timeout=self.options.connect_timeout
            )
        except roslibpy.core.RosTimeoutError:
            problem = f"no answer within {self.options.connect_timeout:g} s"
        except roslibpy.core.ServiceException as error:
            problem = _one_line(str(error))
        raise _Refused(
            f"{name} failed ({problem}); start rosbridge with its rosapi node "
            "(ros2 launch rosbridge_server rosbridge_websocket_launch.xml)"
        )

    def say(self, text: str, gesture: str | None, leds: Colour | None) -> None:
        with self._changed:
            self._check("saying")
            self._said.clear()
        if gesture and self._gesture is not None:
            self._gesture.publish(self._roslibpy.Message({"data": gesture}))
        shows = leds is not None and self._led is not None
        if shows:
            assert leds is not None
            red, green, blue = (round(part / 255, 4) for part in leds)
            self._publish_led({"r": red, "g": green, "b": blue, "a": 1.0})
        self._say.publish(self._roslibpy.Message({"data": text}))
        said = self._take(
            self._said, lambda line: line in ("", text), self.options.say_timeout, "saying"
        )
        if said is None:
            raise RobotLost(
                f"{self.description}: the robot did not report {_quoted(text)} said on "
                f"{self.options.said_topic} within {self.options.say_timeout:g} s"
            )
        if shows:
            self._publish_led({"r": 0.0, "g": 0.0, "b": 0.0, "a": 0.0})  # the robot's own again

    def _publish_led(self, colour: dict[str, float]) -> None:
        assert self._led is not None
        self._led.publish(self._roslibpy.Message(colour))

    def listen(
        self, request_id: str, phrases: Sequence[str], seconds: float, superseded: list[str]
    ) -> Heard | None:
        """Publish a listen request (after cancelling ``superseded``, requests of lost
        connections) and wait for its result; on silence the request is cancelled."""
        with self._changed:
            self._check("listening")
            self._heard.clear()
        for unfinished in superseded:
            self._publish_cancel(unfinished)
        request = {
            "id": request_id,
            "phrases": list(phrases),
            "language": self.options.language,
            "seconds": seconds,
        }
        self._listen.publish(self._roslibpy.Message({"data": json.dumps(request)}))
        result = self._take(
            self._heard,
            lambda data: decode_heard(data)[0] in (None, request_id),
            seconds + self.options.listen_grace,
            "listening",
        )
        if result is None:
            self._publish_cancel(request_id)  # given up: a node still listening stops
            return None
        return decode_heard(result)[1]

    def _publish_cancel(self, request_id: str) -> None:
        if self._cancel is not None:
            self._cancel.publish(self._roslibpy.Message({"data": json.dumps({"id": request_id})}))

    def wait_cue(self, seconds: float) -> Cue | None:
        cue = self._take(self._cues, lambda _: True, seconds, "waiting for a cue")
        return None if cue is None else Cue(cue.strip() or None, source="ROS topic")

    def close(self) -> None:
        """Close the WebSocket (bounded), stop roslibpy's reconnecting, keep the reactor."""
        with self._changed:
            if self._closed:
                return
            self._closed = True
            open_websocket = self._ready and not self._lost
            self._changed.notify_all()
        if open_websocket:
            # Closing must not fail: past the bound the socket is let go anyway.
            with contextlib.suppress(Exception):
                self._ros.close(CLOSE_BOUND)
        from twisted.internet import reactor

        reactor.callFromThread(self._stop_retrying, disconnect=not self._ready)
        # Each connection's event loop manager forwards Twisted's log to Python logging; left
        # running, every reconnection would repeat each Twisted log line once more.
        manager = getattr(self._ros.factory, "_manager", None)
        observer = getattr(manager, "_log_observer", None)
        if observer is not None:
            observer.stop()

    def _stop_retrying(self, disconnect: bool) -> None:
        """On the reactor thread: no more automatic reconnection; drop a half-open socket."""
        factory = self._ros.factory
        factory.stopTrying()
        if disconnect and factory.connector is not None:
            factory.connector.disconnect()

    def _on_close(self, _protocol: object) -> None:
        """The WebSocket closed (on the reactor thread, before roslibpy would reconnect)."""
        self._ros.factory.stopTrying()
        with self._changed:
            self._lost = True
            self._changed.notify_all()

    def _queue(self, queue: deque[str]) -> Callable[[dict[str, Any]], None]:
        def received(message: dict[str, Any]) -> None:
            with self._changed:
                queue.append(str(message.get("data", "")))
                self._changed.notify_all()

        return received

    def _take(
        self, queue: deque[str], wanted: Callable[[str], bool], seconds: float, doing: str
    ) -> str | None:
        """The first queued message ``wanted`` within ``seconds`` (others are dropped), or
        None; :class:`RobotLost` if the connection goes first."""
        deadline = time.monotonic() + max(0.0, seconds)
        with self._changed:
            while True:
                while queue:
                    message = queue.popleft()
                    if wanted(message):
                        return message
                self._check(doing)
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return None
                self._changed.wait(remaining)

    def _check(self, doing: str) -> None:
        """Raise :class:`RobotLost` if the connection is gone (call holding ``_changed``)."""
        if self._closed:
            raise RobotLost(f"{self.description}: the connection was closed while {doing}")
        if self._lost:
            raise RobotLost(f"{self.description}: the connection was lost while {doing}")


def decode_heard(data: str) -> tuple[object, Heard | None]:
    """A heard message's request id (None when it has none) and what it heard (None: silence).

    JSON objects give ``words`` and ``confidence`` (missing: 1; not a number: 0, so unclear; a
    number outside 0-1 as it is, for the bridge to refuse: clamping 85 to 1 would pass it as
    certain); anything else is plain words heard with confidence 1."""
    try:
        fields = json.loads(data)
    except ValueError:
        fields = None
    if not isinstance(fields, dict):
        return None, Heard(data.strip(), 1.0) if data.strip() else None
    words = str(fields.get("words") or "").strip()
    confidence = fields.get("confidence", 1.0)
    if isinstance(confidence, bool) or not isinstance(confidence, int | float):
        confidence = 0.0
    confidence = float(confidence) if math.isfinite(confidence) else 0.0
    return fields.get("id"), Heard(words, confidence) if words else None


def _probe(options: RosbridgeOptions) -> None:
    """A plain TCP connection first: roslibpy only ever reports "no connection within the
    timeout", and retries a refused one for ever; this says what went wrong, at once."""
    address = (options.host, options.port)
    try:
        socket.create_connection(address, timeout=options.connect_timeout).close()
    except ConnectionRefusedError:
        raise _Refused("connection refused (is rosbridge_server running on that port?)") from None
    except socket.gaierror as error:
        raise _Refused(f"unknown host {options.host!r} ({error.strerror})") from None
    except TimeoutError:
        raise _Refused(f"no answer within {options.connect_timeout:g} s") from None
    except OSError as error:
        raise _Refused(_one_line(error.strerror or str(error))) from None


def _import_roslibpy() -> Any:
    try:
        import roslibpy
        import roslibpy.core
    except ImportError:
        raise _Refused("roslibpy is not installed (pip install 'trustlab[robots]')") from None
    return roslibpy


def _quoted(text: str, limit: int = 60) -> str:
    line = _one_line(text)
    return repr(line if len(line) <= limit else line[: limit - 1] + "…")


def _one_line(text: str) -> str:
    return " ".join(text.split())
