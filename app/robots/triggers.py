"""What makes a bridged robot ask a question, apart from the bridge that acts on it.

An enumeration of the standard library only, so that ``trustlab bridge … --help`` can offer the
triggers as choices without loading the bridge's HTTP and WebSocket clients (app.robots.bridge
re-exports it, for everything else)."""

from __future__ import annotations

from enum import StrEnum


class Trigger(StrEnum):
    """What makes the robot ask a category's question (the console's "ask now" always does)."""

    PRESENCE = "presence"
    """The room client reports the participant stepping into that category's zone."""
    ROBOT = "robot"
    """The robot's own cue: a touch, a user in view, a ROS message."""
    CONSOLE = "console"
    """Only the operator console's Wizard-of-Oz prompts."""
