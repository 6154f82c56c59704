"""Furhat, through its Remote API skill and the vendor's own client (``furhat-remote-api``).

The Remote API is plain HTTP served by a skill on the robot (port 54321 unless the skill is told
otherwise): ``POST /furhat/say``, ``GET /furhat/listen``, ``POST /furhat/gesture``,
``GET /furhat/users``, ``GET/POST /furhat/voice(s)``. Each call blocks until the robot has done it
and answers a ``Status`` (``success``, ``message``) or a JSON list.

What the Remote API cannot do, and what this adapter does instead:

- ``listen`` takes no phrases (no grammar): Furhat's recogniser hears free speech and the bridge's
  :class:`~app.speech.vocabulary.Vocabulary` keeps only the yes/no phrases.
- ``listen`` reports no confidence: a recognised utterance counts with
  :data:`RECOGNISED_CONFIDENCE`, see there.
- ``listen`` takes no time limit (the robot stops on its own no-speech timeout): the adapter asks
  the robot to stop (``POST /furhat/listen/stop``) once the bridge's ``seconds`` are up.
- there is no volume: set it on the robot (its web interface).
- there are no events: a user entering the interaction space is noticed by polling the users.

The vendor client hard-codes port 54321 and a client without timeouts that retries failed
requests. The adapter points the client at the configured port, gives it a connection pool that
never retries (a retried ``GET /furhat/listen`` would make the robot listen twice, and retries
multiply every bound), and passes a timeout with every request, so nothing waits forever.
"""

from __future__ import annotations

import http.client
import json
import logging
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

from app.robots.robot import Colour, Cue, Heard, RobotError, RobotLost, RobotUnreachable

log = logging.getLogger(__name__)

REMOTE_API_PORT = 54321
"""The port the Remote API skill listens on unless configured otherwise."""

RECOGNISED_CONFIDENCE = 1.0
"""The confidence of anything Furhat's recogniser reports as heard.

The Remote API returns only the recogniser's final transcript, with no confidence: the recogniser
has already decided (it answers ``SILENCE`` or ``FAILED`` when it has nothing). Any made-up lower
number would interact with the protocol's ``min_confidence`` in a way nobody could reason about,
so a recognition passes the confidence check and the vocabulary's exact phrase match is what
decides: free speech that is not one of the phrases is unclear, and the robot asks again."""

NOTHING_HEARD = frozenset({"", "SILENCE", "INTERRUPTED", "FAILED"})
"""The messages ``GET /furhat/listen`` answers when it heard no words: the vendor client documents
SILENCE, INTERRUPTED (after ``/furhat/listen/stop``) and FAILED; an empty message means the same."""

SLOWEST_SPEECH = 5.0
"""Characters per second a line is at least spoken at (about 60 words a minute, half a usual
speaking rate): bounds how long a blocking say may take before the robot counts as lost."""

START_HINT = "is the robot on and its Remote API skill running?"


@dataclass(frozen=True)
class FurhatOptions:
    """How to reach a Furhat and how it speaks and listens."""

    host: str = "localhost"
    port: int = REMOTE_API_PORT
    voice: str | None = None
    """A voice name of the robot's (``GET /furhat/voices``, e.g. ``Matthew``), set on connect;
    None keeps the robot's current voice."""
    language: str = "en-US"
    """The language the robot listens in (``GET /furhat/listen?language=``)."""
    request_seconds: float = 5.0
    """How long any request may take to connect, and to answer when it is not a say or a listen
    (which get their line's or listening time on top)."""
    poll_seconds: float = 0.25
    """How often :meth:`FurhatRobot.wait_cue` asks the robot who is in its interaction space."""


class FurhatRobot:
    """A Furhat behind its Remote API skill, as the bridge's :class:`~app.robots.robot.Robot`.

    Thread-safe in the way the bridge needs: the vendor client's connection pool serves
    :meth:`wait_cue` on one thread while :meth:`say` or :meth:`listen` runs on another."""

    def __init__(self, options: FurhatOptions) -> None:
        self.options = options
        self.description = f"Furhat at {options.host}:{options.port}"
        self._api: Any = None
        self._connected_once = False
        self._closed = threading.Event()
        self._users_seen: frozenset[str] = frozenset()

    def connect(self) -> None:
        """Reach the Remote API, check it is Furhat's (its voices and users answer as lists), set
        the voice if one is configured, and note who is already in the interaction space (they
        are not a cue: a participant must enter after the bridge starts)."""
        self.close()
        failure = RobotLost if self._connected_once else RobotUnreachable
        api = self._new_client(failure)
        try:
            voices = self._get_list(api, api.get_voices, "/furhat/voices", "name", failure)
            users = self._get_list(api, api.get_users, "/furhat/users", "id", failure)
            if self.options.voice is not None:
                self._set_voice(api, self.options.voice, voices, failure)
        except BaseException:
            _release(api)
            raise
        self._users_seen = frozenset(users)
        self._api = api
        self._closed.clear()
        self._connected_once = True

    def say(self, text: str, gesture: str | None = None, leds: Colour | None = None) -> None:
        """Say ``text`` and return when it has been said; ``gesture`` (a Furhat gesture name such
        as ``Nod``, ``Smile`` or ``BrowRaise``) starts just before, so it plays while speaking. A
        gesture the robot refuses is logged and left out: the line matters, the gesture does not.
        ``leds``: the LED ring shows that colour (``POST /furhat/led``) while the line is said,
        and is switched off afterwards (the Remote API cannot read the colour it had)."""
        api = self._connected()
        if gesture:
            self._gesture(api, gesture)
        if leds is not None:
            self._led(api, leds)
        seconds = self.options.request_seconds + len(text) / SLOWEST_SPEECH
        status = self._request(api.say, "saying a line", seconds, text=text, blocking=True)
        if status.success is False:
            raise RobotLost(f"{self.description} did not say the line: {status.message}")
        if leds is not None:
            self._led(api, (0, 0, 0))

    def listen(self, phrases: Sequence[str], seconds: float) -> Heard | None:
        """Listen once for at most ``seconds``: the robot's words with
        :data:`RECOGNISED_CONFIDENCE`, or None when it heard nothing.

        ``phrases`` cannot be given to the robot (the Remote API's listen has no grammar); the
        bridge's vocabulary filters what comes back. After ``seconds`` the adapter asks the robot
        to stop listening; the robot then has ``request_seconds`` to answer before it counts as
        lost."""
        api = self._connected()
        stopper = threading.Timer(seconds, self._stop_listening, args=(api,))
        stopper.daemon = True
        stopper.start()
        try:
            status = self._request(
                api.listen,
                "listening",
                seconds + self.options.request_seconds,
                language=self.options.language,
            )
        finally:
            stopper.cancel()
            stopper.join()
        message = (status.message or "").strip()
        if message in NOTHING_HEARD and message != "FAILED":
            return None
        if message == "FAILED" or status.success is False:
            log.warning("%s could not listen: %s", self.description, message)
            return None
        return Heard(message, RECOGNISED_CONFIDENCE)

    def wait_cue(self, seconds: float) -> Cue | None:
        """Wait at most ``seconds`` (plus one request) for a user to enter the robot's interaction
        space: a user id in ``GET /furhat/users`` that was not there at the previous look (since
        connecting). None when nobody entered, or when the robot is closed meanwhile."""
        deadline = time.monotonic() + seconds
        while True:
            api = self._api  # read before the check: close() sets the event, then drops the client
            if self._closed.is_set():
                return None
            if api is None:
                raise RobotLost(f"{self.description} is not connected")
            users = self._user_ids(api)
            entered = users - self._users_seen
            self._users_seen = users
            if entered:
                return Cue(source="user entered")
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return None
            self._closed.wait(min(self.options.poll_seconds, remaining))

    def close(self) -> None:
        """Release the client's connections (idempotent); a :meth:`wait_cue` returns None."""
        self._closed.set()
        api, self._api = self._api, None
        if api is not None:
            _release(api)

    # The vendor client, and each kind of request.

    def _new_client(self, failure: type[RobotError]) -> Any:
        try:
            import urllib3
            from furhat_remote_api import FurhatRemoteAPI
        except ImportError as error:
            raise failure(
                f"the Furhat client is not installed ({error.name}): "
                "pip install 'trustlab[robots]' or -r requirements-robots.lock"
            ) from error
        api = FurhatRemoteAPI(self.options.host)
        api.api_client.configuration.host = _base_url(self.options.host, self.options.port)
        api.api_client.rest_client.pool_manager = urllib3.PoolManager(
            num_pools=1, maxsize=4, retries=False
        )
        return api

    def _connected(self) -> Any:
        api = self._api
        if api is None:
            raise RobotLost(f"{self.description} is not connected")
        return api

    def _request(self, method: Callable[..., Any], action: str, read: float, **params: Any) -> Any:
        """One call of the vendor client, bounded; any failure is the robot lost."""
        try:
            return method(_request_timeout=(self.options.request_seconds, read), **params)
        except _transport_errors() as error:
            raise RobotLost(
                f"{self.description}: {_describe(error, read)} while {action}"
            ) from error

    def _get_list(
        self,
        api: Any,
        method: Callable[..., Any],
        path: str,
        key: str,
        failure: type[RobotError],
    ) -> list[str]:
        """The ``key`` of each item of a JSON list the robot answers on ``path``; anything else
        means the address is not Furhat's Remote API."""
        seconds = self.options.request_seconds
        try:
            response = method(_preload_content=False, _request_timeout=(seconds, seconds))
        except _transport_errors() as error:
            status = getattr(error, "status", None)
            if status:
                raise failure(self._not_furhat(f"HTTP {status} on {path}")) from error
            raise failure(
                f"{self.description}: {_describe(error, seconds)}; {START_HINT}"
            ) from error
        try:
            items = json.loads(response.data)
            return [str(item[key]) for item in items]
        except (ValueError, TypeError, KeyError, UnicodeDecodeError) as error:
            raise failure(self._not_furhat(f"{path} is not a list of {key}s")) from error

    def _not_furhat(self, evidence: str) -> str:
        return (
            f"{self.description} answers HTTP but not as Furhat's Remote API ({evidence}); "
            f"start the Remote API skill on the robot, or check the port (the skill's is "
            f"{REMOTE_API_PORT})"
        )

    def _set_voice(
        self, api: Any, voice: str, voices: list[str], failure: type[RobotError]
    ) -> None:
        if voice not in voices:
            shown = ", ".join(voices[:12]) + (", ..." if len(voices) > 12 else "")
            raise failure(f"{self.description} has no voice {voice!r}; its voices: {shown}")
        try:
            status = self._request(
                api.set_voice, "setting the voice", self.options.request_seconds, name=voice
            )
        except RobotLost as error:
            raise failure(str(error)) from error
        if status.success is False:
            raise failure(f"{self.description} did not take voice {voice!r}: {status.message}")

    def _gesture(self, api: Any, gesture: str) -> None:
        from swagger_client.rest import ApiException

        seconds = self.options.request_seconds
        try:
            status = api.gesture(name=gesture, blocking=False, _request_timeout=(seconds, seconds))
        except ApiException as error:
            status = None
            reason = f"HTTP {error.status}"
        except _transport_errors() as error:
            raise RobotLost(
                f"{self.description}: {_describe(error, seconds)} while starting a gesture"
            ) from error
        else:
            reason = status.message or "no reason given"
        if status is None or status.success is False:
            log.warning("%s did not do gesture %r (%s)", self.description, gesture, reason)

    def _led(self, api: Any, colour: Colour) -> None:
        """Set the LED ring; a colour the robot refuses is logged and left out, as a gesture."""
        red, green, blue = colour
        seconds = self.options.request_seconds
        status = self._request(
            api.set_led, "setting the LEDs", seconds, red=red, green=green, blue=blue
        )
        if status.success is False:
            log.warning("%s did not set its LEDs (%s)", self.description, status.message)

    def _stop_listening(self, api: Any) -> None:
        """Ask the robot to end the current listen (its answer then comes back to :meth:`listen`,
        whose own timeout reports a robot that does not answer)."""
        seconds = self.options.request_seconds
        try:
            api.listen_stop(_request_timeout=(seconds, seconds))
        except _transport_errors() as error:
            log.warning(
                "%s: could not stop listening: %s", self.description, _describe(error, seconds)
            )

    def _user_ids(self, api: Any) -> frozenset[str]:
        seconds = self.options.request_seconds
        response = self._request(
            api.get_users, "looking for users", seconds, _preload_content=False
        )
        try:
            return frozenset(str(user["id"]) for user in json.loads(response.data))
        except (ValueError, TypeError, KeyError, UnicodeDecodeError) as error:
            raise RobotLost(
                f"{self.description} answered /furhat/users with no list of users"
            ) from error


def _base_url(host: str, port: int) -> str:
    """The client's base URL (an IPv6 address goes in brackets)."""
    if ":" in host and not host.startswith("["):
        host = f"[{host}]"
    return f"http://{host}:{port}"


def _release(api: Any) -> None:
    """Close the client's connections and its thread pool (the vendor's ApiClient starts one).

    The pool is joined here, on the caller's thread: the vendor's ``ApiClient.__del__`` joins it
    too, and when the garbage collector happens to run that on one of the pool's own threads,
    the join raises ("cannot join current thread") in the middle of unrelated work."""
    api.api_client.rest_client.pool_manager.clear()
    api.api_client.pool.close()
    api.api_client.pool.join()


def _transport_errors() -> tuple[type[BaseException], ...]:
    """What a vendor call raises when the robot cannot be reached or answers an HTTP error (the
    vendor modules are imported by then: this runs only after :meth:`FurhatRobot.connect` built a
    client)."""
    import urllib3
    from swagger_client.rest import ApiException

    return (ApiException, urllib3.exceptions.HTTPError, OSError)


def _describe(error: BaseException, seconds: float) -> str:
    """The reason of a failed request, in a few words (``connection refused``)."""
    import urllib3

    status = getattr(error, "status", None)
    if status:
        return f"HTTP {status}"
    timed_out = urllib3.exceptions.TimeoutError
    if isinstance(error, timed_out) and not isinstance(
        error, urllib3.exceptions.NewConnectionError
    ):
        return f"no answer within {seconds:g} s"
    for cause in _causes(error):
        if isinstance(cause, http.client.RemoteDisconnected):
            return "the robot closed the connection"
        if isinstance(cause, OSError) and cause.strerror:
            return cause.strerror.lower()
    return type(error).__name__


def _causes(error: BaseException) -> Iterator[BaseException]:
    """The error, what it was raised from, and the exceptions it carries (urllib3 wraps the socket
    error in its arguments or its cause)."""
    seen: set[int] = set()
    pending = [error]
    while pending:
        current = pending.pop(0)
        if id(current) in seen:
            continue
        seen.add(id(current))
        yield current
        pending += [a for a in current.args if isinstance(a, BaseException)]
        pending += [e for e in (current.__cause__, current.__context__) if e is not None]
