"""A stand-in Pepper: NAOqi's services on a standalone qi session on loopback.

It speaks real qi messaging (the ``qi`` library serves it), so the adapter's real client connects
to it as to a robot. ALTextToSpeech and ALAnimatedSpeech record what they are told into the
:class:`Script`; ALSpeechRecognition records its vocabulary and, each time it is subscribed to,
plays the participant's next reply: words raise ALMemory's ``WordRecognized`` with
``[words, confidence]`` as NAOqi does, silence raises nothing, and a drop closes the whole
session so the client sees the robot vanish. :meth:`NaoqiStandIn.touch_head` presses a head
sensor. ALLeds keeps the colour of one group (``FaceLeds``), recorded with each line said.

Authentication cannot be simulated: the Python binding offers no server-side authenticator, and a
standalone session cannot listen on ``tcps://`` without SSL configuration it does not expose. The
NAOqi 2.9 path is tested up to what the client does on its own (a TLS client against this plain
server fails, with the credentials hint).
"""

from __future__ import annotations

import re
import threading
from collections import deque
from collections.abc import Iterable
from types import TracebackType
from typing import Any

import qi

from tests.robots.standins.script import Drop, Script, Silence, Words, hex_colour

SERVICES = (
    "ALMemory",
    "ALTextToSpeech",
    "ALAnimatedSpeech",
    "ALSpeechRecognition",
    "ALLeds",
)
"""Everything the stand-in serves by default; pass fewer to play a robot without some."""

_ANNOTATION = re.compile(r"\^\w+\([^)]*\)")


class _Subscriber:
    """What ``ALMemory.subscriber(key)`` hands out on a robot: an object with a ``signal``."""

    def __init__(self, signal: Any) -> None:
        self.signal = signal


class StandInMemory:
    """ALMemory's events: one signal per key, raised by :meth:`raiseEvent`."""

    def __init__(self) -> None:
        self._signals: dict[str, Any] = {}
        self._values: dict[str, object] = {}
        self._lock = threading.Lock()

    def _signal(self, key: str) -> Any:
        with self._lock:
            if key not in self._signals:
                self._signals[key] = qi.Signal("m")
            return self._signals[key]

    @qi.bind(qi.Object, (qi.String,))
    def subscriber(self, key: str) -> _Subscriber:
        return _Subscriber(self._signal(key))

    def raiseEvent(self, key: str, value: object) -> None:
        with self._lock:
            self._values[key] = value
        self._signal(key)(value)

    def getData(self, key: str) -> object:
        with self._lock:
            return self._values.get(key)


class StandInTextToSpeech:
    """ALTextToSpeech: records each line and the voice settings."""

    def __init__(self, stand_in: NaoqiStandIn) -> None:
        self._stand_in = stand_in

    def say(self, text: str) -> None:
        self._stand_in.record("ALTextToSpeech.say", text)
        self._stand_in.script.record_said(text, None, self._stand_in.led)

    def setLanguage(self, language: str) -> None:
        self._stand_in.record("ALTextToSpeech.setLanguage", language)

    def setVoice(self, voice: str) -> None:
        self._stand_in.record("ALTextToSpeech.setVoice", voice)

    def setVolume(self, volume: float) -> None:
        self._stand_in.record("ALTextToSpeech.setVolume", volume)


class StandInAnimatedSpeech:
    """ALAnimatedSpeech: records the words, with the line's annotations as its gesture."""

    def __init__(self, stand_in: NaoqiStandIn) -> None:
        self._stand_in = stand_in

    def say(self, *args: object) -> None:
        text = str(args[0])
        self._stand_in.record("ALAnimatedSpeech.say", *args)
        annotations = _ANNOTATION.findall(text)
        words = " ".join(_ANNOTATION.sub(" ", text).split())
        self._stand_in.script.record_said(words, " ".join(annotations) or None, self._stand_in.led)


class StandInLeds:
    """ALLeds: ``fadeRGB(group, 0x00RRGGBB, seconds)`` colours a group, ``reset(group)`` gives it
    back its default; the stand-in keeps the colour of :attr:`NaoqiStandIn.led_group`."""

    def __init__(self, stand_in: NaoqiStandIn) -> None:
        self._stand_in = stand_in

    def fadeRGB(self, group: str, rgb: int, seconds: float) -> None:
        self._stand_in.record("ALLeds.fadeRGB", group, rgb, seconds)
        if group == self._stand_in.led_group:
            self._stand_in.led = hex_colour((rgb >> 16) & 0xFF, (rgb >> 8) & 0xFF, rgb & 0xFF)

    def reset(self, group: str) -> None:
        self._stand_in.record("ALLeds.reset", group)
        if group == self._stand_in.led_group:
            self._stand_in.led = None


class StandInSpeechRecognition:
    """ALSpeechRecognition: each subscription plays the participant's next reply."""

    def __init__(self, stand_in: NaoqiStandIn) -> None:
        self._stand_in = stand_in

    def pause(self, paused: bool) -> None:
        self._stand_in.record("ALSpeechRecognition.pause", paused)

    def setLanguage(self, language: str) -> None:
        self._stand_in.record("ALSpeechRecognition.setLanguage", language)

    def setVocabulary(self, phrases: list[str], word_spotting: bool) -> None:
        self._stand_in.record("ALSpeechRecognition.setVocabulary", list(phrases), word_spotting)
        self._stand_in.script.record_vocabulary(list(phrases))

    def subscribe(self, name: str) -> None:
        self._stand_in.record("ALSpeechRecognition.subscribe", name)
        self._stand_in.recognise()

    def unsubscribe(self, name: str) -> None:
        self._stand_in.record("ALSpeechRecognition.unsubscribe", name)


class NaoqiStandIn:
    """A Pepper on ``tcp://127.0.0.1:<free port>``, for ``with NaoqiStandIn(script) as robot``."""

    def __init__(self, script: Script | None = None, services: Iterable[str] = SERVICES) -> None:
        self.script = script or Script()
        self.services = tuple(services)
        self.memory = StandInMemory()
        self.led_group = "FaceLeds"
        self.led: str | None = None
        """The colour of :attr:`led_group` (``#rrggbb``), None while it is the robot's own."""
        self.calls: list[tuple[object, ...]] = []
        self.raw_events: deque[object] = deque()
        self._session: Any = None
        self._url = "tcp://127.0.0.1:0"
        self._lock = threading.Lock()
        self._dropping: threading.Thread | None = None

    @property
    def url(self) -> str:
        """Where the stand-in listens (the port is fixed at the first start)."""
        return self._url

    @property
    def host(self) -> str:
        return "127.0.0.1"

    @property
    def port(self) -> int:
        return int(self._url.rsplit(":", 1)[1])

    def __enter__(self) -> NaoqiStandIn:
        self.start()
        return self

    def __exit__(
        self,
        _type: type[BaseException] | None,
        _error: BaseException | None,
        _traceback: TracebackType | None,
    ) -> None:
        self.drop()

    def start(self) -> None:
        """Listen (again, on the same port after a drop) and register the services."""
        if self._dropping is not None:
            self._dropping.join(10.0)
        session = qi.Session()
        session.listenStandalone(self._url)
        self._url = session.endpoints()[0]
        made = {
            "ALMemory": lambda: self.memory,
            "ALTextToSpeech": lambda: StandInTextToSpeech(self),
            "ALAnimatedSpeech": lambda: StandInAnimatedSpeech(self),
            "ALSpeechRecognition": lambda: StandInSpeechRecognition(self),
            "ALLeds": lambda: StandInLeds(self),
        }
        for name in self.services:
            session.registerService(name, made[name]())
        with self._lock:
            self._session = session

    def drop(self) -> None:
        """Close the session: every client sees the robot disconnect (idempotent)."""
        with self._lock:
            session, self._session = self._session, None
        if session is not None:
            session.close()

    def record(self, *call: object) -> None:
        self.calls.append(call)

    def called(self, name: str) -> list[tuple[object, ...]]:
        """The arguments of every call of ``name`` (``"ALTextToSpeech.setLanguage"``)."""
        return [call[1:] for call in self.calls if call[0] == name]

    def recognise(self) -> None:
        """The participant's turn: a queued raw event first, else the script's next reply."""
        if self.raw_events:
            self.memory.raiseEvent("WordRecognized", self.raw_events.popleft())
            return
        reply = self.script.next_reply()
        if isinstance(reply, Words):
            self.memory.raiseEvent("WordRecognized", [reply.words, reply.confidence])
        elif isinstance(reply, Drop):
            # Not from the serving thread: closing waits for the calls in progress.
            self._dropping = threading.Thread(target=self.drop, daemon=True)
            self._dropping.start()
        else:
            assert isinstance(reply, Silence)

    def touch_head(self, sensor: str = "FrontTactilTouched") -> None:
        """A press and release of a head sensor (1.0, then 0.0, as NAOqi raises them)."""
        self.memory.raiseEvent(sensor, 1.0)
        self.memory.raiseEvent(sensor, 0.0)
