"""The names of the live-event topics (app.events), in one module that imports nothing of ours.

Who listens to which: a study's pages and dashboard to its study topic; a station's operator
console, its robots' WebSockets, its room and a kiosk tablet to the station topic (the console's
room panel also to the room topic); a participant's tablet to the participant topic. They live
here, below every service, so that app.services.participants.participant_changes can name them all
while the services that publish changes (stations, questionnaires, erasure …) import it.
"""

from __future__ import annotations


def study_topic(study_id: int) -> str:
    """The event topic of a study (live dashboards and study pages listen to it)."""
    return f"study:{study_id}"


def station_topic_of(station_id: int) -> str:
    """The event topic of the station with this id (robot WebSockets, rooms, operator consoles
    and kiosk tablets listen to it)."""
    return f"station:{station_id}"


def participant_topic(participant_id: int) -> str:
    """The event topic of a participant (their tablet listens to it)."""
    return f"participant:{participant_id}"


def room_topic_of(station_id: int) -> str:
    """The event topic of a station's room (the operator console's room panel listens to it)."""
    return f"room:{station_id}"
