"""A participant's change, told to every view that shows them, from one place.

Every service that changes a participant as a whole — enrols, seats or unseats them, sets their
language, locks or unlocks their answers, withdraws, erases or anonymises them, or records their
answer to a new consent text — calls :func:`participant_changed` in the same transaction. It
publishes one event, ``participant_<change>``, on every topic of a view showing that
participant (app.services.topics):

- the study topic: the study's pages (participant table) and its dashboard;
- the participant topic: their tablet (personal link);
- the topic of the station they sit at, and of the one they were just unseated from: the
  operator console (its room panel with it), the robots' and the room's WebSockets (each reads
  the station's state again on any station event, app.api.station_ws) and a kiosk tablet.

Before this module each service chose its own topics, and some chose too few: an erasure told
the study's pages only, so a console kept offering the next session of someone erased, the room
kept saying "Session 2 comes next" and the tablet stayed where it was (issue 48).

The event carries the participant's site (app.services.privacy.sites.reaches: accounts limited to
other sites hear nothing of it) and, unless the change removed it, their code and station; an erased
or anonymised participant's event names nobody.
"""

from __future__ import annotations

from enum import StrEnum
from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session

from app import events
from app.services.privacy import sites
from app.services.topics import participant_topic, station_topic_of, study_topic
from app.tables import Participant, Station


class Change(StrEnum):
    """What happened to a participant; the event's type is ``participant_<value>``."""

    ENROLLED = "enrolled"
    SEATED = "assigned"
    UNSEATED = "unassigned"
    LANGUAGE = "language_set"
    LOCKED = "locked"
    UNLOCKED = "unlocked"
    WITHDRAWN = "withdrawn"
    ERASED = "erased"
    ANONYMISED = "anonymised"
    RECONSENTED = "reconsented"
    """They accepted a new version of the consent text (app.services.privacy.consent)."""
    CONSENT_DECLINED = "consent_declined"
    """They declined a new version of the consent text."""

    @property
    def event_type(self) -> str:
        """The type of the event announcing this change."""
        return f"participant_{self.value}"


NAMELESS = frozenset({Change.ERASED, Change.ANONYMISED})
"""Changes whose event carries no participant code: the code is what they removed."""

EVENT_TYPES = frozenset(change.event_type for change in Change)
"""Every participant change's event type (the tablet's script acts on two of them)."""


def _stations(db: Session, participant_id: int, also: Station | None) -> list[tuple[int, str]]:
    """(id, name) of the station the participant sits at now, and of ``also``."""
    seated = select(Station.id, Station.name).where(Station.participant_id == participant_id)
    found: dict[int, str] = {row[0]: row[1] for row in db.execute(seated)}
    if also is not None:
        found[also.id] = also.name
    return sorted(found.items())


def topics_of(participant: Participant, station_ids: list[int]) -> list[str]:
    """Every topic of a view showing ``participant``, seated at (or just gone from)
    ``station_ids``."""
    topics = [study_topic(participant.study_id), participant_topic(participant.id)]
    return topics + [station_topic_of(station_id) for station_id in station_ids]


def participant_changed(
    db: Session, participant: Participant, change: Change, *, station: Station | None = None
) -> None:
    """Announce ``change`` of ``participant`` to every view showing them; delivered when the
    caller's transaction commits (app.events), and not at all if it rolls back.

    ``station``: a station the participant no longer sits at but whose views showed them until
    this change (the one they were unseated from, by hand or by their erasure); the station
    they sit at now is found here."""
    seats = _stations(db, participant.id, station)
    data: dict[str, Any] = {"site": sites.event_site(participant)}
    if change not in NAMELESS:
        data["participant"] = participant.code
        if station is not None or seats:
            data["station"] = station.name if station is not None else seats[0][1]
    events.publish(
        db,
        topics=topics_of(participant, [station_id for station_id, _ in seats]),
        type=change.event_type,
        **data,
    )
