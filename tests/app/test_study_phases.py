"""Draft, pilot, live (issue 50, item 4): nobody enrols in a draft; pilot participants run as real
ones do but come from a sequence of their own, are marked, kept out of the analyses and can be
reset; going live freezes the protocol and starts the live sequence at its first entry."""

from __future__ import annotations

from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import func, select
from typer.testing import CliRunner

from app.cli import cli
from app.randomisation import entry_at, pilot_seed
from app.services import studies
from app.services.analysis_views import study_data
from app.services.privacy.sites import Scope
from app.services.sessions import verify
from app.tables import (
    Allocation,
    Answer,
    AuditEvent,
    LearnerState,
    Participant,
    Prompt,
    Response,
    Role,
    Study,
)
from tests.conftest import Lab, UserClientFactory, sqlite_only

DRAFT = "pilot-me"


@pytest.fixture
def admin(user_client: UserClientFactory) -> TestClient:
    return user_client(Role.ADMIN)


@pytest.fixture
def draft(lab: Lab, admin: TestClient) -> Lab:
    """The lab's study copied into a draft, which the lab now runs."""
    created = admin.post(
        "/api/v1/studies", json={"name": DRAFT, "copy_of": lab.study, "phase": "draft"}
    )
    assert created.status_code == 201, created.text
    assert created.json()["phase"] == "draft" and created.json()["live_at"] is None
    lab.study = DRAFT
    return lab


def _phase(admin: TestClient, phase: str) -> dict[str, object]:
    moved = admin.post(f"/api/v1/studies/{DRAFT}/phase", json={"phase": phase})
    assert moved.status_code == 200, moved.text
    return dict(moved.json())


def _expected(lab: Lab, *, pilot: bool, n: int) -> list[str]:
    """The first ``n`` conditions of the study's live or pilot sequence, from its seed."""
    with lab.database.read_session() as db:
        study = studies.get_study(db, lab.study)
        seed = bytes.fromhex(study.allocation_seed)
        conditions = [c.id for c in studies.protocol_of(study).conditions]
        sizes = studies.protocol_of(study).allocation.block_sizes
    seed = pilot_seed(seed) if pilot else seed
    return [entry_at(seed, "", conditions, sizes, i).condition for i in range(n)]


def _allocations(lab: Lab) -> list[tuple[str, bool, int | None, str]]:
    with lab.database.read_session() as db:
        rows = db.execute(
            select(
                Participant.code, Allocation.pilot, Allocation.sequence_index, Allocation.condition
            )
            .join(Allocation, Allocation.participant_id == Participant.id)
            .join(Study, Study.id == Participant.study_id)
            .where(Study.name == lab.study)
            .order_by(Participant.id)
        ).all()
    return [tuple(row) for row in rows]  # type: ignore[misc]


@sqlite_only("phase rules and pages; the pilot's sequence and reset are tested on both engines")
def test_nobody_enrols_in_a_draft(draft: Lab) -> None:
    refused = draft.experimenter.post(f"/api/v1/studies/{DRAFT}/participants", json={})
    assert refused.status_code == 409
    assert "draft" in refused.json()["detail"]
    with draft.database.read_session() as db:
        assert db.scalar(select(func.count()).select_from(Participant)) == 0


def test_a_pilot_runs_apart_and_going_live_starts_the_real_sequence_afresh(
    draft: Lab, admin: TestClient
) -> None:
    _phase(admin, "pilot")
    pilots = [draft.enrol_and_assign() for _ in range(3)]
    assert pilots[0] == "pilot-001"
    for _ in range(2):  # the last pilot practises and answers a session, as a real one would
        draft.start_session()
        assert draft.run_session() > 0
    curves = draft.experimenter.get(f"/studies/{DRAFT}/dashboard.json").json()
    assert curves["adaptation"]["data"] == []  # the live dashboard draws no pilot
    assert curves["measures"][0]["payload"]["data"] == []
    seated = draft.experimenter.get(f"/stations/{draft.station}")
    record = draft.experimenter.get(f"/studies/{DRAFT}/participants/{pilots[-1]}")
    assert 'title="A pilot participant: left out of the analyses">pilot<' in seated.text
    assert 'id="pilot-badge"' in record.text
    summary = _phase(admin, "live")
    assert summary["phase"] == "live" and summary["pilots"] == 3 and summary["live_at"]
    live = [
        draft.experimenter.post(f"/api/v1/studies/{DRAFT}/participants", json={}).json()["code"]
        for _ in range(4)
    ]
    assert live[0] == "P001"

    allocated = _allocations(draft)
    assert [row[0] for row in allocated] == pilots + live
    assert [row[1:3] for row in allocated] == [(True, i) for i in range(3)] + [
        (False, i) for i in range(4)
    ]
    assert [row[3] for row in allocated[:3]] == _expected(draft, pilot=True, n=3)
    assert [row[3] for row in allocated[3:]] == _expected(draft, pilot=False, n=4)

    listed = draft.experimenter.get(f"/api/v1/studies/{DRAFT}/participants").json()
    assert [p["pilot"] for p in listed] == [True] * 3 + [False] * 4
    counted = admin.get(f"/api/v1/studies/{DRAFT}").json()["enrolment"]
    assert sum(group["active"] for group in counted) == 4  # the pilots are not counted
    with draft.database.read_session() as db:
        study = studies.get_study(db, DRAFT)
        assert verify.verify_study(db, study_name=DRAFT).ok
        went_live = db.scalar(
            select(AuditEvent)
            .where(AuditEvent.study_id == study.id, AuditEvent.action == "study.phase_changed")
            .order_by(AuditEvent.id.desc())
        )
        assert went_live is not None
        assert went_live.details["protocol_sha256"] == study.protocol_sha256
        assert went_live.details["to"] == "live"
        dataset = study_data.load_dataset(db, study=study, scope=Scope.every_site())
        pilot_data = study_data.load_dataset(db, study=study, scope=Scope.every_site(), pilot=True)
    assert list(dataset.participants["participant"]) == live
    assert "pilot" not in dataset.participants.columns
    assert list(pilot_data.participants["participant"]) == pilots
    assert set(pilot_data.participants["pilot"]) == {1}
    assert pilot_data.manifest["participants"] == "pilot"
    assert set(pilot_data.steps["participant"]) == {pilots[-1]}
    assert set(pilot_data.responses["participant"]) == set(pilots)


def test_a_pilot_reset_deletes_the_pilots_and_nothing_else(draft: Lab, admin: TestClient) -> None:
    _phase(admin, "pilot")
    pilot = draft.enrol_and_assign()
    draft.start_session()
    draft.run_session()
    _phase(admin, "live")
    freed = draft.experimenter.delete(f"/api/v1/stations/{draft.station}/participant")
    assert freed.status_code in (200, 204), freed.text
    real = draft.enrol_and_assign()
    draft.start_session()
    draft.run_session()

    def rows(code: str) -> dict[str, int]:
        with draft.database.read_session() as db:
            own = select(Participant.id).where(Participant.code == code)
            return {
                table.__tablename__: db.scalar(
                    select(func.count()).select_from(table).where(table.participant_id.in_(own))  # type: ignore[attr-defined]
                )
                or 0
                for table in (Allocation, LearnerState, Prompt, Answer, Response)
            }

    kept_before = rows(real)
    assert all(rows(pilot).values())
    reset = admin.post(f"/api/v1/studies/{DRAFT}/pilot/reset")
    assert reset.status_code == 200, reset.text
    assert reset.json()["participants"] == [pilot]
    assert reset.json()["removed"]["participant"] == 1
    assert rows(real) == kept_before
    with draft.database.read_session() as db:
        assert db.scalar(select(Participant).where(Participant.code == pilot)) is None
        assert not any(rows(pilot).values())
        study_id = studies.get_study(db, DRAFT).id
        named = db.scalars(select(AuditEvent.subject).where(AuditEvent.study_id == study_id)).all()
        assert pilot not in named and any(s.startswith("~pilot-") for s in named)
        assert "study.pilot_reset" in db.scalars(select(AuditEvent.action)).all()
        assert verify.verify_study(db, study_name=DRAFT).ok
    # The next pilot code is free again, and a second reset has nothing to do.
    again = admin.post(f"/api/v1/studies/{DRAFT}/pilot/reset")
    assert again.json() == {"participants": [], "removed": {}}


@sqlite_only("phase rules and pages; the pilot's sequence and reset are tested on both engines")
def test_the_way_back_is_short(draft: Lab, admin: TestClient) -> None:
    _phase(admin, "pilot")
    draft.enrol_and_assign(questionnaires=False)
    refused = admin.post(f"/api/v1/studies/{DRAFT}/phase", json={"phase": "draft"})
    assert refused.status_code == 409 and "reset the pilot first" in refused.json()["detail"]
    assert admin.post(f"/api/v1/studies/{DRAFT}/pilot/reset").status_code == 200
    assert _phase(admin, "draft")["phase"] == "draft"
    assert _phase(admin, "live")["phase"] == "live"
    for phase in ("draft", "pilot"):
        stays = admin.post(f"/api/v1/studies/{DRAFT}/phase", json={"phase": phase})
        assert stays.status_code == 409 and "stays live" in stays.json()["detail"]
    unknown = admin.post(f"/api/v1/studies/{DRAFT}/phase", json={"phase": "beta"})
    assert unknown.status_code == 422
    experimenter = draft.experimenter.post(f"/api/v1/studies/{DRAFT}/phase", json={"phase": "live"})
    assert experimenter.status_code == 403


@sqlite_only("phase rules and pages; the pilot's sequence and reset are tested on both engines")
def test_the_pages_ask_first_and_mark_the_pilots(
    draft: Lab, user_client: UserClientFactory
) -> None:
    admin = user_client(Role.ADMIN)
    page = admin.get(f"/studies/{DRAFT}")
    assert 'id="phase-badge">draft<' in page.text
    assert "Nobody can enrol while the study is a draft" in page.text
    asked = admin.get(f"/admin/studies/{DRAFT}/phase?to=pilot")
    assert asked.status_code == 200 and "Start the pilot of" in asked.text
    started = admin.post(
        f"/admin/studies/{DRAFT}/phase", data={"phase": "pilot"}, follow_redirects=False
    )
    assert started.status_code == 303
    code = draft.enrol_and_assign(questionnaires=False)
    page = admin.get(f"/studies/{DRAFT}")
    assert "Enrol a pilot participant" in page.text
    assert f'>{code}</a> <span class="badge attention"' in page.text
    refused = admin.post(
        f"/admin/studies/{DRAFT}/phase", data={"phase": "draft"}, follow_redirects=False
    )
    assert refused.status_code == 409 and "reset the pilot first" in refused.text
    asked = admin.get(f"/admin/studies/{DRAFT}/pilot/reset")
    assert "Delete 1 pilot participant" in asked.text
    done = admin.post(f"/admin/studies/{DRAFT}/pilot/reset", follow_redirects=False)
    assert done.status_code == 303
    live = admin.get(f"/admin/studies/{DRAFT}/phase?to=live")
    assert "This cannot be undone" in live.text and "Go live" in live.text
    admin.post(f"/admin/studies/{DRAFT}/phase", data={"phase": "live"})
    page = admin.get(f"/studies/{DRAFT}")
    assert 'id="phase-badge"' not in page.text and 'id="study-phase"' not in page.text
    stays = admin.get(f"/admin/studies/{DRAFT}/phase?to=draft")
    assert "so it stays live" in " ".join(stays.text.split())
    assert 'name="phase"' not in stays.text


@sqlite_only("phase rules and pages; the pilot's sequence and reset are tested on both engines")
def test_the_command_line_moves_and_resets(lab: Lab, database_url: str) -> None:
    def run(*args: str) -> str:
        result = CliRunner().invoke(cli, list(args), env={"TRUSTLAB_DATABASE_URL": database_url})
        assert result.exit_code == 0, result.output
        return result.output

    assert "(pilot)" in run(
        "study", "create", "--name", "cli-pilot", "--copy-of", lab.study, "--phase", "pilot"
    )
    lab.study = "cli-pilot"
    lab.enrol_and_assign(questionnaires=False)
    assert "pilot" in run("study", "list")
    assert "deleted 1 pilot participant(s) (pilot-001)" in run(
        "study", "reset-pilot", "cli-pilot", "--yes"
    )
    assert "is live" in run("study", "phase", "cli-pilot", "live", "--yes")
    refused = CliRunner().invoke(
        cli, ["study", "phase", "cli-pilot", "draft"], env={"TRUSTLAB_DATABASE_URL": database_url}
    )
    assert refused.exit_code != 0 and "stays live" in refused.output


@sqlite_only("phase rules and pages; the pilot's sequence and reset are tested on both engines")
def test_a_study_made_in_the_browser_starts_as_a_draft_unless_told(
    lab: Lab, admin: TestClient
) -> None:
    form = admin.get("/admin/studies/new")
    assert 'name="phase" value="draft" checked' in form.text
    for name, phase in (("from-form", "draft"), ("straight-live", "live")):
        created = admin.post(
            "/admin/studies",
            data={"name": name, "start": "study", "from_study": lab.study, "phase": phase},
            follow_redirects=False,
        )
        assert created.status_code == 303, created.text
    bad = admin.post(
        "/admin/studies",
        data={"name": "odd", "start": "study", "from_study": lab.study, "phase": "beta"},
    )
    assert bad.status_code == 422 and "choose one of draft, pilot, live" in bad.text
    with lab.database.read_session() as db:
        assert studies.get_study(db, "from-form").phase == "draft"
        assert studies.get_study(db, "from-form").live_at is None
        assert studies.get_study(db, "straight-live").phase == "live"
        assert db.scalar(select(Study).where(Study.name == "odd")) is None


@sqlite_only("phase rules and pages; the pilot's sequence and reset are tested on both engines")
def test_the_pilots_export_apart_marked_as_pilot(
    draft: Lab, admin: TestClient, database_url: str, tmp_path: Path
) -> None:
    _phase(admin, "pilot")
    pilot = draft.enrol_and_assign()
    _phase(admin, "live")
    draft.experimenter.delete(f"/api/v1/stations/{draft.station}/participant")
    real = draft.enrol_and_assign()

    def export(*extra: str) -> str:
        out = tmp_path / f"wide{len(extra)}.csv"
        result = CliRunner().invoke(
            cli,
            ["export", "--study", DRAFT, "--format", "wide-csv", "--out", str(out), *extra],
            env={"TRUSTLAB_DATABASE_URL": database_url},
        )
        assert result.exit_code == 0, result.output
        return out.read_text()

    study_rows, pilot_rows = export(), export("--pilot")
    assert real in study_rows and pilot not in study_rows
    assert pilot in pilot_rows and real not in pilot_rows
    header = pilot_rows.splitlines()[0].split(",")
    assert "pilot" in header and "pilot" not in study_rows.splitlines()[0].split(",")
    row = dict(zip(header, pilot_rows.splitlines()[1].split(","), strict=False))
    assert row["pilot"] == "1"
    # The same from the analysis page, for whoever downloads rather than types commands.
    page = admin.get(f"/studies/{DRAFT}/analysis").text
    assert 'id="pilot-downloads"' in page and "?pilot=1" in page
    download = admin.get(f"/studies/{DRAFT}/exports/wide-csv?pilot=1")
    assert download.status_code == 200
    assert f"{DRAFT}-pilot-participants_wide.csv" in download.headers["content-disposition"]
    assert pilot in download.text and real not in download.text
    assert real in admin.get(f"/studies/{DRAFT}/exports/wide-csv").text
