"""Joining an online study (app/online/participation.py): one participation per recruitment ID,
the virtual station and its derived key, screening, quotas, the time limit."""

from __future__ import annotations

import threading
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest
from sqlalchemy import func, select
from typer.testing import CliRunner

from app.cli import cli
from app.db import Database
from app.errors import InvalidInput, NotFound
from app.online import participation as online
from app.online.participation import BrowserCheck, Outcome
from app.protocol import ProtocolError, parse_protocol
from app.services import studies
from app.services.audit import Actor
from app.services.participants import tablet_tokens
from app.services.privacy import erasure
from app.services.sessions import stations
from app.tables import (
    AuditEvent,
    Device,
    OnlineParticipation,
    OnlineStatus,
    Participant,
    Station,
)
from tests.conftest import EXP3_ONLY, protocol_text, sqlite_only

SECRET = b"online-tests-secret"
ONLINE = """
[online]
id_parameter = "PROLIFIC_PID"
parameters = ["STUDY_ID", "SESSION_ID"]
completion_url = "https://app.prolific.com/submissions/complete?cc={code}"
completion_code = "C1ABC2"
screen_out_url = "https://app.prolific.com/submissions/complete?cc=SCREENED"
time_limit_minutes = 45
"""
DESKTOP = BrowserCheck(webgl=True, audio=True, width=1366, height=768, keyboard=True, touch=False)
T0 = datetime(2026, 12, 7, 10, 0, tzinfo=UTC)


def online_protocol(extra: str = "", **replacements: str) -> str:
    """The shipped protocol (Exp3 in both conditions) run online."""
    return protocol_text(**EXP3_ONLY, **replacements) + ONLINE + extra


def create_online_study(
    database: Database, name: str = "web", extra: str = "", **replacements: str
) -> str:
    loaded = parse_protocol(online_protocol(extra, **replacements))
    with database.writing() as db:
        studies.create_study(db, name=name, loaded=loaded, actor=Actor.system())
    return name


@pytest.fixture
def web_study(database: Database) -> str:
    return create_online_study(database)


def join(
    database: Database,
    study: str,
    pid: str,
    *,
    check: BrowserCheck = DESKTOP,
    browser: str = "b" * 22,
    at: datetime = T0,
    **query: str,
) -> online.Joined:
    with database.writing() as db:
        return online.join(
            db,
            study_name=study,
            query={"PROLIFIC_PID": pid, "STUDY_ID": "s1", "SESSION_ID": f"x-{pid}", **query},
            browser_id=browser,
            check=check,
            secret=SECRET,
            now=lambda: at,
        )


def count(database: Database, table: type) -> int:
    with database.read_session() as db:
        return int(db.scalar(select(func.count()).select_from(table)) or 0)


def test_a_new_id_is_enrolled_at_a_station_of_its_own_that_its_key_opens(
    database: Database, web_study: str
) -> None:
    joined = join(database, web_study, "5f1a2b3c4d5e6f7a8b9c0d1e")
    assert joined.outcome is Outcome.ENROLLED and joined.token is not None
    with database.read_session() as db:
        row = db.scalar(select(OnlineParticipation))
        assert row is not None
        assert row.recruitment_hash and "5f1a2b3c" not in row.recruitment_hash
        assert row.parameters == {"STUDY_ID": "s1", "SESSION_ID": "x-5f1a2b3c4d5e6f7a8b9c0d1e"}
        assert row.expires_at == T0 + timedelta(minutes=45)
        assert (row.status, row.device, row.flags) == ("active", "desktop", {})
        station = db.get(Station, row.station_id)
        assert (
            station is not None and station.online and station.participant_id == row.participant_id
        )
        seat = stations.authenticate_seat(db, key=online.station_key(SECRET, row))
        assert seat.seat.station_name == station.name
        participant, _study = tablet_tokens.participant_for_token(db, joined.token)
        assert participant.id == row.participant_id
        # the lab's station list does not show it
        assert station.name not in [s.name for s in stations.list_stations(db)]


@sqlite_only("the participation's rules, not the database's")
def test_the_same_id_again_continues_and_is_never_allocated_twice(
    database: Database, web_study: str
) -> None:
    first = join(database, web_study, "PID-1")
    again = join(database, web_study, "PID-1", browser="c" * 22, at=T0 + timedelta(minutes=30))
    assert again.outcome is Outcome.RESUMED
    assert first.participation is not None and again.participation is not None
    assert again.participation.id == first.participation.id
    assert again.token == first.token
    assert count(database, Participant) == 1 and count(database, OnlineParticipation) == 1


def test_parallel_joins_with_one_id_make_one_participation(
    database: Database, web_study: str
) -> None:
    outcomes: list[Outcome] = []
    start = threading.Barrier(4)

    def go() -> None:
        start.wait()
        outcomes.append(join(database, web_study, "SAME-ID").outcome)

    threads = [threading.Thread(target=go) for _ in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert sorted(outcomes) == sorted([Outcome.ENROLLED] + [Outcome.RESUMED] * 3)
    assert count(database, Participant) == 1 and count(database, OnlineParticipation) == 1
    assert count(database, Station) == 1


@sqlite_only("the browser check's rules, not the database's")
@pytest.mark.parametrize(
    ("check", "reason"),
    [
        (BrowserCheck(False, True, 1366, 768, True, False), "webgl"),
        (BrowserCheck(True, False, 1366, 768, True, False), "audio"),
        (BrowserCheck(True, True, 800, 768, True, False), "window"),
        (BrowserCheck(True, True, 390, 844, False, True), "device:phone"),
    ],
)
def test_a_browser_that_cannot_run_the_room_is_screened_out_and_told_again(
    database: Database, web_study: str, check: BrowserCheck, reason: str
) -> None:
    out = join(database, web_study, "PID-2", check=check)
    assert out.outcome is Outcome.SCREENED_OUT
    assert out.participation is not None and out.participation.reason == reason
    assert count(database, Participant) == 0
    # a better browser later does not get a second chance under the same ID
    assert join(database, web_study, "PID-2").outcome is Outcome.SCREENED_OUT


@sqlite_only("the participation's rules, not the database's")
def test_a_second_id_from_the_same_browser_is_flagged_not_refused(
    database: Database, web_study: str
) -> None:
    join(database, web_study, "PID-A", browser="same-browser-0001")
    second = join(database, web_study, "PID-B", browser="same-browser-0001")
    assert second.outcome is Outcome.ENROLLED and second.participation is not None
    assert second.participation.flags == {"second_id_same_browser": True}


@sqlite_only("the participation's rules, not the database's")
def test_the_time_limit_expires_a_participation_and_revokes_its_key(
    database: Database, web_study: str
) -> None:
    joined = join(database, web_study, "PID-3")
    assert join(database, web_study, "PID-3", at=T0 + timedelta(minutes=44)).outcome is (
        Outcome.RESUMED
    )
    late = join(database, web_study, "PID-3", at=T0 + timedelta(minutes=45))
    assert late.outcome is Outcome.EXPIRED
    with database.read_session() as db:
        assert joined.participation is not None
        row = db.get(OnlineParticipation, joined.participation.id)
        assert row is not None and row.status == OnlineStatus.EXPIRED
        assert db.scalar(select(Device.revoked_at)) is not None
        with pytest.raises(Exception, match="unknown or revoked"):
            stations.authenticate_seat(db, key=online.station_key(SECRET, row))


def test_enrolment_closes_when_every_condition_has_its_complete_participants(
    database: Database,
) -> None:
    study = create_online_study(database, extra="target_per_condition = 1\n")
    ids = []
    for n in range(4):  # a block of four or two of two: both conditions
        joined = join(database, study, f"Q-{n}")
        assert joined.participation is not None
        ids.append(joined.participation.id)
    # in progress: not counted, others may still join
    assert join(database, study, "Q-extra").outcome is Outcome.ENROLLED
    with database.writing() as db:
        for pid in ids:
            row = db.get(OnlineParticipation, pid)
            assert row is not None
            online.finish(db, row, OnlineStatus.COMPLETED, at=T0)
    assert join(database, study, "Q-late").outcome is Outcome.FULL
    assert join(database, study, "Q-0").outcome is Outcome.COMPLETED  # a return: told so


@sqlite_only("the participation's rules, not the database's")
def test_a_link_without_its_id_or_a_study_not_run_online_is_refused(
    database: Database, web_study: str, study_name: str
) -> None:
    with pytest.raises(InvalidInput, match="PROLIFIC_PID is missing or malformed"):
        join(database, web_study, "")
    with pytest.raises(InvalidInput, match="PROLIFIC_PID"):
        join(database, web_study, "bad id with spaces")
    with pytest.raises(NotFound, match="not run online"):
        join(database, study_name, "PID-4")
    assert count(database, OnlineParticipation) == 0


def test_online_protocol_checks() -> None:
    with pytest.raises(ProtocolError) as refused:
        parse_protocol(
            online_protocol(
                'parameters = ["STUDY_ID", "STUDY_ID", "PROLIFIC_PID"]',
                **{"stratify_by = []": 'stratify_by = ["gender"]'},
            ).replace('parameters = ["STUDY_ID", "SESSION_ID"]\n', "")
        )
    text = str(refused.value)
    assert "online.parameters[1]: 'STUDY_ID' is listed twice" in text
    assert "online.parameters[2]: 'PROLIFIC_PID' is the id_parameter" in text
    assert "the stratification factor 'gender' must come from a URL parameter" in text
    with pytest.raises(ProtocolError, match=r"online\.completion_url"):
        parse_protocol(online_protocol().replace("https://app.prolific", "ftp://app.prolific"))


def test_staff_cannot_name_a_station_as_online_participants_are_named(database: Database) -> None:
    with database.writing() as db, pytest.raises(InvalidInput, match="kept for online"):
        stations.create_station(db, name="online-7", actor=Actor.system())


@sqlite_only("a command's words, not the database's")
def test_an_admin_finds_a_recruitment_id_on_request_and_the_lookup_is_audited(
    database: Database, database_url: str, web_study: str, tmp_path: Path
) -> None:
    joined = join(database, web_study, "PID-ASKS")
    assert joined.participation is not None
    env = {
        "TRUSTLAB_DATABASE_URL": database_url,
        "TRUSTLAB_SECRET_KEY": SECRET.decode(),
        "TRUSTLAB_VAR_DIR": str(tmp_path),
    }
    found = CliRunner().invoke(
        cli, ["online", "find", "--study", "web", "--id", "PID-ASKS"], env=env
    )
    assert found.exit_code == 0, found.output
    assert found.output.startswith("P001: active, joined 2026-12-07 10:00 UTC")
    unknown = CliRunner().invoke(
        cli, ["online", "find", "--study", "web", "--id", "NOBODY"], env=env
    )
    assert unknown.exit_code != 0 and "no participation of that recruitment ID" in unknown.output
    with database.read_session() as db:
        logged = db.scalars(
            select(AuditEvent).where(AuditEvent.action == "online.recruitment_id_looked_up")
        ).all()
        assert [(e.subject, e.details) for e in logged] == [
            ("P001", {"participation": joined.participation.id})
        ]
        assert "PID-ASKS" not in repr([e.details for e in logged])


def test_erasing_an_online_participant_removes_their_recruitment_id(
    database: Database, web_study: str
) -> None:
    joined = join(database, web_study, "PID-GONE")
    assert joined.participation is not None
    with database.writing() as db:
        result = erasure.erase_participant(
            db, study_name=web_study, code="P001", actor=Actor.system(), secret=SECRET
        )
    assert result.removed["online_participation"] == 1
    assert count(database, OnlineParticipation) == 0
    with database.read_session() as db:
        station = db.scalar(select(Station))
        assert station is not None and station.participant_id is None
