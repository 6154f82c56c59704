"""A protocol's ``[quality]`` table: which answers count as careless, and which of those a study
leaves out of its analysis.

Unattended participants (online, but also a busy lab's tablet) sometimes answer without reading.
The literature's usual signs are recorded for every participant (app/services/participants/
data_quality.py computes them from what is stored):

- failed **attention checks**: items declared with the answer an attentive participant gives
  (``expected`` on a questionnaire item);
- **speeding**: a questionnaire page answered in less than ``min_seconds_per_item`` seconds per
  item (2 s per item after Huang et al., 2012, *J. Bus. Psychol.* 27, 99–114);
- **straight-lining**: the same point given to every Likert item of a page that has at least
  ``straightlining_min_items`` of them;
- **time away** from the tab (questionnaire pages and the room), in all;
- a **second recruitment ID** from a browser that had joined the study already (online studies).

Each sign becomes a flag by the thresholds below; ``exclude`` names the flags that leave a
participant out of every analysis. The rules are part of the protocol, so they are fixed before
the first participant, and ``trustlab prereg`` registers them with the rest of the plan.
"""

from __future__ import annotations

from collections.abc import Sequence
from enum import StrEnum

from pydantic import Field

from app.spec_base import StrictSpec


class Flag(StrEnum):
    """A sign of careless answering, as exports and pages name it."""

    ATTENTION = "attention"
    """More attention checks failed than ``attention_failures_allowed``."""
    SPEEDING = "speeding"
    """A questionnaire page answered faster than ``min_seconds_per_item`` per item."""
    STRAIGHTLINING = "straightlining"
    """One point given to every Likert item of a page of at least ``straightlining_min_items``."""
    AWAY = "away"
    """Away from the study's tab for longer than ``max_away_seconds`` in all."""
    SECOND_ID = "second_id_same_browser"
    """An online participant whose browser had joined the study under another recruitment ID."""


class QualitySpec(StrictSpec):
    """What counts as careless answering, and what a study does about it (docs/online.md)."""

    min_seconds_per_item: float = Field(
        default=2.0,
        ge=0.0,
        le=60.0,
        allow_inf_nan=False,
        description="A questionnaire page answered in less than this many seconds per item is "
        "flagged 'speeding' (0: never).",
    )
    straightlining_min_items: int = Field(
        default=5,
        ge=2,
        le=200,
        description="A page with at least this many Likert items, all given the same point, is "
        "flagged 'straightlining'.",
    )
    max_away_seconds: float | None = Field(
        default=120.0,
        ge=0.0,
        allow_inf_nan=False,
        description="Away from the study's tab (another tab or window in front) for longer than "
        "this in all is flagged 'away' (none: never).",
    )
    attention_failures_allowed: int = Field(
        default=0,
        ge=0,
        description="How many attention checks a participant may fail before being flagged "
        "'attention'.",
    )
    exclude: list[Flag] = Field(
        default_factory=list,
        description="The flags that leave a participant out of every analysis (listed with the "
        "reason, and registered by trustlab prereg); none: flagged only.",
    )


def check_quality(
    quality: QualitySpec, *, attention_checks: int, online: bool
) -> list[tuple[str, str]]:
    """Every problem of ``quality`` in a protocol with this many attention-check items, online
    or not, as (key path, reason)."""
    problems: list[tuple[str, str]] = []
    if len(set(quality.exclude)) != len(quality.exclude):
        problems.append(("quality.exclude", "each flag at most once"))
    if Flag.ATTENTION in quality.exclude and not attention_checks:
        problems.append(
            (
                "quality.exclude",
                "'attention' needs attention checks: give an item its expected answer",
            )
        )
    elif attention_checks and quality.attention_failures_allowed >= attention_checks:
        problems.append(
            (
                "quality.attention_failures_allowed",
                f"the questionnaires have {attention_checks} attention check(s): allowing as many "
                "failures flags no one",
            )
        )
    if Flag.SECOND_ID in quality.exclude and not online:
        problems.append(
            ("quality.exclude", f"{Flag.SECOND_ID.value!r} is for online studies ([online])")
        )
    return problems


def flag_names(flags: Sequence[Flag]) -> str:
    """Flags as one export cell: their names, in :class:`Flag` order, joined by ``;``."""
    return ";".join(flag.value for flag in Flag if flag in flags)
