"""A stand-in Furhat: the Remote API skill's HTTP paths on loopback, answered from a Script.

It serves what the adapter uses, with the shapes of the vendor client's models (``Status``
``{success, message}``, ``Voice`` ``{name, language}``, ``User`` ``{id, location, rotation}``):

- ``POST /furhat/say?text=&blocking=`` records the line (with the gesture started just before),
  or drops that connection unsaid when the script says so (``Script.drop_says``);
- ``POST /furhat/gesture?name=&blocking=`` records the gesture; an unknown name is refused;
- ``POST /furhat/led?red=&green=&blue=`` sets the LED ring (a part not given is 0); a line is
  recorded with the colour the ring shows while it is said;
- ``GET /furhat/listen?language=`` takes the participant's next reply: words as the message
  (the Remote API carries no confidence), silence as ``SILENCE`` (or :attr:`silence_message`), and
  a drop closes that connection without an answer (the stand-in keeps serving, like a robot whose
  network blinked; :meth:`stop` is the robot gone);
- ``POST /furhat/listen/stop`` ends a listen held by ``listen_until_stopped`` with ``INTERRUPTED``;
- ``GET /furhat/voices``, ``POST /furhat/voice?name=``, ``GET /furhat/users``.

Any other path is a 404, as on a server that is not the skill.
"""

from __future__ import annotations

import http.server
import itertools
import json
import socket
import threading
from collections.abc import Callable
from typing import Any
from urllib.parse import parse_qs, urlsplit

from tests.robots.standins.script import Drop, Script, Silence, Words, hex_colour

VOICES = (("Matthew", "en-US"), ("Joanna", "en-US"), ("Hans", "de-DE"))
GESTURES = ("Nod", "Shake", "Smile", "BigSmile", "BrowRaise", "BrowFrown", "Thoughtful", "Wink")
POLL_SECONDS = 0.02
"""How often the server loop looks for a stop (its default, half a second, slows every test)."""
HANG_GUARD = 30.0
"""The longest a held listen waits for its stop: a bound against hangs, not a timing expectation."""


class FurhatStandIn:
    """``with FurhatStandIn(script) as robot:`` then point the adapter at robot.host, robot.port."""

    host = "127.0.0.1"

    def __init__(
        self,
        script: Script,
        *,
        silence_message: str = "SILENCE",
        listen_until_stopped: bool = False,
    ) -> None:
        self.script = script
        self.silence_message = silence_message
        self.listen_until_stopped = listen_until_stopped
        """Listens hear nothing and last until ``POST /furhat/listen/stop`` (a robot whose own
        listening time is longer than the bridge's)."""
        self.gestures: list[str] = []
        self.led = "#000000"
        """The LED ring's colour now (off at start)."""
        self.led_changes: list[str] = []
        self.voice: str | None = None
        self.requests: list[tuple[str, str, dict[str, str]]] = []
        """Every request on a Remote API path: method, path and query, in order."""
        self.listen_stops = 0
        self.users: dict[str, dict[str, Any]] = {}
        self._user_ids = (f"user-{n}" for n in itertools.count(1))
        self._pending_gesture: str | None = None
        self._changed = threading.Condition()
        self._server: http.server.ThreadingHTTPServer | None = None
        self._thread: threading.Thread | None = None
        self.port = 0

    # The test's controls.

    def enter_user(self) -> str:
        """A new user steps into the interaction space; returns its id."""
        with self._changed:
            user_id = next(self._user_ids)
            self.users[user_id] = {
                "id": user_id,
                "location": {"x": 0.0, "y": 0.0, "z": 1.0},
                "rotation": {"x": 0.0, "y": 0.0, "z": 0.0},
            }
            return user_id

    def leave_user(self, user_id: str) -> None:
        with self._changed:
            self.users.pop(user_id, None)

    def start(self) -> FurhatStandIn:
        server = http.server.ThreadingHTTPServer((self.host, 0), _handler_for(self))
        server.daemon_threads = True
        self._server = server
        self.port = server.server_address[1]
        self._thread = threading.Thread(
            target=server.serve_forever, args=(POLL_SECONDS,), name="furhat-standin"
        )
        self._thread.daemon = True
        self._thread.start()
        return self

    def stop(self) -> None:
        """The robot is gone: the port refuses connections (idempotent)."""
        server, self._server = self._server, None
        if server is not None:
            server.shutdown()
            server.server_close()
        with self._changed:
            self._changed.notify_all()

    def __enter__(self) -> FurhatStandIn:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # What each path does; each returns the JSON answer, or None to drop the connection.

    def _say(self, query: dict[str, str]) -> Any:
        with self._changed:
            gesture, self._pending_gesture = self._pending_gesture, None
        if self.script.say_drops():
            return None
        with self._changed:
            leds = self.led if self.led != "#000000" else None
        self.script.record_said(query.get("text", ""), gesture, leds)
        return _status(True, "")

    def _led(self, query: dict[str, str]) -> Any:
        parts = [min(255, int(query.get(part) or 0)) for part in ("red", "green", "blue")]
        with self._changed:  # a part not given is 0, as on the robot
            self.led = hex_colour(*parts)
            self.led_changes.append(self.led)
        return _status(True, "")

    def _gesture(self, query: dict[str, str]) -> Any:
        name = query.get("name", "")
        if name not in GESTURES:
            return _status(False, f"No gesture named {name}")
        with self._changed:
            self.gestures.append(name)
            self._pending_gesture = name
        return _status(True, "")

    def _listen(self, query: dict[str, str]) -> Any:
        with self._changed:
            stops = self.listen_stops
        if self.listen_until_stopped:
            with self._changed:
                self._changed.wait_for(
                    lambda: self.listen_stops > stops or self._server is None, HANG_GUARD
                )
            return _status(True, "INTERRUPTED")
        reply = self.script.next_reply()
        if isinstance(reply, Drop):
            return None
        if isinstance(reply, Words):
            return _status(True, reply.words)
        assert isinstance(reply, Silence)
        return _status(True, self.silence_message)

    def _listen_stop(self, query: dict[str, str]) -> Any:
        with self._changed:
            self.listen_stops += 1
            self._changed.notify_all()
        return _status(True, "")

    def _voices(self, query: dict[str, str]) -> Any:
        return [{"name": name, "language": language} for name, language in VOICES]

    def _set_voice(self, query: dict[str, str]) -> Any:
        name = query.get("name", "")
        if name not in dict(VOICES):
            return _status(False, f"No voice named {name}")
        self.voice = name
        return _status(True, "")

    def _users(self, query: dict[str, str]) -> Any:
        with self._changed:
            return list(self.users.values())

    def record_request(self, method: str, path: str, query: dict[str, str]) -> None:
        with self._changed:
            self.requests.append((method, path, query))

    def queries(self, path: str) -> list[dict[str, str]]:
        """The query of each request on ``path``, in order."""
        with self._changed:
            return [query for _, p, query in self.requests if p == path]

    def route(self, method: str, path: str) -> Callable[[dict[str, str]], Any] | None:
        return {
            ("POST", "/furhat/say"): self._say,
            ("POST", "/furhat/gesture"): self._gesture,
            ("POST", "/furhat/led"): self._led,
            ("GET", "/furhat/listen"): self._listen,
            ("POST", "/furhat/listen/stop"): self._listen_stop,
            ("GET", "/furhat/voices"): self._voices,
            ("POST", "/furhat/voice"): self._set_voice,
            ("GET", "/furhat/users"): self._users,
        }.get((method, path))


def _status(success: bool, message: str) -> dict[str, Any]:
    return {"success": success, "message": message}


def _handler_for(robot: FurhatStandIn) -> type[http.server.BaseHTTPRequestHandler]:
    class RemoteApiHandler(http.server.BaseHTTPRequestHandler):
        """One request: HTTP/1.0, so every answer closes its connection (a stopped stand-in
        leaves no kept-alive connection that would still answer)."""

        def do_GET(self) -> None:
            self._answer("GET")

        def do_POST(self) -> None:
            self._answer("POST")

        def _answer(self, method: str) -> None:
            url = urlsplit(self.path)
            length = int(self.headers.get("Content-Length") or 0)
            self.rfile.read(length)
            action = robot.route(method, url.path)
            if action is None:
                self.send_error(404)
                return
            query = {k: v[-1] for k, v in parse_qs(url.query, keep_blank_values=True).items()}
            robot.record_request(method, url.path, query)
            answer = action(query)
            if answer is None:
                self.close_connection = True
                self.connection.shutdown(socket.SHUT_RDWR)
                return
            body = json.dumps(answer).encode()
            try:
                self.send_response(200)
                self.send_header("Content-Type", "application/json")
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)
            except (BrokenPipeError, ConnectionResetError):
                self.close_connection = True  # the bridge went away mid-request (killed)

        def log_message(self, format: str, *args: Any) -> None:
            """Quiet: the tests read the script, not the access log."""

    return RemoteApiHandler
