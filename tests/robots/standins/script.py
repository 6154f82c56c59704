"""What every stand-in robot shares: a scripted participant and a record of what it was told.

A stand-in speaks its robot's own protocol on loopback (NAOqi's qi messaging, Furhat's Remote API
over HTTP, rosbridge v2 over a WebSocket), so the bridge's real vendor client talks to it. Each
time the bridge listens, the stand-in takes the participant's next :class:`Reply` from the
script: words with a confidence, silence, or a dropped connection. Everything the robot is told
to say lands in :attr:`Script.said`, in order, so tests check the words spoken.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass, field


@dataclass(frozen=True)
class Words:
    """The recogniser hears ``words`` with ``confidence``."""

    words: str
    confidence: float = 0.9


@dataclass(frozen=True)
class Silence:
    """Nothing is heard before the listening time is up."""


@dataclass(frozen=True)
class Drop:
    """The robot's connection drops while the bridge listens (the stand-in closes it)."""


Reply = Words | Silence | Drop


@dataclass(frozen=True)
class Said:
    """A line the robot was told to say, with the gesture that went with it (if any) and the
    colour its LEDs showed while it was said (``#rrggbb``; None: the robot's own)."""

    text: str
    gesture: str | None = None
    leds: str | None = None


def hex_colour(red: float, green: float, blue: float) -> str:
    """``#rrggbb`` of 0-255 parts (as a stand-in records a colour)."""
    return "#" + "".join(f"{round(part):02x}" for part in (red, green, blue))


@dataclass
class Script:
    """The participant's replies in order, and what the robot said and was asked to listen for.

    Thread-safe: stand-ins serve on their own threads. :meth:`wait_said` lets a test wait for a
    line without sleeping."""

    replies: deque[Reply] = field(default_factory=deque)
    said: list[Said] = field(default_factory=list)
    vocabularies: list[list[str]] = field(default_factory=list)
    said_at: list[float] = field(default_factory=list)
    """``time.perf_counter()`` of each line in :attr:`said` (bench/bridge.py's latencies)."""
    heard_at: list[float] = field(default_factory=list)
    """``time.perf_counter()`` of each :class:`Words` handed to the recogniser."""
    drop_says: set[int] = field(default_factory=set)
    """Which requests to say a line (1 for the first, counting dropped ones) drop the robot's
    connection instead of saying it (a robot lost while it speaks)."""
    says: int = 0
    _changed: threading.Condition = field(default_factory=threading.Condition)

    def add(self, *replies: Reply | str) -> None:
        """Queue replies; a plain string is :class:`Words` with confidence 0.9."""
        with self._changed:
            self.replies.extend(Words(r) if isinstance(r, str) else r for r in replies)

    def next_reply(self) -> Reply:
        """The participant's next reply (silence once the script is used up)."""
        with self._changed:
            reply = self.replies.popleft() if self.replies else Silence()
            if isinstance(reply, Words):
                self.heard_at.append(time.perf_counter())
            return reply

    def say_drops(self) -> bool:
        """Count a request to say a line; True when it is one of :attr:`drop_says`: the stand-in
        then drops the connection and nothing is said."""
        with self._changed:
            self.says += 1
            return self.says in self.drop_says

    def record_said(self, text: str, gesture: str | None = None, leds: str | None = None) -> None:
        with self._changed:
            self.said.append(Said(text, gesture, leds))
            self.said_at.append(time.perf_counter())
            self._changed.notify_all()

    def record_vocabulary(self, phrases: list[str]) -> None:
        with self._changed:
            self.vocabularies.append(list(phrases))

    def wait_said(self, count: int, timeout: float = 30.0) -> list[Said]:
        """Wait until at least ``count`` lines were said; raise AssertionError after ``timeout``
        (a bound against hangs, not a timing expectation)."""
        with self._changed:
            if not self._changed.wait_for(lambda: len(self.said) >= count, timeout):
                raise AssertionError(f"only {len(self.said)} lines said: {self.said}")
            return list(self.said)
