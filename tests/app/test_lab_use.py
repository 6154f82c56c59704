"""A lab's day at the staff pages (issue 21, defects 4 and 9): a console tied to its study that
asks before a likely slip, studies and stations that can be archived, titles given at creation,
and refusals explained next to the control."""

from __future__ import annotations

import json
from pathlib import Path

from typer.testing import CliRunner

from app.cli import cli
from app.db import Database
from app.protocol import default_protocol, parse_protocol
from app.services import studies
from app.services.audit import Actor
from app.tables import Participant, ParticipantStatus, Role, Station
from tests.conftest import (
    EXP3_ONLY,
    Lab,
    UserClientFactory,
    fill_pre_study,
    protocol_text,
    tablet_client,
)


def _second_study(database: Database, name: str = "rt2", title: str = "Main study") -> str:
    with database.writing() as db:
        studies.create_study(
            db,
            name=name,
            loaded=parse_protocol(protocol_text(**EXP3_ONLY)),
            actor=Actor.system(),
            title=title,
        )
    return name


def _enrol(lab: Lab, study: str, code: str) -> None:
    enrolled = lab.experimenter.post(f"/api/v1/studies/{study}/participants", json={"code": code})
    assert enrolled.status_code == 201, enrolled.text


def _station(database: Database, name: str) -> Station:
    with database.read_session() as db:
        station = db.query(Station).filter_by(name=name).one()
        db.expunge(station)
        return station


def _seated_code(lab: Lab) -> str | None:
    return lab.robot.get("/api/v1/station").json()["participant"]


def test_a_new_console_asks_which_study_and_the_first_seating_ties_it(
    lab: Lab, database: Database
) -> None:
    _second_study(database)
    page = lab.experimenter.get("/stations/lab-1").text
    assert "Choose the study this station runs…" in page  # no study preselected
    assert 'value="rt2"' in page and 'value="rt"' in page
    refused = lab.experimenter.post("/stations/lab-1/assign", data={"code": "P001"})
    assert refused.status_code == 422
    assert "choose the study this station runs, then type the code" in refused.text
    _enrol(lab, "rt2", "M01")
    seated = lab.experimenter.post("/stations/lab-1/assign", data={"study": "rt2", "code": "M01"})
    assert seated.status_code == 200, seated.text
    assert _seated_code(lab) == "M01"
    with database.read_session() as db:
        assert _station(database, "lab-1").study_id == studies.get_study(db, "rt2").id


def test_a_code_of_another_study_is_asked_about_then_seated_when_confirmed(
    lab: Lab, database: Database
) -> None:
    _second_study(database)
    _enrol(lab, "rt", "A01")
    _enrol(lab, "rt2", "B01")
    assert lab.experimenter.post("/stations/lab-1/study", data={"study": "rt"}).status_code == 200
    page = lab.experimenter.get("/stations/lab-1").text
    assert "This station runs" in page and "Choose the study" not in page
    asked = lab.experimenter.post("/stations/lab-1/assign", data={"study": "rt", "code": "B01"})
    assert asked.status_code == 200
    assert "Seat B01 here?" in asked.text
    assert "has no participant &#39;B01&#39;" in asked.text
    assert "is in the study &#39;Main study&#39; (rt2), but this station runs" in asked.text
    assert _seated_code(lab) is None  # nothing happened yet
    confirmed = lab.experimenter.post(
        "/stations/lab-1/assign", data={"study": "rt2", "code": "B01", "confirmed": "true"}
    )
    assert confirmed.status_code == 200, confirmed.text
    assert "Seat B01 here?" not in confirmed.text
    assert _seated_code(lab) == "B01"
    with database.read_session() as db:  # the station keeps its study: one seating is not a change
        assert _station(database, "lab-1").study_id == studies.get_study(db, "rt").id


def test_a_participant_who_finished_is_seated_only_once_confirmed(
    lab: Lab, database: Database
) -> None:
    _enrol(lab, "rt", "F01")
    with database.writing() as db:
        participant = db.query(Participant).filter_by(code="F01").one()
        participant.status = ParticipantStatus.COMPLETED
        db.commit()
    asked = lab.experimenter.post("/stations/lab-1/assign", data={"study": "rt", "code": "F01"})
    assert "Seat F01 here?" in asked.text
    assert "F01 has finished the study: every session is done." in asked.text
    assert _seated_code(lab) is None
    lab.experimenter.post(
        "/stations/lab-1/assign", data={"study": "rt", "code": "F01", "confirmed": "true"}
    )
    assert _seated_code(lab) == "F01"


def test_an_unknown_code_is_refused_beside_the_form(lab: Lab) -> None:
    refused = lab.experimenter.post(
        "/stations/lab-1/assign", data={"study": "rt", "code": "NOBODY"}
    )
    assert refused.status_code == 404
    assert "NOBODY" in refused.text and 'role="alert"' in refused.text


def test_changing_the_stations_study_and_its_learner_bars_show_question_texts(
    lab: Lab, database: Database
) -> None:
    _second_study(database)
    lab.enrol_and_assign()
    page = lab.experimenter.get("/stations/lab-1").text
    question = default_protocol().protocol.categories[0].questions[0]
    assert f"1. {question}" in page  # the text above its bar, not only in a tooltip
    changed = lab.experimenter.post("/stations/lab-1/study", data={"study": "rt2"})
    assert changed.status_code == 200
    with database.read_session() as db:
        assert _station(database, "lab-1").study_id == studies.get_study(db, "rt2").id
    empty = lab.experimenter.post("/stations/lab-1/study", data={"study": ""})
    assert empty.status_code == 422 and "choose the study this station runs" in empty.text


def test_an_archived_study_leaves_the_lists_and_consoles_but_keeps_its_pages(
    lab: Lab, database: Database, user_client: UserClientFactory
) -> None:
    _second_study(database)
    admin = user_client(Role.ADMIN)
    assert (
        lab.experimenter.post("/admin/studies/rt2/archive", data={"archived": "true"}).status_code
        == 403
    )
    archived = admin.post("/admin/studies/rt2/archive", data={"archived": "true"})
    assert (
        "Archived Main study: it is hidden from the study list and the consoles." in archived.text
    )
    listing = lab.experimenter.get("/").text
    assert 'href="/studies/rt2"' not in listing and "1 archived study" in listing
    assert 'href="/studies/rt2"' in lab.experimenter.get("/?archived=true").text
    console = lab.experimenter.get("/stations/lab-1").text
    assert 'value="rt2"' not in console  # the only study in use is offered alone
    study_page = lab.experimenter.get("/studies/rt2")
    assert study_page.status_code == 200 and "archived</span>" in study_page.text
    shown = admin.post("/admin/studies/rt2/archive", data={"archived": "false"})
    assert "Main study is shown again." in shown.text
    assert 'href="/studies/rt2"' in lab.experimenter.get("/").text


def test_a_free_station_can_be_archived_a_busy_one_cannot(
    lab: Lab, user_client: UserClientFactory
) -> None:
    admin = user_client(Role.ADMIN)
    lab.enrol_and_assign()
    busy = admin.post("/stations/lab-1/archive", data={"archived": "true"})
    assert busy.status_code == 409 and "has a participant seated: free it first" in busy.text
    assert admin.post("/stations", data={"name": "spare"}).status_code == 200
    done = admin.post("/stations/spare/archive", data={"archived": "true"})
    assert "Archived station spare." in done.text
    listing = admin.get("/stations").text
    assert 'id="station-spare"' not in listing and "1 archived station" in listing
    assert 'id="station-spare"' in admin.get("/stations?archived=true").text


def test_a_bad_station_name_is_explained_by_the_server_next_to_the_form(
    user_client: UserClientFactory,
) -> None:
    admin = user_client(Role.ADMIN)
    bad = admin.post("/stations", data={"name": "Lab One"})
    assert bad.status_code == 422
    assert 'class="error" role="alert"' in bad.text and "Lab One" in bad.text
    assert 'value="Lab One"' in bad.text  # kept in the field to correct
    assert admin.post("/stations", data={"name": "lab-one"}).status_code == 200
    taken = admin.post("/stations", data={"name": "lab-one"})
    assert taken.status_code == 409 and 'role="alert"' in taken.text


def test_a_title_given_at_creation_from_the_page_the_api_and_the_cli(
    user_client: UserClientFactory, database_url: str, tmp_path: Path
) -> None:
    admin = user_client(Role.ADMIN)
    source = default_protocol().source_text.encode()
    admin.post(
        "/admin/studies",
        data={"name": "pilot", "title": "  Pilot   spring 2026 "},
        files={"protocol": ("p.toml", source, "text/plain")},
    )
    assert "<h1>Pilot spring 2026</h1>" in admin.get("/studies/pilot").text
    made = admin.post(
        "/api/v1/studies",
        json={"name": "main", "title": "Main study", "protocol_toml": source.decode()},
    )
    assert made.status_code == 201 and made.json()["title"] == "Main study"
    unnamed = admin.post(
        "/api/v1/studies", json={"name": "plain", "protocol_toml": source.decode()}
    )
    assert unnamed.json()["title"] == default_protocol().protocol.study.title
    too_long = admin.post(
        "/api/v1/studies",
        json={"name": "long", "title": "x" * 201, "protocol_toml": source.decode()},
    )
    assert too_long.status_code == 422
    protocol = tmp_path / "lab.toml"
    protocol.write_text(source.decode())
    result = CliRunner().invoke(
        cli,
        [
            "study",
            "create",
            "--protocol",
            str(protocol),
            "--name",
            "cli",
            "--title",
            "From the shell",
            "--json",
        ],
        env={"TRUSTLAB_DATABASE_URL": database_url},
    )
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout)["title"] == "From the shell"


def test_the_console_waiting_for_the_tablet_offers_its_link_and_warns_of_a_loopback_address(
    lab: Lab,
) -> None:
    """While the console waits for consent on the tablet it shows the participant's tablet link
    as a QR code; a link on 127.0.0.1 says a tablet cannot reach it (it is the tablet itself)."""
    lab.enrol_and_assign("W01", questionnaires=False)
    page = lab.experimenter.get("/stations/lab-1").text
    assert "waiting for W01 to give consent on the tablet" in page
    assert "No tablet link is issued for W01" in page
    issued = lab.experimenter.post(f"/api/v1/studies/{lab.study}/participants/W01/link")
    token = issued.json()["token"]
    page = lab.experimenter.get("/stations/lab-1").text
    assert f"http://testserver/t/{token}" in page and "<svg" in page
    assert "a tablet cannot reach it" not in page
    local = lab.experimenter.get("/stations/lab-1", headers={"host": "127.0.0.1:8000"}).text
    assert f"http://127.0.0.1:8000/t/{token}" in local
    assert "a tablet cannot reach it" in local
    fill_pre_study(lab.tablets.setdefault("W01", tablet_client(lab.app, lab, "W01")))
    assert "tablet-link" not in lab.experimenter.get("/stations/lab-1").text  # nothing to wait for
