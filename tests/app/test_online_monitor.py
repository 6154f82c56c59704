"""The dashboard's online panel (app/online/monitor.py) and its data-quality panel
(app/web/monitor_pages.py): where each participant is, drop-outs by step, durations, flags."""

from __future__ import annotations

from datetime import timedelta

from fastapi.testclient import TestClient
from sqlalchemy import select, update

from app.db import Database
from app.online import participation as online
from app.online.monitor import flow, online_monitor, step_of
from app.protocol import parse_protocol
from app.services.participants import questionnaires
from app.services.participants.questionnaires import PageTiming
from app.services.privacy.sites import Scope
from app.services.studies import get_study, protocol_of
from app.tables import OnlineParticipation, OnlineStatus, Participant, ParticipantStatus, Role
from tests.app.test_data_quality import QUALITY, WITH_CHECK, _answer
from tests.app.test_online_join import T0, BrowserCheck, create_online_study, join, online_protocol
from tests.conftest import PRE_STUDY_ANSWERS, UserClientFactory, sqlite_only

NO_WEBGL = BrowserCheck(webgl=False, audio=True, width=1366, height=768, keyboard=True, touch=False)


def _participant(joined: online.Joined) -> int:
    assert joined.participation is not None and joined.participation.participant_id is not None
    return joined.participation.participant_id


def _set(database: Database, participant_id: int, **values: object) -> None:
    with database.writing() as db:
        db.execute(
            update(OnlineParticipation)
            .where(OnlineParticipation.participant_id == participant_id)
            .values(**values)
        )
        db.commit()


def test_the_steps_follow_the_study_in_order() -> None:
    protocol = parse_protocol(online_protocol()).protocol
    keys = [key for key, _ in flow(protocol)]
    assert keys[:6] == [
        "language",
        "consent",
        "questionnaire:demographics",
        "questionnaire:background",
        "questionnaire:tipi",
        "questionnaire:nars",
    ]
    assert keys[6:9] == ["room:0", "room:1", "questionnaire:trust:1"]
    assert keys[-3:] == ["questionnaire:trust:4", "questionnaire:overall", "done"]
    assert dict(flow(protocol))["room:0"] == "In the room: the familiarisation run"
    page = questionnaires.Page("questionnaire", protocol.instruments_at("session")[0], 2)
    assert step_of(page) == "questionnaire:trust:2"
    assert step_of(questionnaires.Page("wait"), 3) == "room:3"


def test_the_panel_counts_who_is_where_who_dropped_out_and_how_long_it_took(
    database: Database,
) -> None:
    study = create_online_study(database, extra=QUALITY, **WITH_CHECK)
    new = _participant(join(database, study, "PID-NEW"))
    ready = _participant(join(database, study, "PID-READY"))
    running = _participant(join(database, study, "PID-RUNNING"))
    late = _participant(join(database, study, "PID-LATE"))
    withdrawn = _participant(join(database, study, "PID-WITHDRAWN"))
    done = _participant(join(database, study, "PID-DONE"))
    assert join(database, study, "PID-NO-3D", check=NO_WEBGL).outcome is online.Outcome.SCREENED_OUT
    pre = {name: (answers, PageTiming(30.0, 0.0)) for name, answers in PRE_STUDY_ANSWERS.items()}
    pre["nars"] = ({**PRE_STUDY_ANSWERS["nars"], "nars_check": "4"}, PageTiming(40.0, 0.0))
    for participant_id in (ready, running):
        _answer(database, participant_id, pre)
    _answer(database, late, {"demographics": pre["demographics"]})
    with database.writing() as db:
        row = db.scalar(
            select(OnlineParticipation).where(OnlineParticipation.participant_id == running)
        )
        assert row is not None
        online.start_session(db, row)  # its familiarisation run starts
        person = db.get(Participant, withdrawn)
        assert person is not None
        person.status = ParticipantStatus.WITHDRAWN
        db.commit()
    # the withdrawn one's participation is still active: nobody has looked since
    _set(database, done, status=OnlineStatus.COMPLETED, finished_at=T0 + timedelta(minutes=38))
    # PID-LATE's time limit (45 minutes) passes; nobody has looked since
    _set(database, late, expires_at=T0 + timedelta(minutes=20))
    now = T0 + timedelta(minutes=21)
    _set(database, new, last_seen_at=now - timedelta(seconds=30))  # a page of theirs, just now

    with database.read_session() as db:
        found = get_study(db, study)
        monitor = online_monitor(
            db, study=found, protocol=protocol_of(found), scope=Scope.every_site(), now=now
        )
    assert (monitor.active, monitor.completed, monitor.expired, monitor.ended) == (3, 1, 1, 1)
    assert monitor.screened_out == 1
    assert monitor.online_now == 1  # PID-NEW; the others' last requests are older
    assert [(row.step, row.count) for row in monitor.at_step] == [("consent", 1), ("room:0", 2)]
    assert [(row.step, row.count) for row in monitor.dropped_at] == [
        ("consent", 1),  # the withdrawn one never consented
        ("questionnaire:background", 1),  # PID-LATE had answered the first page only
    ]
    assert monitor.median_minutes_to_complete == 38.0
    pages = dict(monitor.median_page_seconds)
    assert pages["About you"] == 30.0 and pages["Attitudes towards robots"] == 40.0
    assert monitor.median_session_minutes is None  # no session has ended

    with database.read_session() as db:
        found = get_study(db, study)
        limited = Scope(sites=frozenset({"elsewhere"}))
        protocol = protocol_of(found)
        hidden = online_monitor(db, study=found, protocol=protocol, scope=limited, now=now)
    assert hidden.screened_out is None and hidden.active == 0 and hidden.at_step == []


@sqlite_only("the pages around the panel, not the database")
def test_the_dashboard_shows_the_online_and_quality_panels(
    user_client: UserClientFactory, database: Database, client: TestClient
) -> None:
    study = create_online_study(database, extra=QUALITY, **WITH_CHECK)
    staff = user_client(Role.EXPERIMENTER)
    empty = staff.get(f"/studies/{study}/monitor")
    assert empty.status_code == 200
    assert "Nobody is taking part right now" in empty.text
    assert "/join/web?PROLIFIC_PID=" in empty.text
    assert "No participant is flagged." in empty.text
    careless = _participant(join(database, study, "PID-CARELESS"))
    _answer(
        database,
        careless,
        {"nars": ({**{f"nars_{n}": "3" for n in range(1, 15)}, "nars_check": "1"}, None)},
    )
    with database.read_session() as db:
        code = db.scalar(select(Participant.code).where(Participant.id == careless))
    page = staff.get(f"/studies/{study}/dashboard")
    assert 'id="online-monitor"' in page.text and f'hx-get="/studies/{study}/monitor"' in page.text
    panel = staff.get(f"/studies/{study}/monitor").text
    assert f'data-participant="{code}"' in panel
    assert "attention: failed 1 of 1 attention checks" in panel
    assert "straightlining: one answer throughout nars" in panel
    assert "excluded (protocol's rule)" in panel
    assert '<tr data-step="consent"><td>Consent</td><td>1</td></tr>' not in panel  # consented
    assert 'data-step="questionnaire:demographics"' in panel


@sqlite_only("a lab study's dashboard, not the database")
def test_a_lab_study_without_rules_shows_neither_panel(
    user_client: UserClientFactory, exp3_study: str
) -> None:
    staff = user_client(Role.EXPERIMENTER)
    page = staff.get(f"/studies/{exp3_study}/dashboard")
    assert page.status_code == 200
    assert 'id="online-monitor"' not in page.text and 'id="quality-monitor"' not in page.text
