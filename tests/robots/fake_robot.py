"""An in-process robot for the bridge loop's own tests: the same scripted participant as the
stand-ins (tests/robots/standins/script.py), without a vendor protocol in between. The vendor
adapters are tested end to end against their stand-ins in test_bridges_end_to_end.py."""

from __future__ import annotations

import queue
import threading
from collections.abc import Sequence

from app.robots.robot import Colour, Cue, Heard, RobotLost, RobotUnreachable
from tests.robots.standins.script import Drop, Script, Silence, Words, hex_colour


class FakeRobot:
    """A robot that says into ``script.said`` and hears ``script``'s replies; a :class:`Drop`
    loses it until the bridge connects again (``refuse_connects`` refuses that many)."""

    description = "the fake robot"

    def __init__(self, script: Script, *, refuse_connects: int = 0) -> None:
        self.script = script
        self.connects = 0
        self.attempts = 0
        """Calls of :meth:`connect`, refused ones included (``connects``: the ones that worked)."""
        self.refuse_connects = refuse_connects
        self.away = threading.Event()
        """While set, connecting fails (the robot is lost and stays away)."""
        self.away_after_drop = False
        """A drop (while listening, or saying: ``Script.drop_says``) sets :attr:`away`."""
        self.cues: queue.Queue[Cue] = queue.Queue()
        self.listening = threading.Event()
        """Set while :meth:`listen` waits for :attr:`release` (when ``hold`` is set)."""
        self.release = threading.Event()
        self.hold = False
        """Make each listen wait for :attr:`release` before it hears the next reply."""
        self._connected = False
        self._lock = threading.Lock()

    def connect(self) -> None:
        with self._lock:
            self.attempts += 1
            if self.refuse_connects > 0:
                self.refuse_connects -= 1
                raise RobotUnreachable("the fake robot refused the connection")
            if self.away.is_set():
                raise RobotLost("the fake robot is still away")
            self.connects += 1
            self._connected = True

    def _check(self) -> None:
        with self._lock:
            if not self._connected:
                raise RobotLost("the fake robot is not connected")

    def say(self, text: str, gesture: str | None = None, leds: Colour | None = None) -> None:
        self._check()
        if self.script.say_drops():
            with self._lock:
                self._connected = False
                if self.away_after_drop:
                    self.away.set()
            raise RobotLost("the fake robot dropped the connection while speaking")
        self.script.record_said(text, gesture, hex_colour(*leds) if leds else None)

    def listen(self, phrases: Sequence[str], seconds: float) -> Heard | None:
        self._check()
        self.script.record_vocabulary(list(phrases))
        if self.hold:
            self.listening.set()
            if not self.release.wait(60.0):
                raise RobotLost("the fake robot was never released")
            self.release.clear()
        reply = self.script.next_reply()
        if isinstance(reply, Drop):
            with self._lock:
                self._connected = False
                if self.away_after_drop:
                    self.away.set()
            raise RobotLost("the fake robot dropped the connection")
        if isinstance(reply, Silence):
            return None
        assert isinstance(reply, Words)
        return Heard(reply.words, reply.confidence)

    def wait_cue(self, seconds: float) -> Cue | None:
        try:
            return self.cues.get(timeout=seconds)
        except queue.Empty:
            return None

    def close(self) -> None:
        with self._lock:
            self._connected = False
