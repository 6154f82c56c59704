"""Data quality (app/quality.py, app/services/participants/data_quality.py): attention checks
declared in the protocol, page times and time away measured by the pages, straight-lining, and
the flags every export carries and the analysis excludes by."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import pandas as pd
import pyreadstat
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select

from analysis.exports.files import write_export
from app.db import Database
from app.errors import InvalidInput
from app.online import participation as online
from app.protocol import ProtocolError, parse_protocol
from app.quality import Flag
from app.services.analysis_views import study_data
from app.services.audit import Actor, ActorKind
from app.services.participants import data_quality, questionnaires
from app.services.participants.questionnaires import PageTiming
from app.services.privacy.sites import Scope
from app.services.studies import get_study, protocol_of
from app.tables import OnlineParticipation, OnlineStatus, Participant, Submission
from tests.app.test_online_join import create_online_study, join, online_protocol
from tests.conftest import PRE_STUDY_ANSWERS, client_of, sqlite_only

NARS_14 = (
    '{ key = "nars_14", text = "I feel that in the future society will be dominated by '
    'robots.", scale = "agree5" },'
)
CHECK = (
    '    { key = "nars_check", text = "Please choose Agree here.", scale = "agree5", '
    "expected = 4 },"
)
WITH_CHECK = {NARS_14: NARS_14 + "\n" + CHECK}
QUALITY = """
[quality]
min_seconds_per_item = 2.0
straightlining_min_items = 5
max_away_seconds = 120
exclude = ["attention", "speeding"]
"""


def _problems(text: str) -> str:
    with pytest.raises(ProtocolError) as refused:
        parse_protocol(text)
    return str(refused.value)


@pytest.mark.parametrize(
    ("declared", "said"),
    [
        (
            "expected = 9",
            "questionnaires.instruments[3].items[14].expected: must be between 1 and 5",
        ),
        ('expected = "agree"', "expected: must be a whole number"),
        ("expected = true", "give the expected answer itself"),
        (
            "expected = 4, required = false",
            "items[14].required: an attention check must be required",
        ),
    ],
)
def test_an_attention_check_expects_an_answer_its_item_can_be_given(
    declared: str, said: str
) -> None:
    text = online_protocol(**{NARS_14: NARS_14 + "\n" + CHECK.replace("expected = 4", declared)})
    assert said in _problems(text)


def test_attention_checks_on_choices_and_numbers_and_never_in_a_score() -> None:
    # a choice's expected answer is one of its values; a number's lies within its range
    assert "must be one of the options' values" in _problems(
        online_protocol(**{'kind = "choice", options': 'kind = "choice", expected = "x", options'})
    )
    age = 'kind = "number", minimum = 18, maximum = 99 }'
    assert "must be between 18 and 99" in _problems(
        online_protocol(**{age: 'kind = "number", minimum = 18, maximum = 99, expected = 17 }'})
    )
    text = online_protocol(
        **WITH_CHECK, **{'items = ["nars_1", "nars_2"': 'items = ["nars_check", "nars_2"'}
    )
    assert "'nars_check' is an attention check: it cannot be part of a score" in _problems(text)
    text_item = '"Is there anything else you would like to tell us?", kind = "text"'
    assert "a text item cannot be an attention check" in _problems(
        online_protocol(**{text_item: text_item + ', expected = "x"'})
    )


def test_the_quality_rules_are_checked_against_the_protocol() -> None:
    lab = online_protocol().replace("\n[online]", "\n[unused]")
    assert "'attention' needs attention checks" in _problems(
        online_protocol('[quality]\nexclude = ["attention"]\n')
    )
    assert "allowing as many failures flags no one" in _problems(
        online_protocol("[quality]\nattention_failures_allowed = 1\n", **WITH_CHECK)
    )
    assert "'second_id_same_browser' is for online studies" in _problems(
        lab.split("\n[unused]")[0] + '\n[quality]\nexclude = ["second_id_same_browser"]\n'
    )
    assert "quality.exclude[0]: Input should be" in _problems(
        online_protocol('[quality]\nexclude = ["sleepy"]\n')
    )
    loaded = parse_protocol(online_protocol(QUALITY, **WITH_CHECK)).protocol
    assert loaded.quality_rules() == loaded.quality
    assert [item.key for _, item in loaded.attention_checks()] == ["nars_check"]
    # without [quality]: an online study has the defaults, a lab study none
    assert parse_protocol(online_protocol()).protocol.quality_rules() is not None
    assert parse_protocol(lab.split("\n[unused]")[0]).protocol.quality_rules() is None


@pytest.mark.parametrize(
    ("fields", "timing"),
    [
        ({}, None),
        ({"page-seconds": "31.5", "away-seconds": "2"}, PageTiming(31.5, 2.0)),
        ({"page-seconds": "10", "away-seconds": "40"}, PageTiming(10.0, 10.0)),  # away ≤ open
        ({"page-seconds": "7"}, PageTiming(7.0, 0.0)),
    ],
)
def test_a_pages_timing_comes_from_its_form(
    fields: dict[str, str], timing: PageTiming | None
) -> None:
    assert PageTiming.from_form(fields) == timing


@pytest.mark.parametrize(
    "fields",
    [
        {"page-seconds": "soon"},
        {"page-seconds": "-1"},
        {"page-seconds": "nan"},
        {"page-seconds": "1e9"},
        {"page-seconds": "3", "away-seconds": "-2"},
    ],
)
def test_a_timing_that_is_no_number_of_seconds_is_refused(fields: dict[str, str]) -> None:
    with pytest.raises(InvalidInput, match="the page's timing"):
        PageTiming.from_form(fields)


def _answer(
    database: Database,
    participant_id: int,
    pages: dict[str, tuple[dict[str, str], PageTiming | None]],
) -> None:
    """Consent, then each page's answers with the timing its page measured."""
    with database.writing() as db:
        participant = db.get(Participant, participant_id)
        assert participant is not None
        study = get_study(db, "web")
        protocol = protocol_of(study)
        actor = Actor(ActorKind.PARTICIPANT, participant.code)
        questionnaires.accept_consent(
            db, participant=participant, protocol=protocol, accepted=True, actor=actor
        )
        for instrument, (answers, timing) in pages.items():
            questionnaires.submit(
                db,
                participant=participant,
                protocol=protocol,
                instrument_key=instrument,
                session=None,
                answers=answers,
                actor=actor,
                timing=timing,
            )


def _participant_of(joined: online.Joined) -> int:
    assert joined.participation is not None and joined.participation.participant_id is not None
    return joined.participation.participant_id


def test_flags_are_drawn_from_answers_page_times_and_time_away(
    database: Database, tmp_path: Path
) -> None:
    study = create_online_study(database, extra=QUALITY, **WITH_CHECK)
    careful = _participant_of(join(database, study, "PID-CAREFUL", browser="a" * 22))
    careless = _participant_of(join(database, study, "PID-CARELESS", browser="b" * 22))
    second = _participant_of(join(database, study, "PID-SECOND", browser="a" * 22))
    slow = PageTiming(90.0, 0.0)
    good = {**PRE_STUDY_ANSWERS["nars"], "nars_check": "4"}
    _answer(
        database,
        careful,
        {
            "demographics": (PRE_STUDY_ANSWERS["demographics"], slow),
            "nars": (good, PageTiming(75.0, 30.0)),
        },
    )
    same = {f"nars_{n}": "3" for n in range(1, 15)}
    _answer(
        database,
        careless,
        {
            "demographics": (PRE_STUDY_ANSWERS["demographics"], None),  # an API client's page
            "nars": ({**same, "nars_check": "2"}, PageTiming(6.0, 6.0)),
            "background": (dict.fromkeys(PRE_STUDY_ANSWERS["background"], "2"), slow),
        },
    )
    with database.writing() as db:
        row = db.scalar(
            select(OnlineParticipation).where(OnlineParticipation.participant_id == careless)
        )
        assert row is not None
        online.record_away(db, row, 80.0)
        online.record_away(db, row, 40.0)  # 6 + 80 + 40 > 120
    with database.read_session() as db:
        study_row = get_study(db, study)
        whom = Participant.study_id == study_row.id
        found = data_quality.quality_by_participant(db, protocol_of(study_row), whom)
        stored = db.scalar(
            select(Submission).where(
                Submission.participant_id == careful, Submission.instrument == "nars"
            )
        )
        assert stored is not None and (stored.seconds_on_page, stored.seconds_away) == (75.0, 30.0)
    assert found[careful].flags == ()
    assert (found[careful].attention_checks, found[careful].attention_failed) == (1, 0)
    assert found[careful].fastest_seconds_per_item == 5.0  # 75 s over nars' 15 items
    bad = found[careless]
    assert bad.flags == (Flag.ATTENTION, Flag.SPEEDING, Flag.STRAIGHTLINING, Flag.AWAY)
    assert bad.straightlined_pages == ["nars"]  # background has 3 items: fewer than 5
    assert bad.fastest_seconds_per_item == 0.4 and bad.seconds_away == 126.0
    assert bad.reasons()[0] == "attention: failed 1 of 1 attention checks"
    assert found[second].flags == (Flag.SECOND_ID,)
    assert found[second].attention_checks == 0  # answered nothing yet: nothing failed

    with database.read_session() as db:
        dataset = study_data.load_dataset(db, study=get_study(db, study), scope=Scope.every_site())
    columns = dataset.participants.set_index("participant")
    codes = _codes(database)
    assert columns.loc[codes[careless], "quality_flags"] == (
        "attention;speeding;straightlining;away"
    )
    assert columns.loc[codes[careful], "quality_flags"] == ""
    assert columns.loc[codes[second], "quality_flags"] == "second_id_same_browser"
    assert columns.loc[codes[careless], "seconds_away"] == 126.0
    assert dataset.excluded_flags == frozenset({"attention", "speeding"})
    assert dataset.protocol["quality"]["exclude"] == ["attention", "speeding"]
    # the attention check is exported, but it is no measure
    nars = dataset.instrument("nars")
    check = next(item for item in nars.items if item.key == "nars_check")
    assert check.expected == "4" and not check.is_measure
    # every export carries the flags: the wide file, the SPSS file and the codebook
    wide = pd.read_csv(write_export(dataset, "wide-csv", tmp_path / "wide.csv"))
    flags = dict(zip(wide["participant"], wide["quality_flags"].fillna(""), strict=True))
    assert flags[codes[careless]] == "attention;speeding;straightlining;away"
    spss, _meta = pyreadstat.read_sav(str(write_export(dataset, "sav", tmp_path / "s.sav")))
    assert set(data_quality.QUALITY_COLUMNS) <= set(spss.columns)
    codebook = pd.read_csv(write_export(dataset, "codebook-csv", tmp_path / "codebook.csv"))
    labels = dict(zip(codebook["column"], codebook["label"], strict=False))
    assert labels["attention_failed"] == "Attention checks answered otherwise than expected"
    assert labels["nars_check"].endswith("(attention check: expected 4)")


def _codes(database: Database) -> dict[int, str]:
    with database.read_session() as db:
        return {row.id: row.code for row in db.execute(select(Participant.id, Participant.code))}


@sqlite_only("the rules' absence, not the database")
def test_a_lab_study_without_rules_has_no_flags_and_no_quality_columns(
    database: Database, exp3_study: str
) -> None:
    with database.read_session() as db:
        study = get_study(db, exp3_study)
        assert (
            data_quality.quality_by_participant(
                db, protocol_of(study), Participant.study_id == study.id
            )
            == {}
        )
        dataset = study_data.load_dataset(db, study=study, scope=Scope.every_site())
    assert "quality_flags" not in dataset.participants.columns
    assert "quality" not in dataset.protocol and dataset.excluded_flags == frozenset()


@sqlite_only("the pages' handling of the timing fields, not the database's")
def test_the_tablet_page_stores_its_timing_and_refuses_a_broken_one(
    client: TestClient, database: Database
) -> None:
    create_online_study(database)
    browser = client_of(client)
    query = "PROLIFIC_PID=PID-TIMED&STUDY_ID=s1&SESSION_ID=x1"
    form = {"query": query, "browser": "browser-timed-1", "webgl": "1", "audio": "1"}
    form |= {"width": "1366", "height": "768", "keyboard": "1"}
    assert browser.post("/join/web", data=form, follow_redirects=False).status_code == 303
    consent = browser.get("/tablet/consent")
    token = _form_token(consent.text)
    accepted = browser.post(
        "/tablet/consent", data={"csrf_token": token, "accept": "yes"}, follow_redirects=False
    )
    assert accepted.status_code == 303, accepted.text
    page = browser.get("/tablet/q/demographics")
    assert 'name="page-seconds"' in page.text and 'name="away-seconds"' in page.text
    # the tablet's JSON view of a page never tells an attention check's answer
    token = browser.cookies["tl_tablet"]
    shown = client_of(client, headers={"Authorization": f"Bearer {token}"}).get("/api/v1/tablet")
    assert shown.json()["instrument"]["key"] == "demographics"
    assert all("expected" not in item for item in shown.json()["instrument"]["items"])
    answers: dict[str, Any] = {
        "csrf_token": _form_token(page.text),
        **PRE_STUDY_ANSWERS["demographics"],
    }
    broken = browser.post(
        "/tablet/q/demographics", data={**answers, "page-seconds": "later"}, follow_redirects=False
    )
    # a broken page's timing is refused, and nothing of the page is stored; an online
    # participant is not told to hand a tablet to anyone
    assert broken.status_code == 422 and "Something went wrong" in broken.text
    assert "experimenter" not in broken.text
    with database.read_session() as db:
        assert db.scalar(select(Submission).where(Submission.instrument == "demographics")) is None
    sent = browser.post(
        "/tablet/q/demographics",
        data={**answers, "page-seconds": "41.25", "away-seconds": "3.5"},
        follow_redirects=False,
    )
    assert sent.status_code == 303, sent.text
    # a revision keeps the first submission's timing
    again = browser.post(
        "/tablet/q/demographics",
        data={**answers, "age": "28", "page-seconds": "2", "away-seconds": "0"},
        follow_redirects=False,
    )
    assert again.status_code == 303
    with database.read_session() as db:
        rows = db.execute(
            select(Submission.instrument, Submission.seconds_on_page, Submission.seconds_away)
        ).all()
    assert sorted(rows, key=str) == sorted(
        [("consent", None, None), ("demographics", 41.25, 3.5)], key=str
    )

    # the room's beacon adds each hidden spell; nothing once the participation is over
    assert browser.post("/online/away", data={"seconds": "12.5"}).status_code == 204
    assert browser.post("/online/away", data={"seconds": "-1"}).status_code == 422
    assert browser.post("/online/away", data={"seconds": "inf"}).status_code == 422
    assert browser.post("/online/away", data={"seconds": "2"}).status_code == 204
    with database.writing() as db:
        row = db.scalar(select(OnlineParticipation))
        assert row is not None and row.room_seconds_away == 14.5
        row.status = OnlineStatus.COMPLETED
        db.commit()
    assert browser.post("/online/away", data={"seconds": "30"}).status_code == 204
    with database.read_session() as db:
        assert db.scalar(select(OnlineParticipation.room_seconds_away)) == 14.5
    assert client_of(client).post("/online/away", data={"seconds": "1"}).status_code == 401


def _form_token(page: str) -> str:
    found = re.search(r'name="csrf_token" value="([^"]+)"', page)
    assert found, page
    return found.group(1)
