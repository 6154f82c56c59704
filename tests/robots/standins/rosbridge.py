"""A ROS 2 robot behind rosbridge, on loopback: a rosbridge v2 WebSocket server that plays the
robot node of trustlab's speech interface (docs in ``app/robots/rosbridge.py``).

It speaks the protocol's real messages (``advertise``, ``unadvertise``, ``publish``,
``subscribe``, ``unsubscribe``, ``call_service`` answered by ``service_response``), so the
adapter's own client, roslibpy, talks to it unchanged. Like a robot node it subscribes to the say,
gesture and listen topics and publishes on the said, heard and cue topics:

- a line published on the say topic is recorded in the :class:`Script` (with the gesture published
  just before it, if any, and the colour the LED topic last set) and answered on the said topic
  with the same text; a ColorRGBA on the LED topic sets that colour (``a`` = 0: the robot's own);
- a request published on the listen topic takes the participant's next reply: words are published
  on the heard topic as ``{"id", "words", "confidence"}``, silence publishes nothing, and a drop
  aborts the TCP connection without a WebSocket close (a robot that vanishes); a cancel on the
  cancel topic is recorded (:attr:`RosbridgeStandIn.listen_log` keeps both in arrival order);
- :meth:`RosbridgeStandIn.cue` publishes a cue, as a touch sensor's node would.

``missing_topics`` leaves topics out of ``/rosapi/topics`` (a robot whose node does not provide
them); ``rosapi=False`` is a rosbridge started without its rosapi node; ``topic_types`` gives a
topic another type; ``reports_said=False`` is a robot that never reports a line said;
``stale_heard`` is published on the heard topic before each answer to a listen request (a late
result of an earlier one); ``late_after_drop`` is the node's result of the request a drop cut
off, published (with that request's id) when the next listen request arrives, on whichever
connection: a node keeps listening when rosbridge's client goes. The server runs on its own
thread with its own asyncio loop, on port 0.
"""

from __future__ import annotations

import asyncio
import json
import threading
from collections.abc import Coroutine, Iterable
from types import TracebackType
from typing import Any

from websockets.asyncio.server import Server, ServerConnection, serve
from websockets.exceptions import ConnectionClosed

from tests.robots.standins.script import Drop, Script, Silence, Words, hex_colour

STRING = "std_msgs/msg/String"
SAY, SAID, GESTURE = "/trustlab/say", "/trustlab/said", "/trustlab/gesture"
LED = "/trustlab/led"
LISTEN, HEARD, CUE = "/trustlab/listen", "/trustlab/heard", "/trustlab/cue"
CANCEL = "/trustlab/listen_cancel"
ROBOT_TOPICS = (SAY, SAID, GESTURE, LISTEN, HEARD, CUE)
"""The topics the robot node itself subscribes to or publishes on (the documented defaults)."""

BOUND = 10.0
"""Seconds any call into the server's loop may take before the test fails (a hang guard)."""


class RosbridgeStandIn:
    """``with RosbridgeStandIn(script) as robot:`` serves on ``127.0.0.1:robot.port``."""

    def __init__(
        self,
        script: Script,
        *,
        missing_topics: Iterable[str] = (),
        rosapi: bool = True,
        topic_types: dict[str, str] | None = None,
        reports_said: bool = True,
        stale_heard: str | None = None,
        late_after_drop: Words | None = None,
    ) -> None:
        self.script = script
        self.reports_said = reports_said
        self.stale_heard = stale_heard
        self.late_after_drop = late_after_drop
        self._cut_off: dict[str, Any] | None = None
        """The listen request a drop cut off, until its late result is published."""
        self.missing_topics = frozenset(missing_topics)
        self.rosapi = rosapi
        self.topic_types = dict.fromkeys(ROBOT_TOPICS, STRING) | (topic_types or {})
        self.listen_requests: list[dict[str, Any]] = []
        """Every listen request's JSON, in order (phrases, language, seconds, id)."""
        self.listen_log: list[tuple[str, Any]] = []
        """``("listen", id)`` and ``("cancel", id)`` in the order they arrived."""
        self.port = 0
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, daemon=True)
        self._server: Server | None = None
        self._subscribers: dict[str, set[ServerConnection]] = {}
        self._advertised: dict[str, str] = {}
        self._gesture: str | None = None
        self.led: str | None = None
        """The colour the LED topic last set (``#rrggbb``), None: the robot's own."""
        self.led_messages: list[dict[str, float]] = []
        self._open = 0
        self._changed = threading.Condition()

    def __enter__(self) -> RosbridgeStandIn:
        self._thread.start()
        self._server = self._run(self._listen())
        self.port = self._server.sockets[0].getsockname()[1]
        return self

    def __exit__(
        self,
        kind: type[BaseException] | None,
        error: BaseException | None,
        trace: TracebackType | None,
    ) -> None:
        if self._server is not None:
            self._server.close()
            self._run(self._server.wait_closed())
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(BOUND)
        self._loop.close()

    def cue(self, category: str | None = None) -> None:
        """Publish a cue on the cue topic: empty for "the next category", else its name."""
        self._run(self._publish(CUE, category or ""))

    def wait_connections(self, count: int) -> None:
        """Wait until exactly ``count`` clients are connected (an AssertionError after a bound)."""
        with self._changed:
            if not self._changed.wait_for(lambda: self._open == count, BOUND):
                raise AssertionError(f"{self._open} clients connected, expected {count}")

    def _run(self, work: Coroutine[Any, Any, Any]) -> Any:
        return asyncio.run_coroutine_threadsafe(work, self._loop).result(BOUND)

    async def _listen(self) -> Server:
        return await serve(self._serve, "127.0.0.1", 0, ping_interval=None)

    async def _serve(self, connection: ServerConnection) -> None:
        self._count_open(+1)
        try:
            async for frame in connection:
                await self._handle(connection, json.loads(frame))
        except ConnectionClosed:
            pass
        finally:
            for subscribers in self._subscribers.values():
                subscribers.discard(connection)
            self._count_open(-1)

    def _count_open(self, change: int) -> None:
        with self._changed:
            self._open += change
            self._changed.notify_all()

    async def _handle(self, connection: ServerConnection, message: dict[str, Any]) -> None:
        op, topic = message["op"], message.get("topic", "")
        if op == "subscribe":
            self._subscribers.setdefault(topic, set()).add(connection)
        elif op == "unsubscribe":
            self._subscribers.get(topic, set()).discard(connection)
        elif op == "advertise":
            self._advertised[topic] = message["type"]
        elif op == "unadvertise":
            self._advertised.pop(topic, None)
        elif op == "publish" and topic == LED:
            self._led_published(message["msg"])
        elif op == "publish":
            await self._published(connection, topic, message["msg"].get("data", ""))
        elif op == "call_service":
            await connection.send(json.dumps(self._service_response(message)))

    def _led_published(self, colour: dict[str, float]) -> None:
        """A ColorRGBA on the LED topic: the colour (parts 0-1) while ``a`` > 0, else the
        robot's own."""
        self.led_messages.append(dict(colour))
        if colour.get("a", 0.0) > 0:
            self.led = hex_colour(*(255 * colour.get(part, 0.0) for part in "rgb"))
        else:
            self.led = None

    async def _published(self, connection: ServerConnection, topic: str, data: str) -> None:
        """What the robot node does with a message from the bridge."""
        if topic == GESTURE:
            self._gesture = data
        elif topic == SAY:
            self.script.record_said(data, self._gesture, self.led)
            self._gesture = None
            if self.reports_said:
                await self._publish(SAID, data)
        elif topic == CANCEL:
            self.listen_log.append(("cancel", json.loads(data)["id"]))
        elif topic == LISTEN:
            request = json.loads(data)
            self.listen_requests.append(request)
            self.listen_log.append(("listen", request["id"]))
            self.script.record_vocabulary(request["phrases"])
            if self.stale_heard is not None:
                await self._publish(HEARD, self.stale_heard)
            if self._cut_off is not None and self.late_after_drop is not None:
                late = self.late_after_drop
                result = {"id": self._cut_off["id"], "words": late.words}
                await self._publish(HEARD, json.dumps(result | {"confidence": late.confidence}))
                self._cut_off = None
            reply = self.script.next_reply()
            if isinstance(reply, Words):
                heard = {"id": request["id"], "words": reply.words, "confidence": reply.confidence}
                await self._publish(HEARD, json.dumps(heard))
            elif isinstance(reply, Drop):
                self._cut_off = request
                connection.transport.abort()
            else:
                assert isinstance(reply, Silence)

    async def _publish(self, topic: str, data: str) -> None:
        frame = json.dumps({"op": "publish", "topic": topic, "msg": {"data": data}})
        for subscriber in list(self._subscribers.get(topic, ())):
            await subscriber.send(frame)

    def _service_response(self, call: dict[str, Any]) -> dict[str, Any]:
        """rosbridge's answer to ``call_service``: ``values`` on success, an error line else."""
        service, args = call["service"], call.get("args") or {}
        response: dict[str, Any] = {"op": "service_response", "service": service}
        if "id" in call:
            response["id"] = call["id"]
        topics = self._topics()
        if self.rosapi and service == "/rosapi/topics":
            listed = {"topics": list(topics), "types": list(topics.values())}
            return response | {"values": listed, "result": True}
        if self.rosapi and service == "/rosapi/topic_type":
            kind = {"type": topics.get(args.get("topic", ""), "")}
            return response | {"values": kind, "result": True}
        return response | {"values": f"Service {service} does not exist", "result": False}

    def _topics(self) -> dict[str, str]:
        """Every topic in this ROS graph and its type: the robot's and the clients' advertised."""
        present = {t: k for t, k in self.topic_types.items() if t not in self.missing_topics}
        return present | self._advertised | {"/rosout": "rcl_interfaces/msg/Log"}
