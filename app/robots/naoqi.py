"""A Pepper or NAO robot reached through NAOqi's own Python client, ``qi`` (libqi-python).

The robot speaks with ALTextToSpeech, listens with ALSpeechRecognition restricted to the
protocol's phrases (the result arrives as the ALMemory event ``WordRecognized``), and its cue to
ask is a touch of one of its tactile sensors (ALMemory touch events). A reply's LED colour, where
the protocol sets one, goes to an ALLeds group (``fadeRGB`` before the line, ``reset`` after).

Everything goes through qi's futures with a bound (:attr:`NaoqiOptions.call_seconds`): a robot
that stops answering turns into :class:`RobotLost` instead of a hung bridge, and a session that
drops (qi's ``disconnected`` signal) ends any wait at once.

NAOqi 2.5 accepts plain ``tcp://host:9559``; NAOqi 2.9 demands a login over TLS
(``tcps://host:9503``, user ``nao`` and the robot's password), which qi sends through a client
authenticator. Setting a password switches to the second form.
"""

from __future__ import annotations

import contextlib
import math
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from app.robots.robot import Colour, Cue, Heard, RobotError, RobotLost, RobotUnreachable

HEAD_SENSORS = ("FrontTactilTouched", "MiddleTactilTouched", "RearTactilTouched")
"""The three head sensors NAO and Pepper share: the default cue to ask."""

HAND_SENSORS = ("HandRightBackTouched", "HandLeftBackTouched")
"""The backs of the hands (NAO and Pepper): add these to let a participant touch a hand."""

RECOGNISER_SUBSCRIBER = "trustlab"
"""The name the bridge subscribes to ALSpeechRecognition under (visible on the robot)."""

PLAIN_TCP_PORT = 9559
TLS_PORT = 9503

SECONDS_PER_CHARACTER = 0.15
"""How long a spoken character may take, on top of :attr:`NaoqiOptions.call_seconds`, before a
``say`` counts as unanswered (speech runs at about 15 characters a second; this is generous)."""

_NETWORK_FAILURES = (
    "refused",
    "host not found",
    "no route",
    "unreachable",
    "timed out",
    "name or service",
)
"""Connection errors that mean the address is wrong or the robot is off, not the login."""


@dataclass(frozen=True)
class NaoqiOptions:
    """How to reach one NAOqi robot and how it should speak."""

    host: str = "127.0.0.1"
    """The robot's address (press Pepper's power button once, or NAO's chest button, to hear it).
    The default fits a virtual robot in Choregraphe or a bridge running on the robot itself."""

    port: int | None = None
    """None: NAOqi's own port for the protocol, 9559 (tcp) or 9503 (tcps, with a password)."""

    user: str = "nao"
    """The NAOqi 2.9 login (only sent with a password)."""

    password: str | None = None
    """The NAOqi 2.9 robot's password; setting it switches to ``tcps://`` and a login. NAOqi 2.5
    and earlier need none."""

    language: str = "English"
    """The language of speech and recognition, as NAOqi names it (``"English"``, ``"German"``)."""

    voice: str | None = None
    """A NAOqi voice name; None keeps the robot's default voice."""

    volume: float | None = None
    """Speech volume 0-1 (ALTextToSpeech.setVolume); None keeps the robot's setting."""

    animated: bool = True
    """Play the protocol's gestures with ALAnimatedSpeech; off: every line is plain speech and
    gestures are left out (a robot without ALAnimatedSpeech needs this)."""

    cue_events: tuple[str, ...] = HEAD_SENSORS
    """The ALMemory touch events that count as the participant's cue to ask."""

    led_group: str | None = "FaceLeds"
    """The ALLeds group that shows the protocol's colour for a reply's level (``FaceLeds``: the
    eyes of NAO and Pepper; ``ChestLeds``, ``AllLeds``, ...); None: LEDs are left alone."""

    call_seconds: float = 10.0
    """The most a connection or a single call may take before the robot counts as not answering."""

    client_logs: bool = False
    """Let the qi client print its own info and warning lines; off, it prints only errors (the
    adapter reports every failure itself, in one line). qi's log level is process-wide."""

    def __post_init__(self) -> None:
        if self.port is not None and not 0 < self.port < 65536:
            raise ValueError(f"port must be 1-65535, not {self.port}")
        if self.volume is not None and not 0.0 <= self.volume <= 1.0:
            raise ValueError(f"volume must be between 0 and 1, not {self.volume}")
        if not self.call_seconds > 0:
            raise ValueError(f"call_seconds must be positive, not {self.call_seconds}")

    @property
    def secure(self) -> bool:
        """True when the robot is reached the NAOqi 2.9 way (TLS and a login)."""
        return self.password is not None

    @property
    def url(self) -> str:
        """The qi URL of the robot's service directory."""
        scheme, default_port = ("tcps", TLS_PORT) if self.secure else ("tcp", PLAIN_TCP_PORT)
        return f"{scheme}://{self.host}:{self.port or default_port}"


class _Login:
    """qi's client authenticator: hands NAOqi 2.9 the user and password when asked."""

    def __init__(self, user: str, password: str) -> None:
        self._data = {"user": user, "token": password}

    def initialAuthData(self) -> dict[str, str]:  # noqa: N802 (the name qi calls)
        return dict(self._data)

    def _processAuth(self, _server_data: object) -> dict[str, str]:  # noqa: N802
        return {}


class LoginFactory:
    """What ``Session.setClientAuthenticatorFactory`` takes: one login per connection."""

    def __init__(self, user: str, password: str) -> None:
        self.user, self.password = user, password

    def newAuthenticator(self) -> _Login:  # noqa: N802 (the name qi calls)
        return _Login(self.user, self.password)


def annotate(text: str, gesture: str) -> str:
    """``text`` with ``gesture`` as ALAnimatedSpeech annotations.

    A gesture written as an annotation (starting with ``^``, e.g.
    ``^start(animations/Stand/Gestures/Yes_1)``) goes before the text unchanged. A gesture with a
    slash is an animation path: it starts with the words and the line ends when it does
    (``^start(path) text ^wait(path)``). Anything else is an animation tag (``affirmative``,
    ``hello``), played the same way with ``^startTag``/``^waitTag``."""
    gesture = gesture.strip()
    if gesture.startswith("^"):
        return f"{gesture} {text}"
    start, wait = ("start", "wait") if "/" in gesture else ("startTag", "waitTag")
    return f"^{start}({gesture}) {text} ^{wait}({gesture})"


def heard_from_event(value: object) -> Heard:
    """What a ``WordRecognized`` value says: NAOqi sends ``[words, confidence, ...]`` (the best
    guess first). Whatever else arrives becomes words with what could be read of it, and a
    confidence of 0 when none can: the vocabulary then finds it unclear, the bridge asks again."""
    if isinstance(value, list | tuple) and value:
        words = value[0] if isinstance(value[0], str) else str(value[0])
        confidence = _as_float(value[1]) if len(value) > 1 else 0.0
        return Heard(words, confidence)
    if isinstance(value, str):
        return Heard(value, 0.0)
    return Heard("" if value is None else str(value), 0.0)


def _as_float(value: object) -> float:
    if isinstance(value, int | float) and not isinstance(value, bool):
        return float(value)
    return 0.0


def _is_press(value: object) -> bool:
    """Touch events carry 1.0 when pressed and 0.0 when released; only a press is a cue."""
    return isinstance(value, int | float) and not math.isnan(value) and value > 0


def _cue_source(event: str) -> str:
    if "Tactil" in event:
        return "head touched"
    if event.startswith("Hand"):
        return "hand touched"
    return event


def _one_line(error: object) -> str:
    """The first line of a qi error (some carry a multi-line list of candidates)."""
    lines = [line.strip() for line in str(error).splitlines() if line.strip()]
    return lines[0][:200] if lines else "unknown error"


class NaoqiRobot:
    """A Pepper or NAO as the bridge's :class:`~app.robots.robot.Robot`.

    ``say`` uses ALTextToSpeech; a line with a gesture (and :attr:`NaoqiOptions.animated` on) goes
    to ALAnimatedSpeech with its body language otherwise off, so the only movement is the
    protocol's gesture (see :func:`annotate`): no contextual gestures blur the study's
    manipulation.
    ``listen`` restricts ALSpeechRecognition to the phrases and takes the first ``WordRecognized``.
    ``wait_cue`` counts a press of one of :attr:`NaoqiOptions.cue_events` while it waits; a touch
    while the robot speaks or listens does not queue another question.
    """

    def __init__(self, options: NaoqiOptions | None = None) -> None:
        self.options = options or NaoqiOptions()
        self.description = f"NAOqi robot at {self.options.url}"
        self._session: Any = None
        self._services: dict[str, Any] = {}
        self._keep: list[Any] = []  # ALMemory subscribers: their signals live as long as they do
        self._generation = 0
        self._connected_before = False
        self._changed = threading.Condition()
        self._lost: str | None = "never connected"
        self._listening = False
        self._heard: Heard | None = None
        self._waiting_cue = False
        self._cue: Cue | None = None

    # -- connection -------------------------------------------------------------------------

    def connect(self) -> None:
        failure: type[RobotError] = RobotLost if self._connected_before else RobotUnreachable
        self.close()
        try:
            import qi  # the robots extra is optional
            import qi.logging
        except ImportError:
            raise failure(
                "the NAOqi client `qi` is not installed: pip install 'trustlab[robots]'"
            ) from None
        qi.logging.setLevel(qi.logging.INFO if self.options.client_logs else qi.logging.ERROR)
        session = qi.Session()
        if self.options.password is not None:
            session.setClientAuthenticatorFactory(
                LoginFactory(self.options.user, self.options.password)
            )
        self._open(session, failure)
        with self._changed:
            self._generation += 1
            generation = self._generation
            self._session, self._lost = session, None
        session.disconnected.connect(lambda reason: self._on_disconnected(generation, reason))
        try:
            self._find_services(failure)
            self._prepare_voice(failure)
            self._subscribe_events(generation, failure)
        except RobotError:
            self.close()
            raise
        self._connected_before = True

    def _open(self, session: Any, failure: type[RobotError]) -> None:
        """Connect ``session`` within the bound; one line on failure, naming the address."""
        url, seconds = self.options.url, self.options.call_seconds
        future = session.connect(url, _async=True)
        if not _finished(future, seconds):
            future.cancel()
            raise failure(f"NAOqi at {url} did not answer within {seconds:g} s")
        if not future.hasError(0):
            return
        reason = _one_line(future.error(0))
        if any(marker in reason.lower() for marker in _NETWORK_FAILURES):
            # A NAOqi 2.9 robot refuses plain tcp: its only port is the TLS one.
            refused_plain = "refused" in reason.lower() and not self.options.secure
            also = " (NAOqi 2.9 wants its password, over tcps)" if refused_plain else ""
            raise failure(f"cannot reach NAOqi at {url}: {reason}{also}")
        if self.options.secure:
            hint = f"check NAOqi 2.9 credentials (user {self.options.user!r} and its password)"
        else:
            hint = "NAOqi 2.9 needs a login: give the robot's password (tcps, port 9503)"
        raise failure(f"NAOqi at {url} refused the connection ({reason}): {hint}")

    def _find_services(self, failure: type[RobotError]) -> None:
        needed = ["ALMemory", "ALTextToSpeech", "ALSpeechRecognition"]
        if self.options.animated:
            needed.append("ALAnimatedSpeech")
        for name in needed:
            future = self._session.service(name, _async=True)
            if not _finished(future, self.options.call_seconds):
                future.cancel()
                raise failure(f"{self.description} did not hand out {name} in time")
            if future.hasError(0):
                advice = " (turn animated speech off)" if name == "ALAnimatedSpeech" else ""
                raise failure(f"{self.description} has no {name} service{advice}")
            self._services[name] = future.value(0)
        if self.options.led_group is not None:  # optional: a robot without ALLeds still talks
            future = self._session.service("ALLeds", _async=True)
            if _finished(future, self.options.call_seconds) and not future.hasError(0):
                self._services["ALLeds"] = future.value(0)
            else:
                future.cancel()

    def _prepare_voice(self, failure: type[RobotError]) -> None:
        options = self.options
        self._call("ALTextToSpeech", "setLanguage", options.language, failure=failure)
        if options.voice is not None:
            self._call("ALTextToSpeech", "setVoice", options.voice, failure=failure)
        if options.volume is not None:
            self._call("ALTextToSpeech", "setVolume", float(options.volume), failure=failure)
        # The recogniser may be running for someone else (Autonomous Life, a dialog): pause it to
        # change its language, as NAOqi requires.
        self._call("ALSpeechRecognition", "pause", True, failure=failure)
        self._call("ALSpeechRecognition", "setLanguage", options.language, failure=failure)
        self._call("ALSpeechRecognition", "pause", False, failure=failure)

    def _subscribe_events(self, generation: int, failure: type[RobotError]) -> None:
        def on_word(value: object) -> None:
            self._on_word(generation, value)

        self._subscribe("WordRecognized", on_word, failure)
        for event in self.options.cue_events:
            self._subscribe(event, self._touch_handler(generation, event), failure)

    def _touch_handler(self, generation: int, event: str) -> Callable[[object], None]:
        def on_touch(value: object) -> None:
            self._on_touch(generation, event, value)

        return on_touch

    def _subscribe(
        self, event: str, handler: Callable[[object], None], failure: type[RobotError]
    ) -> None:
        subscriber = self._call("ALMemory", "subscriber", event, failure=failure)
        cannot_follow = f"{self.description}: cannot follow the ALMemory event {event}"
        try:
            future = subscriber.signal.connect(handler, _async=True)
        except (AttributeError, RuntimeError) as error:
            raise failure(f"{cannot_follow}: {_one_line(error)}") from None
        if not _finished(future, self.options.call_seconds):
            future.cancel()
            raise failure(f"{cannot_follow}: no answer in {self.options.call_seconds:g} s")
        if future.hasError(0):
            raise failure(f"{cannot_follow}: {_one_line(future.error(0))}")
        self._keep.append(subscriber)

    def close(self) -> None:
        with self._changed:
            session, self._session = self._session, None
            self._generation += 1
            self._services, self._keep = {}, []
            self._lost = "closed"
            self._changed.notify_all()
        if session is not None:
            with contextlib.suppress(RuntimeError):
                _finished(session.close(_async=True), self.options.call_seconds)

    # -- the bridge's calls ----------------------------------------------------------------

    def say(self, text: str, gesture: str | None = None, leds: Colour | None = None) -> None:
        seconds = self.options.call_seconds + SECONDS_PER_CHARACTER * len(text)
        group = self.options.led_group
        with self._changed:
            show = leds is not None and group is not None and "ALLeds" in self._services
        if show:
            assert leds is not None
            red, green, blue = leds
            self._call("ALLeds", "fadeRGB", group, (red << 16) | (green << 8) | blue, 0.0)
        if gesture and self.options.animated:
            configuration = {"bodyLanguageMode": "disabled"}
            annotated = annotate(text, gesture)
            self._call("ALAnimatedSpeech", "say", annotated, configuration, seconds=seconds)
        else:
            self._call("ALTextToSpeech", "say", text, seconds=seconds)
        if show:
            self._call("ALLeds", "reset", group)  # back to the robot's own colours

    def listen(self, phrases: Sequence[str], seconds: float) -> Heard | None:
        self._call("ALSpeechRecognition", "pause", True)
        self._call("ALSpeechRecognition", "setVocabulary", list(phrases), False)
        self._call("ALSpeechRecognition", "pause", False)
        with self._changed:
            self._heard, self._listening = None, True
        try:
            self._call("ALSpeechRecognition", "subscribe", RECOGNISER_SUBSCRIBER)
            with self._changed:
                self._changed.wait_for(
                    lambda: self._heard is not None or self._lost is not None, max(seconds, 0.0)
                )
                heard, lost = self._heard, self._lost
        finally:
            with self._changed:
                self._listening = False
        if lost is not None:
            raise RobotLost(f"{self.description} dropped the connection while listening ({lost})")
        self._call("ALSpeechRecognition", "unsubscribe", RECOGNISER_SUBSCRIBER)
        return heard

    def wait_cue(self, seconds: float) -> Cue | None:
        with self._changed:
            if self._lost is not None:
                raise RobotLost(f"{self.description} is not connected ({self._lost})")
            self._cue, self._waiting_cue = None, True
            try:
                self._changed.wait_for(
                    lambda: self._cue is not None or self._lost is not None, max(seconds, 0.0)
                )
                cue, lost = self._cue, self._lost
            finally:
                self._waiting_cue = False
        if lost is not None:
            raise RobotLost(f"{self.description} dropped the connection ({lost})")
        return cue

    # -- qi plumbing -----------------------------------------------------------------------

    def _call(
        self,
        service: str,
        method: str,
        *args: object,
        seconds: float | None = None,
        failure: type[RobotError] = RobotLost,
    ) -> Any:
        """``service.method(*args)`` on the robot, bounded; any failure as one line.

        A failed call leaves the connection lost (every later call and wait raises
        :class:`RobotLost` until :meth:`connect`): a robot half way through closing may still
        answer one call after refusing another, and the bridge should reconnect either way."""
        with self._changed:
            proxy, lost = self._services.get(service), self._lost
        if proxy is None or lost is not None:
            raise failure(f"{self.description} is not connected ({lost or 'never connected'})")
        bound = self.options.call_seconds if seconds is None else seconds
        try:
            future = getattr(proxy, method)(*args, _async=True)
        except (AttributeError, RuntimeError) as error:
            problem = _one_line(error)
        else:
            if not _finished(future, bound):
                future.cancel()
                problem = f"got no answer in {bound:g} s"
            elif future.hasError(0):
                problem = _one_line(future.error(0))
            else:
                return future.value(0)
        self._give_up(f"{service}.{method}: {problem}")
        raise failure(f"{self.description}: {service}.{method}: {problem}")

    def _give_up(self, reason: str) -> None:
        """Count the connection as lost (ends any wait on another thread)."""
        with self._changed:
            if self._lost is None:
                self._lost = reason
                self._changed.notify_all()

    def _on_disconnected(self, generation: int, reason: object) -> None:
        with self._changed:
            if generation == self._generation:
                self._lost = _one_line(reason) if str(reason).strip() else "disconnected"
                self._changed.notify_all()

    def _on_word(self, generation: int, value: object) -> None:
        heard = heard_from_event(value)
        with self._changed:
            if generation == self._generation and self._listening and self._heard is None:
                self._heard = heard
                self._changed.notify_all()

    def _on_touch(self, generation: int, event: str, value: object) -> None:
        if not _is_press(value):
            return
        with self._changed:
            if generation == self._generation and self._waiting_cue and self._cue is None:
                self._cue = Cue(source=_cue_source(event))
                self._changed.notify_all()


def _finished(future: Any, seconds: float) -> bool:
    """Wait for a qi future at most ``seconds``; True when it is no longer running."""
    future.wait(max(1, round(seconds * 1000)))
    return bool(future.isFinished())
