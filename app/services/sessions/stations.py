"""Stations, the device keys of their robot clients, and who is assigned to them.

A robot works against a station, not a participant: the experimenter assigns a participant to the
station and the robot's key only ever reaches whoever is assigned there. Keys are shown once at
creation; only their SHA-256 is stored, so a leaked database does not leak working keys.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import timedelta
from typing import Any

from sqlalchemy import delete, select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from app import events
from app.errors import Conflict, InvalidInput, NotAuthenticated, NotFound
from app.inputs import STATION_NAME
from app.security import new_token, token_digest
from app.services import audit
from app.services.audit import Actor
from app.services.participants import participant_changes
from app.services.participants.participant_changes import Change
from app.services.privacy import sites
from app.services.sessions import step_store
from app.services.topics import station_topic_of
from app.sql import Cursor
from app.tables import (
    Device,
    DeviceSocket,
    Participant,
    ParticipantStatus,
    SessionStatus,
    Station,
    Study,
    StudySession,
    utcnow,
)

KEY_PREFIX = "tlk_"
ONLINE_STATIONS = "online-"
"""The names of online participants' virtual stations begin so (app.online.participation)."""
DEVICE_REVOKED = "device_revoked"
DEVICE_CONNECTION = "device_connection"
DEVICE_NOTICE = "device_notice"
CONSOLE_ONLY = frozenset({DEVICE_CONNECTION, DEVICE_NOTICE})
"""Events on a station's topic for its operator console only: robots are not woken by them."""
NOTICE_MAX_LENGTH = 300
"""The station event announcing a revoked key (data: ``device_id``): every worker closes that
device's open WebSocket at once (app.api.station_ws)."""
KEY_MAX_LENGTH = 200
"""The longest bearer value taken for a device key (issued keys have 47 characters). The REST
dependency and :func:`authenticate_seat` both refuse longer ones unhashed: one limit, so a key
that passes the first check is never turned away by the second."""


def station_topic(station: Station) -> str:
    """The event topic of a station (robot WebSockets and operator consoles listen to it)."""
    return station_topic_of(station.id)


def get_station(db: Session, name: str, *, for_update: bool = False) -> Station:
    """The station with this name; NotFound names the existing ones."""
    query = select(Station).where(Station.name == name)
    if for_update:
        query = query.with_for_update()
    station = db.scalar(query)
    if station is None:
        known = db.scalars(select(Station.name).order_by(Station.name).limit(10)).all()
        hint = f"; stations: {', '.join(known)}" if known else "; no station exists yet"
        raise NotFound(f"no station named {name!r}{hint}")
    return station


def list_stations(db: Session, *, archived: bool | None = None) -> list[Station]:
    """The lab's stations by name: every one (``archived=None``), or only the shown or archived
    ones. Online participants' own stations are not the lab's: the online monitor shows them."""
    query = select(Station).where(Station.online.is_(False)).order_by(Station.name)
    if archived is not None:
        hidden = Station.archived_at.is_not(None)
        query = query.where(hidden if archived else ~hidden)
    return list(db.scalars(query))


def set_archived(db: Session, *, station_name: str, archived: bool, actor: Actor) -> Station:
    """Hide a station from the station list (the bots' stations after the demo), or show it
    again; commits. A station with someone seated is freed first, so nobody is left at a station
    nobody sees; its keys keep working and its log stays."""
    station = get_station(db, station_name, for_update=True)
    if (station.archived_at is not None) == archived:
        return station
    if archived and station.participant_id is not None:
        raise Conflict(f"station {station.name!r} has a participant seated: free it first")
    station.archived_at = utcnow() if archived else None
    audit.record(
        db,
        actor=actor,
        action="station.archived" if archived else "station.unarchived",
        subject=station.name,
    )
    db.commit()
    return station


def set_station_study(db: Session, *, station_name: str, study: Study, actor: Actor) -> Station:
    """Tie a station's console to a study: it seats that study's participants without asking
    (app.web.stations); commits. The seated participant, if any, stays."""
    station = get_station(db, station_name, for_update=True)
    _tie(db, station, study, actor)
    db.commit()
    return station


def _tie(db: Session, station: Station, study: Study, actor: Actor) -> None:
    """Record that ``station`` runs ``study`` (before commit)."""
    if station.study_id == study.id:
        return
    station.study_id = study.id
    audit.record(
        db, actor=actor, action="station.study_set", study_id=study.id, subject=station.name
    )


def seating_questions(db: Session, *, station: Station, participant: Participant) -> list[str]:
    """What an experimenter should confirm before seating ``participant`` here, in words.

    Typing a code into the wrong console or the wrong study costs a session: a participant who has
    finished, one of another study than the station's, or one seated at another station is seated
    only once someone says so. Empty: seat at once."""
    questions = []
    if station.study_id is not None and participant.study_id != station.study_id:
        own = db.get(Study, station.study_id)
        theirs = db.get(Study, participant.study_id)
        assert own is not None and theirs is not None
        questions.append(
            f"{participant.code} is in the study {theirs.title!r} ({theirs.name}), "
            f"but this station runs {own.title!r} ({own.name})."
        )
    if participant.status == ParticipantStatus.COMPLETED:
        questions.append(f"{participant.code} has finished the study: every session is done.")
    elsewhere = db.scalar(
        select(Station.name).where(
            Station.participant_id == participant.id, Station.id != station.id
        )
    )
    if elsewhere is not None:
        questions.append(
            f"{participant.code} is seated at station {elsewhere!r}; seating them here frees it."
        )
    return questions


def create_station(db: Session, *, name: str, actor: Actor, site: str | None = None) -> Station:
    """Create a station, of ``site`` (empty: shared by every site); commits."""
    STATION_NAME.check(name)
    if name.startswith(ONLINE_STATIONS):
        raise InvalidInput(
            f"station names beginning with {ONLINE_STATIONS!r} are kept for online participants' "
            "own stations: choose another name"
        )
    site = sites.station_site(db, site)
    if db.scalar(select(Station.id).where(Station.name == name)) is not None:
        raise Conflict(f"a station named {name!r} already exists")
    station = Station(name=name, site=site)
    db.add(station)
    try:
        db.flush()  # PostgreSQL: a concurrent creation of the same name is refused here
    except IntegrityError:
        db.rollback()
        raise Conflict(f"a station named {name!r} already exists") from None
    audit.record(db, actor=actor, action="station.created", subject=name, details={"site": site})
    db.commit()
    return station


def set_station_site(db: Session, *, station_name: str, site: str | None, actor: Actor) -> Station:
    """Give a station a site, or make it shared (``site`` empty); commits. Refused while a
    participant of another site is seated there, as seating them would be."""
    station = get_station(db, station_name, for_update=True)
    site = sites.station_site(db, site)
    if station.site == site:
        return station
    if station.participant_id is not None:
        seated = db.get(Participant, station.participant_id)
        assert seated is not None
        sites.check_seating(station, seated, site)
    before = station.site
    station.site = site
    audit.record(
        db,
        actor=actor,
        action="station.site_set",
        subject=station.name,
        details={"from": before, "to": site},
    )
    db.commit()
    return station


@dataclass(frozen=True)
class IssuedKey:
    """A new device and its key (shown once, never stored)."""

    device: Device
    key: str


def issue_device_key(db: Session, *, station_name: str, label: str, actor: Actor) -> IssuedKey:
    """Create a device key for a station; commits."""
    station = get_station(db, station_name)
    label = label.strip() or "robot"
    if len(label) > 64:
        raise InvalidInput("a device label has at most 64 characters")
    key = KEY_PREFIX + new_token(32)
    device = Device(
        station_id=station.id,
        label=label,
        key_hash=token_digest(key),
        key_prefix=key[: len(KEY_PREFIX) + 6],
        created_by=actor.name,
    )
    db.add(device)
    db.flush()
    audit.record(
        db,
        actor=actor,
        action="device.key_issued",
        subject=f"{station.name}/{label}",
        details={"device_id": device.id, "key_prefix": device.key_prefix},
    )
    db.commit()
    return IssuedKey(device=device, key=key)


def revoke_device(db: Session, *, device_id: int, actor: Actor) -> Device:
    """Revoke a device key at once; commits.

    Its next request is refused (keys are looked up on every request), and its open WebSocket,
    in whichever worker, is closed on the :data:`DEVICE_REVOKED` event (on SQLite, a revocation
    from the command line is another process: the socket's periodic key check closes it)."""
    device = db.get(Device, device_id, with_for_update=True)
    if device is None:
        raise NotFound(f"no device with id {device_id}")
    if device.revoked_at is not None:
        raise Conflict(f"device {device_id} is already revoked")
    device.revoked_at = utcnow()
    audit.record(
        db,
        actor=actor,
        action="device.key_revoked",
        subject=f"{device.station.name}/{device.label}",
        details={"device_id": device.id, "key_prefix": device.key_prefix},
    )
    events.publish(
        db,
        topics=[station_topic(device.station)],
        type=DEVICE_REVOKED,
        device_id=device.id,
        site=sites.STUDY_WIDE,  # a key, not a participant's activity
    )
    db.commit()
    return device


def authenticate_seat(db: Session, *, key: str) -> step_store.DeviceSeat:
    """The live device holding this key and its station's seat, in one statement (every robot
    request needs them: app.api.device_work); NotAuthenticated otherwise, never saying why.

    Looked up on every request, never cached: a revoked key is refused on its very next request,
    whichever worker process serves it.
    """
    found = None
    if key.startswith(KEY_PREFIX) and len(key) <= KEY_MAX_LENGTH:
        found = step_store.device_seat(Cursor.of(db), digest=token_digest(key))
    if found is None:
        raise NotAuthenticated("unknown or revoked device key")
    return found


def _running_session(db: Session, participant_id: int) -> StudySession | None:
    return db.scalar(
        select(StudySession).where(
            StudySession.participant_id == participant_id,
            StudySession.status == SessionStatus.RUNNING,
        )
    )


def assign_participant(
    db: Session,
    *,
    station_name: str,
    participant: Participant,
    actor: Actor,
    tie_untied_to: Study | None = None,
) -> Station:
    """Seat a participant at a station; commits. One participant per station and vice versa.

    ``tie_untied_to``: a station that runs no study yet runs this one from now on (the console's
    first seating, in the same transaction)."""
    station = get_station(db, station_name, for_update=True)
    if participant.status == ParticipantStatus.WITHDRAWN:
        raise Conflict(f"participant {participant.code!r} has withdrawn")
    if station.participant_id == participant.id:
        return station
    sites.check_seating(station, participant, station.site)
    current = None
    if station.participant_id is not None:
        current = db.get(Participant, station.participant_id)
        if current is not None and _running_session(db, current.id) is not None:
            raise Conflict(
                f"station {station.name!r} is running a session with {current.code!r}: "
                "end that session first"
            )
    elsewhere = db.scalar(select(Station).where(Station.participant_id == participant.id))
    if elsewhere is not None:
        if _running_session(db, participant.id) is not None:
            raise Conflict(
                f"{participant.code!r} is in a session at station {elsewhere.name!r}: end it first"
            )
        elsewhere.participant_id = None
        elsewhere.assigned_at = None
        db.flush()
        # the views of the station they leave, and theirs, learn it too
        participant_changes.participant_changed(db, participant, Change.UNSEATED, station=elsewhere)
    station.participant_id = participant.id
    db.flush()
    if current is not None:  # whoever sat here is unseated by this seating: their views learn it
        participant_changes.participant_changed(db, current, Change.UNSEATED, station=station)
    station.assigned_at = utcnow()
    if tie_untied_to is not None and station.study_id is None:
        _tie(db, station, tie_untied_to, actor)
    _seating_changed(db, station, participant, actor, Change.SEATED)
    db.commit()
    return station


def _seating_changed(
    db: Session, station: Station, participant: Participant, actor: Actor, change: Change
) -> None:
    """Audit a seating change and tell every view of the participant and of the station
    (before commit)."""
    audit.record(
        db,
        actor=actor,
        action=f"station.{change.value}",
        study_id=participant.study_id,
        subject=participant.code,
        details={"station": station.name},
    )
    participant_changes.participant_changed(db, participant, change, station=station)


def unassign(db: Session, *, station_name: str, actor: Actor) -> Station:
    """Free a station; commits. Refused while its participant is in a session."""
    station = get_station(db, station_name, for_update=True)
    if station.participant_id is None:
        return station
    participant = db.get(Participant, station.participant_id)
    assert participant is not None
    if _running_session(db, participant.id) is not None:
        raise Conflict(f"{participant.code!r} is in a session: end it before freeing the station")
    station.participant_id = None
    station.assigned_at = None
    _seating_changed(db, station, participant, actor, Change.UNSEATED)
    db.commit()
    return station


def socket_opened(db: Session, *, device_id: int, socket_id: str, lasts: timedelta) -> None:
    """Record that a WebSocket of this device opened (``socket_id``: the caller's name for it,
    unique), open for ``lasts`` unless :func:`socket_alive` pushes that on; its station's console
    shows it at once (the caller commits). Each socket has its own row, so that two sockets of
    one key (a bridge reconnecting before its old socket timed out) are both counted."""
    now = utcnow()
    db.add(DeviceSocket(id=socket_id, device_id=device_id, opened_at=now, expires_at=now + lasts))
    _update_device(db, device_id, DEVICE_CONNECTION, {Device.connected_at: now})


def socket_alive(db: Session, *, device_id: int, socket_id: str, lasts: timedelta) -> None:
    """Push on an open socket's expiry (at each heartbeat); its row comes back if it was lost
    (the database was away when the socket opened). The caller commits."""
    expires = utcnow() + lasts
    found = db.execute(
        update(DeviceSocket)
        .where(DeviceSocket.id == socket_id)
        .values(expires_at=expires)
        .returning(DeviceSocket.id)
    ).scalar_one_or_none()
    if found is None:
        socket_opened(db, device_id=device_id, socket_id=socket_id, lasts=lasts)


def socket_closed(db: Session, *, device_id: int, socket_id: str) -> None:
    """Record that a WebSocket of this device closed: the device stays connected while another
    of its sockets is open (the caller commits)."""
    db.execute(delete(DeviceSocket).where(DeviceSocket.id == socket_id))
    _update_device(db, device_id, DEVICE_CONNECTION, {Device.disconnected_at: utcnow()})


def set_notice(db: Session, *, device_id: int, text: str | None, attention: bool) -> None:
    """Show ``text`` from this device on its station's console (None clears it); ``attention``
    asks the operator to act. Commits."""
    values = {
        Device.notice: text,
        Device.notice_attention: attention and text is not None,
        Device.notice_at: utcnow() if text is not None else None,
    }
    _update_device(db, device_id, DEVICE_NOTICE, values)
    db.commit()


def _update_device(db: Session, device_id: int, event: str, values: dict[Any, Any]) -> None:
    station_id = db.execute(
        update(Device).where(Device.id == device_id).values(values).returning(Device.station_id)
    ).scalar_one_or_none()
    if station_id is not None:
        events.publish(
            db,
            topics=[station_topic_of(station_id)],
            type=event,
            device_id=device_id,
            # when a robot is heard tells when its station is used
            # (app.services.privacy.sites.Contact)
            site=sites.device_event_site(db, station_id),
        )
