"""What a bridge needs of a robot, whatever its vendor: say a line, listen for one of a few
phrases, and report its own cue to ask (a touch, a user in view, a ROS message).

The methods block (every vendor client here is synchronous or runs its own event loop in a thread);
the bridge calls them from worker threads, so an adapter must allow :meth:`Robot.wait_cue` on one
thread while another says or listens. Every wait is bounded: a robot that stops answering raises
:class:`RobotLost` instead of hanging the bridge.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

from app.speech.vocabulary import Heard

__all__ = ["Colour", "Cue", "Heard", "Robot", "RobotError", "RobotLost", "RobotUnreachable"]

Colour = tuple[int, int, int]
"""An LED colour: red, green, blue, each 0-255."""


def colour_of(hex_colour: str) -> Colour:
    """``#rrggbb`` (the protocol's form) as red, green and blue."""
    value = int(hex_colour.removeprefix("#"), 16)
    return (value >> 16) & 0xFF, (value >> 8) & 0xFF, value & 0xFF


class RobotError(Exception):
    """A robot problem, as one line a lab can act on (``str(error)`` is that line)."""


class RobotUnreachable(RobotError):
    """The bridge cannot start with this robot: wrong address, connection or authentication
    refused, a missing topic or service, a vendor client that is not installed."""


class RobotLost(RobotError):
    """The robot was reachable but stopped answering; the bridge reconnects."""


@dataclass(frozen=True)
class Cue:
    """The robot's own signal to ask a question: ``category`` names one when the cue says which
    (a ROS message can), else None: ask the category the station expects next."""

    category: str | None = None
    source: str = ""


class Robot(Protocol):
    """One robot, reached through its vendor's own client library."""

    description: str
    """Where the robot is, for the bridge's messages (``Furhat at 10.0.0.5:54321``)."""

    def connect(self) -> None:
        """Reach the robot and check it has what the bridge uses; raise :class:`RobotUnreachable`
        (at start) or :class:`RobotLost` (on a reconnection) with one line otherwise."""

    def say(self, text: str, gesture: str | None = None, leds: Colour | None = None) -> None:
        """Say ``text`` with the robot's own text-to-speech and return when it has been said;
        ``gesture`` (the protocol's, for the reply's level) goes with it when given, and so does
        ``leds``: the robot's LEDs show that colour while it speaks, then go back to its own."""

    def listen(self, phrases: Sequence[str], seconds: float) -> Heard | None:
        """Listen for one of ``phrases`` with the robot's recogniser, at most ``seconds``; None
        when nothing was heard (silence)."""

    def wait_cue(self, seconds: float) -> Cue | None:
        """Wait at most ``seconds`` for the robot's own cue to ask; None when none came. Called
        only when the bridge's trigger is the robot's cue."""

    def close(self) -> None:
        """Release the connection (idempotent)."""
