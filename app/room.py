"""The escape room's floor plan: a protocol's ``[room]`` table, its checks and the default layout.

The browser room client (templates/room.html, static/js/room.js) draws the maze from this plan and
requests a category's prompt when the participant walks into that category's trigger zone, so a
zone outside the walls, two zones that overlap, or a category without a zone would silently cost
answers: all of them are refused when the study is created, with the key path and the reason.

Coordinates are metres on the floor: ``x`` from the left wall (0) to the right (``width``), ``z``
from the near wall (0) to the far one (``depth``). The outer walls are implied; ``walls`` are the
inner ones, as segments. A protocol without ``[room]`` gets :func:`default_room`: the seed paper's
set-up (a dotted start circle, an S-shaped path between two inner walls, the red button and the
solid exit circle) with its categories' zones spaced along the path in protocol order.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from typing import Annotated

from pydantic import Field

from app.spec_base import StrictSpec

Metres = Annotated[float, Field(allow_inf_nan=False)]
Radius = Annotated[float, Field(gt=0.0, le=10.0, allow_inf_nan=False)]


class Spot(StrictSpec):
    """A point on the floor (the red button, the keys, the robot)."""

    x: Metres
    z: Metres


class Circle(StrictSpec):
    """A circle on the floor (the start and the exit)."""

    x: Metres
    z: Metres
    radius: Radius = 0.6


class Wall(StrictSpec):
    """An inner wall from (x1, z1) to (x2, z2)."""

    x1: Metres
    z1: Metres
    x2: Metres
    z2: Metres


class Zone(StrictSpec):
    """Where walking in requests ``category``'s prompt."""

    category: Annotated[str, Field(pattern=r"^[a-z][a-z0-9_]{0,39}$")]
    x: Metres
    z: Metres
    radius: Radius = 0.6


class RoomSpec(StrictSpec):
    """The maze a browser room client draws."""

    width: Annotated[float, Field(ge=2.0, le=100.0, allow_inf_nan=False)]
    depth: Annotated[float, Field(ge=2.0, le=100.0, allow_inf_nan=False)]
    wall_height: Annotated[float, Field(gt=0.5, le=10.0, allow_inf_nan=False)] = 2.4
    start: Circle
    exit: Circle
    red_button: Spot
    robot: Spot
    keys: Spot | None = None
    walls: list[Wall] = Field(default_factory=list, max_length=200)
    zones: list[Zone] = Field(default_factory=list, max_length=50)

    def zone_for(self, category: str) -> Zone:
        """The zone of ``category`` (KeyError if it has none)."""
        for zone in self.zones:
            if zone.category == category:
                return zone
        raise KeyError(category)


def _outside(
    room: RoomSpec, x: float, z: float, radius: float = 0.0, what: str = "it"
) -> str | None:
    """Why a circle (or a point, radius 0) at (x, z) does not lie inside the maze, or None."""
    minus = f" - radius {radius:g}" if radius else ""
    plus = f" + radius {radius:g}" if radius else ""
    reasons = []
    if x - radius < 0.0:
        reasons.append(f"x {x:g}{minus} < 0")
    if x + radius > room.width:
        reasons.append(f"x {x:g}{plus} > width {room.width:g}")
    if z - radius < 0.0:
        reasons.append(f"z {z:g}{minus} < 0")
    if z + radius > room.depth:
        reasons.append(f"z {z:g}{plus} > depth {room.depth:g}")
    if not reasons:
        return None
    return f"{what} lies outside the maze ({'; '.join(reasons)})"


def _overlap(a: Zone | Circle, b: Zone | Circle) -> float | None:
    """The distance between the centres when the two circles overlap, else None."""
    distance = math.hypot(a.x - b.x, a.z - b.z)
    return distance if distance < a.radius + b.radius else None


def check_room(room: RoomSpec, categories: Sequence[str]) -> list[tuple[str, str]]:
    """Every problem of ``room`` for a protocol with these categories, as (key path, reason)."""
    problems: list[tuple[str, str]] = []
    for name in ("start", "exit"):
        circle: Circle = getattr(room, name)
        reason = _outside(room, circle.x, circle.z, circle.radius, f"the {name} circle")
        if reason:
            problems.append((f"room.{name}", reason))
    for name in ("red_button", "robot", "keys"):
        spot: Spot | None = getattr(room, name)
        if spot is not None and (reason := _outside(room, spot.x, spot.z, 0.0, name)):
            problems.append((f"room.{name}", reason))
    if (apart := _overlap(room.start, room.exit)) is not None:
        problems.append(("room.exit", f"overlaps the start circle (centres {apart:.2f} m apart)"))
    for index, wall in enumerate(room.walls):
        for end, (x, z) in (("start", (wall.x1, wall.z1)), ("end", (wall.x2, wall.z2))):
            if reason := _outside(room, x, z, 0.0, f"its {end}"):
                problems.append((f"room.walls[{index}]", reason))
        if math.hypot(wall.x2 - wall.x1, wall.z2 - wall.z1) < 0.05:
            problems.append((f"room.walls[{index}]", "a wall needs two different ends"))
    known = list(categories)
    seen: dict[str, int] = {}
    for index, zone in enumerate(room.zones):
        path = f"room.zones[{index}]"
        if zone.category not in known:
            problems.append(
                (
                    f"{path}.category",
                    f"no category {zone.category!r} in this protocol "
                    f"(categories: {', '.join(known)})",
                )
            )
        elif zone.category in seen:
            problems.append(
                (
                    f"{path}.category",
                    f"a second zone for {zone.category!r} (room.zones[{seen[zone.category]}]); "
                    "each category has one zone",
                )
            )
        else:
            seen[zone.category] = index
        if reason := _outside(room, zone.x, zone.z, zone.radius, "the zone"):
            problems.append((path, reason))
        for other in range(index):
            if (apart := _overlap(zone, room.zones[other])) is not None:
                problems.append(
                    (
                        path,
                        f"overlaps room.zones[{other}] ({room.zones[other].category!r}): centres "
                        f"{apart:.2f} m apart, radii {zone.radius:g} + "
                        f"{room.zones[other].radius:g}",
                    )
                )
        for name in ("start", "exit"):
            if (apart := _overlap(zone, getattr(room, name))) is not None:
                problems.append((path, f"overlaps the {name} circle (centres {apart:.2f} m apart)"))
    for category in known:
        if category not in seen:
            problems.append(("room.zones", f"no zone for category {category!r}"))
    return problems


# ------------------------------------------------------------------------------ the default layout

DEFAULT_WIDTH = 8.0
DEFAULT_DEPTH = 6.0
DEFAULT_PATH = ((1.35, 0.9), (1.35, 5.0), (4.0, 5.0), (4.0, 1.0), (6.65, 1.0), (6.65, 5.1))
"""The walk from the start circle to the exit: up the left corridor, through the far gap, down the
middle corridor, through the near gap and up the right corridor."""


def _along(path: Sequence[tuple[float, float]], fraction: float) -> tuple[float, float]:
    """The point ``fraction`` (0-1) of the way along the polyline ``path``."""
    legs = list(itertools.pairwise(path))
    lengths = [math.hypot(b[0] - a[0], b[1] - a[1]) for a, b in legs]
    remaining = fraction * sum(lengths)
    for (a, b), length in zip(legs, lengths, strict=True):
        if remaining <= length:
            t = remaining / length
            return (a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1]))
        remaining -= length
    return path[-1]


def default_room(categories: Sequence[str]) -> RoomSpec:
    """The seed paper's set-up for these categories: the zones are spaced evenly along the path
    between the start and the exit, in protocol order, small enough never to overlap."""
    count = max(1, len(categories))
    length = sum(math.dist(a, b) for a, b in itertools.pairwise(DEFAULT_PATH))
    spacing = length * 0.7 / count  # the zones fill the middle 70 % of the walk
    radius = round(min(0.7, spacing / 3.0), 2)  # a corner brings zones closer: spacing / √2
    zones = []
    for index, category in enumerate(categories):
        x, z = _along(DEFAULT_PATH, 0.15 + 0.7 * (index + 0.5) / count)
        zones.append(Zone(category=category, x=round(x, 2), z=round(z, 2), radius=radius))
    last = zones[-1] if zones else None
    return RoomSpec(
        width=DEFAULT_WIDTH,
        depth=DEFAULT_DEPTH,
        start=Circle(x=1.35, z=0.9, radius=0.6),
        exit=Circle(x=6.65, z=5.1, radius=0.6),
        red_button=Spot(x=7.85, z=4.2),
        robot=Spot(x=4.0, z=5.3),
        keys=Spot(x=min(7.85, last.x + 1.0), z=last.z) if last else None,
        walls=[Wall(x1=2.7, z1=0.0, x2=2.7, z2=4.0), Wall(x1=5.3, z1=2.0, x2=5.3, z2=6.0)],
        zones=zones,
    )
