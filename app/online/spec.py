"""A protocol's ``[online]`` table: the study runs unattended from a public link.

A study that declares ``[online]`` can be joined at ``/join/STUDY`` by anyone a recruitment
platform (Prolific, MTurk, a lab's own panel) sends there: the platform's URL parameters name the
participant (``id_parameter``) and the server does what an experimenter does in the lab — it
enrols them, gives them a virtual station of their own and starts each session when they are
ready (app/online/participation.py). What the platform needs back (the completion URL with its
code, the screen-out URL) and what the lab promised its ethics board (a time limit, the devices
allowed, how many complete participants per condition) are declared here, checked when the
study is created like every other part of the protocol.
"""

from __future__ import annotations

from collections.abc import Sequence
from enum import StrEnum
from typing import Annotated

from pydantic import Field, StringConstraints

from app.spec_base import StrictSpec

ParameterName = Annotated[str, StringConstraints(pattern=r"^[A-Za-z][A-Za-z0-9_]{0,39}$")]
"""A URL parameter's name as platforms spell them (``PROLIFIC_PID``, ``workerId``)."""
WebAddress = Annotated[
    str, StringConstraints(strip_whitespace=True, pattern=r"^https?://[^\s]+$", max_length=500)
]
CompletionCode = Annotated[str, StringConstraints(pattern=r"^[A-Za-z0-9_-]{1,64}$")]

CODE_PLACEHOLDER = "{code}"
"""Written in ``completion_url`` where the completion code goes; without it the URL is used as
it is (a platform's URL that already names the code)."""


class DeviceKind(StrEnum):
    """What the participant's browser runs on, as the browser check tells it (app/online)."""

    DESKTOP = "desktop"
    """A computer with a keyboard: the room is walked with the arrow keys."""
    TABLET = "tablet"
    """A touch screen of at least a tablet's size: the room shows its on-screen pads."""
    PHONE = "phone"
    """A small touch screen."""


class OnlineSpec(StrictSpec):
    """Running the study from a public link, with no experimenter (docs/online.md)."""

    id_parameter: ParameterName = Field(
        default="PROLIFIC_PID",
        description="The URL parameter that carries the participant's recruitment ID "
        "(Prolific: PROLIFIC_PID; MTurk: workerId). Stored only as a keyed hash.",
    )
    parameters: list[ParameterName] = Field(
        default_factory=list,
        max_length=20,
        description="Further URL parameters kept with the participation (Prolific: STUDY_ID, "
        "SESSION_ID). A stratification factor's value is read from the parameter of its name.",
    )
    completion_url: WebAddress = Field(
        description="Where a participant who finished is sent back to; {code} is replaced by "
        "the completion code (Prolific: https://app.prolific.com/submissions/complete?cc={code})."
    )
    completion_code: CompletionCode = Field(
        description="The code the platform expects from participants who finished (also shown "
        "on the last page)."
    )
    screen_out_url: WebAddress | None = Field(
        default=None,
        description="Where a participant whose browser cannot run the study, or who arrives "
        "when it is full, is sent back to (none: they are told to return the study).",
    )
    time_limit_minutes: int = Field(
        default=60,
        ge=5,
        le=24 * 60,
        description="From joining to finishing; a return within it continues where they left "
        "off, after it the participation has expired.",
    )
    devices: list[DeviceKind] = Field(
        default_factory=lambda: [DeviceKind.DESKTOP],
        min_length=1,
        max_length=3,
        description="The devices allowed: desktop (keyboard), tablet and/or phone (touch).",
    )
    min_width: int = Field(
        default=1024, ge=320, le=4000, description="The smallest browser window, in CSS pixels."
    )
    min_height: int = Field(
        default=600, ge=320, le=4000, description="The smallest browser window's height."
    )
    target_per_condition: int | None = Field(
        default=None,
        ge=1,
        le=100_000,
        description="Complete participants wanted per condition in each stratum: enrolment "
        "closes when every condition has them (none: open until an admin closes the study).",
    )
    site: str | None = Field(
        default=None,
        description="In a study with [sites]: the site online participants belong to.",
    )

    def completion_link(self) -> str:
        """The URL a participant who finished is sent to."""
        return self.completion_url.replace(CODE_PLACEHOLDER, self.completion_code)


def check_online(
    online: OnlineSpec,
    *,
    stratify_by: Sequence[str],
    site_names: Sequence[str] | None,
) -> list[tuple[str, str]]:
    """Every problem of ``online`` in a protocol with these stratification factors and sites
    (None: no ``[sites]``), as (key path, reason)."""
    problems: list[tuple[str, str]] = []
    seen: set[str] = {online.id_parameter}
    for index, name in enumerate(online.parameters):
        if name in seen:
            why = "is the id_parameter" if name == online.id_parameter else "is listed twice"
            problems.append((f"online.parameters[{index}]", f"{name!r} {why}"))
        seen.add(name)
    if len(set(online.devices)) != len(online.devices):
        problems.append(("online.devices", "each device at most once"))
    for factor in stratify_by:
        if factor not in online.parameters:
            problems.append(
                (
                    "online.parameters",
                    f"the stratification factor {factor!r} must come from a URL parameter of "
                    "that name: add it here (and to the platform's link)",
                )
            )
    if site_names is None:
        if online.site is not None:
            problems.append(("online.site", "the protocol declares no [sites]"))
    elif online.site is None:
        problems.append(
            ("online.site", "a study with [sites]: name the site of online participants")
        )
    elif online.site not in site_names:
        problems.append(("online.site", f"{online.site!r} is not one of sites.names"))
    return problems
