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
    gesture: Callable[[str], str] = lambda given: given
    """How the stand-in records a protocol's gesture (NAOqi: as the line's annotations)."""
    recover: Callable[[Any], None] = lambda stand_in: None
    """Bring the robot back after a :class:`Drop` (NAOqi's stand-in closes its session)."""


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


def naoqi() -> Kind:
    from app.robots.naoqi import NaoqiOptions, NaoqiRobot
    from tests.robots.standins.naoqi import NaoqiStandIn

    return Kind(
        "naoqi",
        NaoqiStandIn,
        lambda stand_in: NaoqiRobot(NaoqiOptions(host=stand_in.host, port=stand_in.port)),
        gesture=lambda tag: f"^startTag({tag}) ^waitTag({tag})",
        recover=lambda stand_in: stand_in.start(),
    )


KINDS: dict[str, Callable[[], Kind]] = {"naoqi": naoqi, "furhat": furhat, "rosbridge": rosbridge}
