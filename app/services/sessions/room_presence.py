"""The room's live state: where a station's room client last saw the participant.

A browser room client (static/js/room.js) reports the participant's position, heading and trigger
zone, and each line spoken, at most twice a second. Each report overwrites the station's one
``room_presence`` row, which names the participant seated at the time (so that erasure and
retention find it after they have left: app.services.privacy.personal_data), and announces itself on
the station's *room* topic, which only the operator console listens to: robots' WebSockets and
the study's dashboards (on the station and study topics) are not woken twice a second by someone
walking.
"""

from __future__ import annotations

from dataclasses import dataclass

from sqlalchemy import select
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.orm import Session

from app import events
from app.services.privacy import sites
from app.services.topics import room_topic_of, station_topic_of
from app.tables import RoomPresence, Station, utcnow

PRESENCE_CHANGED = "room_presence"
ZONE_ENTERED = "zone_entered"
"""Pushed to the station's robots when the participant steps into a trigger zone: a robot bridge
whose trigger is the room's presence asks that zone's category then."""


@dataclass(frozen=True)
class Said:
    """A line said in the room: ``kind`` is question, reply, robot or participant."""

    kind: str
    text: str


def record(
    db: Session,
    *,
    station_id: int,
    device_id: int | None,
    x: float,
    z: float,
    heading: float,
    zone: str | None,
    said: Said | None,
) -> None:
    """Store the participant's place (and a new line said, if any) as the station's presence;
    commits. One statement whichever engine: an insert that updates the row already there, so
    two clients of one station racing never meet a duplicate key. Stepping into a zone (from
    none or another) is also pushed to the station's robots, once: standing in it is not."""
    previous = db.get(RoomPresence, station_id)
    entered = zone is not None and zone != (previous.zone if previous is not None else None)
    now = utcnow()
    seated = db.scalar(select(Station.participant_id).where(Station.id == station_id))
    values: dict[str, object] = {
        "station_id": station_id,
        "device_id": device_id,
        "participant_id": seated,
        "x": x,
        "z": z,
        "heading": heading % 360.0,
        "zone": zone,
        "updated_at": now,
    }
    if said is not None:
        values |= {"utterance_kind": said.kind, "utterance": said.text, "utterance_at": now}
    elif previous is not None and previous.participant_id != seated:
        # The row names whoever sits there now: the last line said is the previous one's.
        values |= {"utterance_kind": None, "utterance": None, "utterance_at": None}
    dialect = postgresql if db.get_bind().dialect.name == "postgresql" else sqlite
    statement = dialect.insert(RoomPresence).values(values)
    changed = {name: statement.excluded[name] for name in values if name != "station_id"}
    db.execute(statement.on_conflict_do_update(index_elements=["station_id"], set_=changed))
    # Where the participant walks is their activity: it names their site, so that a console of
    # an account limited to other sites does not hear it (app.services.privacy.sites.reaches).
    site = sites.seated_site(db, station_id)
    events.publish(db, topics=[room_topic_of(station_id)], type=PRESENCE_CHANGED, site=site)
    if entered:
        events.publish(
            db, topics=[station_topic_of(station_id)], type=ZONE_ENTERED, zone=zone, site=site
        )
    db.commit()


def read(db: Session, *, station_id: int) -> RoomPresence | None:
    """The station's presence row, or None when no room client has reported yet."""
    return db.get(RoomPresence, station_id)
