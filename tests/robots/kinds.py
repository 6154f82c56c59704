"""The robot kinds a bridge supports, each as its stand-in and its real adapter pointed at it:
shared by the end-to-end tests and bench/bridge.py."""

from __future__ import annotations

import contextlib
import dataclasses
from collections.abc import Callable
from typing import Any

from app.robots.robot import Robot
from tests.robots.standins.script import Script


@dataclasses.dataclass(frozen=True)
class Kind:
    """A robot kind: its stand-in (a context manager given the script) and its adapter."""

    name: str
    stand_in: Callable[[Script], contextlib.AbstractContextManager[Any]]
    robot: Callable[[Any], Robot]
    confidence: Callable[[float], float] = lambda given: given
    """The confidence the bridge stores for a scripted one (Furhat reports none)."""


def furhat() -> Kind:
    from app.robots.furhat import FurhatOptions, FurhatRobot
    from tests.robots.standins.furhat import FurhatStandIn

    return Kind(
        "furhat",
        FurhatStandIn,
        lambda stand_in: FurhatRobot(FurhatOptions(host=stand_in.host, port=stand_in.port)),
        confidence=lambda given: 1.0,
    )


def rosbridge() -> Kind:
    from app.robots.rosbridge import RosbridgeOptions, RosbridgeRobot
    from tests.robots.standins.rosbridge import RosbridgeStandIn

    return Kind(
        "rosbridge",
        RosbridgeStandIn,
        lambda stand_in: RosbridgeRobot(
            RosbridgeOptions(host="127.0.0.1", port=stand_in.port, listen_grace=0.3)
        ),
    )


KINDS: dict[str, Callable[[], Kind]] = {"furhat": furhat, "rosbridge": rosbridge}
