"""Withdrawal with erasure: nothing of the participant left in any table, any export or the
database file; their allocation slot kept so the sequence still balances and verifies; everyone
else untouched; each refusal in one line with nothing changed."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import delete, func, select
from sqlalchemy.exc import DBAPIError
from typer.testing import CliRunner

from app.cli import cli
from app.services import audit
from app.services.audit import Actor
from app.services.privacy import erasure, subject_access
from app.services.sessions import verify
from app.settings import Settings
from app.tables import (
    Allocation,
    Answer,
    AuditEvent,
    ErasureInProgress,
    LearnerState,
    Participant,
    Prompt,
    Role,
    RoomPresence,
)
from tests.app.personal_data import (
    STRATUM,
    dump_database,
    enrol_with_data,
    heard_in_the_room_then_unseated,
    mentions,
    personal_data_study,
    run_cli,
)
from tests.conftest import Lab, UserClientFactory, sqlite_only


def test_an_erased_participant_leaves_no_trace_and_their_slot_keeps_the_sequence_whole(
    lab: Lab, database_url: str, tmp_path: Path
) -> None:
    lab.study = personal_data_study(lab.database)
    enrol_with_data(lab, "GONE-4711")
    enrol_with_data(lab, "STAYS-0815")
    before = run_cli(
        database_url,
        "export",
        "--study",
        lab.study,
        "--format",
        "all",
        "--out",
        str(tmp_path / "before"),
    )
    assert before.exit_code == 0, before.output
    with lab.database.read_session() as db:
        allocations = db.scalar(select(func.count()).select_from(Allocation))
        kept_answers = db.scalar(
            select(func.count())
            .select_from(Answer)
            .join(Participant)
            .where(Participant.code == "STAYS-0815")
        )

    erased = run_cli(
        database_url,
        "participant",
        "withdraw",
        "--study",
        lab.study,
        "--code",
        "GONE-4711",
        "--erase",
        "--yes",
    )

    assert erased.exit_code == 0, erased.output
    assert "erased GONE-4711" in erased.output and "allocation slot stays" in erased.output
    assert str(tmp_path / "before") in erased.output  # the earlier export is listed
    assert mentions(dump_database(lab.database, lab.app.state.database), "GONE-4711") == []
    after = run_cli(
        database_url,
        "export",
        "--study",
        lab.study,
        "--format",
        "all",
        "--out",
        str(tmp_path / "after"),
    )
    assert after.exit_code == 0, after.output
    files = list((tmp_path / "after").iterdir())
    assert len(files) > 5
    for path in files:
        assert mentions(path.read_bytes(), "GONE-4711") == [], path.name
    wide = next(p for p in files if p.name.endswith("wide.csv")).read_text()
    assert "STAYS-0815" in wide
    with lab.database.read_session() as db:
        assert db.scalar(select(func.count()).select_from(Allocation)) == allocations
        assert (
            db.scalar(
                select(func.count())
                .select_from(Answer)
                .join(Participant)
                .where(Participant.code == "STAYS-0815")
            )
            == kept_answers
        )
        slot = db.scalar(select(Participant).where(Participant.erased_at.is_not(None)))
        assert slot is not None and erasure.is_erased_code(slot.code) and slot.status == "withdrawn"
        assert slot.strata == {} and slot.token_hash is None and slot.language is None
        assert db.scalar(select(func.count()).select_from(ErasureInProgress)) == 0
        event = db.scalar(select(AuditEvent).where(AuditEvent.action == "participant.erased"))
        assert event is not None and event.subject == slot.code
        report = verify.verify_study(db, study_name=lab.study)
    assert report.ok, report.to_json()
    # The stratum's sequence goes on after the erased slot: the next enrolment verifies too.
    enrolled = lab.experimenter.post(
        f"/api/v1/studies/{lab.study}/participants",
        json={"code": "NEXT-1", "strata": {"hand": STRATUM}},
    )
    assert enrolled.status_code == 201, enrolled.text
    with lab.database.read_session() as db:
        assert verify.verify_study(db, study_name=lab.study).ok


@sqlite_only("refusals happen before anything is written; the database does not matter")
def test_each_refusal_is_one_line_and_changes_nothing(lab: Lab, database_url: str) -> None:
    lab.study = personal_data_study(lab.database)
    enrol_with_data(lab, "P-ONE")
    keep_only = personal_data_study(
        lab.database, "kept", **{"[allocation]": '[withdrawal]\noptions = ["keep"]\n\n[allocation]'}
    )
    erase_only = personal_data_study(
        lab.database,
        "erasing",
        **{"[allocation]": '[withdrawal]\noptions = ["erase"]\n\n[allocation]'},
    )
    for study in (keep_only, erase_only):
        assert (
            lab.experimenter.post(
                f"/api/v1/studies/{study}/participants",
                json={"code": "Q1", "strata": {"hand": "x"}},
            ).status_code
            == 201
        )

    def refused(*args: str) -> str:
        result = run_cli(database_url, "participant", "withdraw", *args)
        assert result.exit_code != 0, result.output
        lines = result.stderr.strip().splitlines()
        assert len(lines) == 1 and "Traceback" not in result.output, result.output
        return lines[0]

    assert "add --yes" in refused("--study", lab.study, "--code", "P-ONE", "--erase")
    assert "no participant 'NOBODY'" in refused(
        "--study", lab.study, "--code", "NOBODY", "--erase", "--yes"
    )
    assert "has no 'erase'" in refused("--study", keep_only, "--code", "Q1", "--erase", "--yes")
    assert "erase instead" in refused("--study", erase_only, "--code", "Q1")
    with lab.database.read_session() as db:
        answers = db.scalar(select(func.count()).select_from(Answer))
        assert (
            answers
            and db.scalar(select(Participant.erased_at).where(Participant.code == "P-ONE")) is None
        )
    ok = run_cli(
        database_url,
        "participant",
        "withdraw",
        "--study",
        lab.study,
        "--code",
        "P-ONE",
        "--erase",
        "--yes",
    )
    assert ok.exit_code == 0, ok.output
    assert "already erased" in refused("--study", lab.study, "--code", "P-ONE", "--erase", "--yes")
    kept = run_cli(
        database_url,
        "participant",
        "withdraw",
        "--study",
        erase_only,
        "--code",
        "Q1",
        "--erase",
        "--yes",
    )
    assert kept.exit_code == 0 and "(rows removed: learner 3)" in kept.output


@sqlite_only("the guard's SQL differs per database; test_schema checks PostgreSQL's exists")
def test_the_marker_opens_the_guard_for_the_marked_participant_only(lab: Lab) -> None:
    lab.study = personal_data_study(lab.database)
    enrol_with_data(lab, "P-MARKED")
    enrol_with_data(lab, "P-OTHER")
    with lab.database.writing() as db:
        marked, other = (
            db.scalar(select(Participant.id).where(Participant.code == code))
            for code in ("P-MARKED", "P-OTHER")
        )
        db.add(ErasureInProgress(participant_id=marked, study_id=1))
        db.flush()
        db.execute(delete(Answer).where(Answer.participant_id == marked))
        with pytest.raises(DBAPIError, match="append-only"):
            db.execute(delete(Answer).where(Answer.participant_id == other))
        db.rollback()
    with lab.database.writing() as db:
        with pytest.raises(DBAPIError, match="append-only"):
            db.execute(delete(Prompt).where(Prompt.participant_id == marked))
        db.rollback()


@sqlite_only("the web form; the erasure itself is checked on both databases above")
def test_the_web_page_asks_which_option_and_for_the_code_before_erasing(
    lab: Lab, user_client: UserClientFactory
) -> None:
    lab.study = personal_data_study(lab.database)
    enrol_with_data(lab, "P-WEB")
    experimenter = user_client(Role.EXPERIMENTER, "web-experimenter")
    page = experimenter.get(f"/studies/{lab.study}/participants/P-WEB/withdraw")
    assert page.status_code == 200
    assert (
        'value="keep"' in page.text and 'value="erase"' in page.text and "confirm_code" in page.text
    )
    form = experimenter.post(
        f"/studies/{lab.study}/participants/P-WEB/withdraw",
        data={"data": "erase", "confirm_code": "P-WE"},
    )
    assert form.status_code == 422 and "Type P-WEB to confirm" in form.text
    with lab.database.read_session() as db:
        assert db.scalar(select(Participant.erased_at).where(Participant.code == "P-WEB")) is None
    done = experimenter.post(
        f"/studies/{lab.study}/participants/P-WEB/withdraw",
        data={"data": "erase", "confirm_code": "P-WEB"},
    )
    assert done.status_code == 200 and "Erased P-WEB" in done.text
    study_page = experimenter.get(f"/studies/{lab.study}")
    assert "P-WEB" not in study_page.text and "(1) was erased" in study_page.text


@sqlite_only("the API's validation; the erasure itself is checked on both databases above")
def test_the_api_needs_the_code_repeated(lab: Lab, client: TestClient) -> None:
    lab.study = personal_data_study(lab.database)
    enrol_with_data(lab, "P-API")
    url = f"/api/v1/studies/{lab.study}/participants/P-API/erase"
    wrong = lab.experimenter.post(url, json={"confirm": "P-AP"})
    assert wrong.status_code == 422 and "confirm must repeat" in wrong.text
    done = lab.experimenter.post(url, json={"confirm": "P-API"})
    assert done.status_code == 200, done.text
    body = done.json()
    assert body["removed"]["answer"] == 3 and body["removed"]["response"] > 0
    again = lab.experimenter.post(url, json={"confirm": "P-API"})
    assert again.status_code == 409 and "already erased" in again.json()["detail"]
    listed = lab.experimenter.get(f"/api/v1/studies/{lab.study}/participants").json()
    assert all(p["code"] != "P-API" and not p["code"].startswith("~") for p in listed)


def test_a_code_enrolled_again_after_its_erasure_can_be_erased_again_and_again(
    lab: Lab, database_url: str, settings: Settings
) -> None:
    """The pseudonym is a hash of the code: the second person's erasure must not meet the
    first's row (it was a 500 from the API and a traceback from the command line)."""
    lab.study = personal_data_study(lab.database)
    url = f"/api/v1/studies/{lab.study}/participants/AGAIN-7/erase"
    enrol_with_data(lab, "AGAIN-7")
    assert lab.experimenter.post(url, json={"confirm": "AGAIN-7"}).status_code == 200
    enrol_with_data(lab, "AGAIN-7")
    secret = settings.secret.decode()
    by_cli = CliRunner().invoke(
        cli,
        ["participant", "withdraw", "--study", lab.study, "--code", "AGAIN-7", "--erase", "--yes"],
        env={"TRUSTLAB_DATABASE_URL": database_url, "TRUSTLAB_SECRET_KEY": secret},
    )
    assert by_cli.exit_code == 0, by_cli.output
    assert "erased AGAIN-7" in by_cli.output
    enrol_with_data(lab, "AGAIN-7")
    third = lab.experimenter.post(url, json={"confirm": "AGAIN-7"})
    assert third.status_code == 200, third.text
    again = lab.experimenter.post(url, json={"confirm": "AGAIN-7"})
    assert again.status_code == 409 and "already erased" in again.json()["detail"]
    with lab.database.read_session() as db:
        slots = list(db.scalars(select(Participant).where(Participant.erased_at.is_not(None))))
        report = verify.verify_study(db, study_name=lab.study)
    assert len(slots) == 3 and len({slot.code for slot in slots}) == 3
    assert all(erasure.is_erased_code(slot.code) for slot in slots)
    assert report.ok, report.to_json()
    assert mentions(dump_database(lab.database, lab.app.state.database), "AGAIN-7") == []


@sqlite_only("paths on disk; the audit rows they come from are the same on both engines")
def test_earlier_backups_are_found_from_any_folder(
    lab: Lab, database_url: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A backup made with a relative --out was listed as "no longer there" by an erasure run
    from another folder: backups and exports are recorded with absolute paths."""
    lab.study = personal_data_study(lab.database)
    enrol_with_data(lab, "P-COPIED")
    made_in = tmp_path / "made-here"
    made_in.mkdir()
    monkeypatch.chdir(made_in)
    for name in ("kept.db", "deleted.db"):
        made = run_cli(database_url, "db", "backup", "--out", f"backups/{name}")
        assert made.exit_code == 0, made.output
    (made_in / "backups" / "deleted.db").unlink()
    exported = run_cli(
        database_url, "export", "--study", lab.study, "--format", "wide-csv", "--out", "w.csv"
    )
    assert exported.exit_code == 0, exported.output
    with lab.database.writing() as db:  # as recorded before: the path as typed
        audit.record(
            db, actor=Actor.command_line(), action="db.backed_up", details={"file": "old/b.db"}
        )
        db.commit()
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    done = lab.experimenter.post(
        f"/api/v1/studies/{lab.study}/participants/P-COPIED/erase", json={"confirm": "P-COPIED"}
    )
    assert done.status_code == 200, done.text
    copies = {copy["where"]: copy["exists"] for copy in done.json()["earlier_copies"]}
    assert copies == {
        str(made_in / "backups" / "kept.db"): True,
        str(made_in / "backups" / "deleted.db"): False,
        str(made_in / "w.csv"): True,
        "old/b.db (relative to the folder it was written from)": None,
    }


@sqlite_only("the form's rendering; no query differs")
def test_a_refused_withdraw_form_comes_back_with_every_choice_made(
    lab: Lab, user_client: UserClientFactory
) -> None:
    """A mistyped code brought the form back on "Keep it", so the next submit kept the data."""
    lab.study = personal_data_study(lab.database)
    enrol_with_data(lab, "P-TYPO")
    experimenter = user_client(Role.EXPERIMENTER, "typo-experimenter")
    url = f"/studies/{lab.study}/participants/P-TYPO/withdraw"
    fresh = experimenter.get(url).text
    assert _checked(fresh) == ["keep"] and "autofocus" not in fresh
    refused = experimenter.post(
        url, data={"data": "erase", "confirm_code": "P-TYP", "reason": "moved <away>"}
    )
    assert refused.status_code == 422
    assert _checked(refused.text) == ["erase"]
    assert ">moved &lt;away&gt;</textarea>" in refused.text
    assert 'autofocus aria-invalid="true"' in refused.text
    # The layout: each choice a row of its own (radio beside its words), the code's caption
    # one piece of text beside the field.
    assert refused.text.count('<label class="check choice"><input type="radio"') == 2
    assert "<span>To erase, type the code <strong>P-TYPO</strong> again</span>" in refused.text


def _checked(page: str) -> list[str]:
    return re.findall(r'<input type="radio" name="data" value="(\w+)" checked>', page)


def test_an_erased_participants_ids_are_never_given_again(lab: Lab) -> None:
    """Robots, console forms and exports name steps by id: after the participant with the
    highest step id is erased, the next step must not get that id again (SQLite did, with no
    AUTOINCREMENT), nor the next answer or learner theirs."""
    lab.study = personal_data_study(lab.database)
    enrol_with_data(lab, "P-FIRST")
    enrol_with_data(lab, "P-HIGHEST")

    def highest() -> tuple[int | None, ...]:
        with lab.database.read_session() as db:
            return tuple(
                db.scalar(select(func.max(table.id))) for table in (Prompt, Answer, LearnerState)
            )

    before = highest()
    erased = lab.experimenter.post(
        f"/api/v1/studies/{lab.study}/participants/P-HIGHEST/erase", json={"confirm": "P-HIGHEST"}
    )
    assert erased.status_code == 200, erased.text
    assert highest() < before  # the highest rows are gone
    enrol_with_data(lab, "P-NEXT")
    after = highest()
    assert all(new > old for new, old in zip(after, before, strict=True)), (before, after)


def test_the_room_presence_of_an_unseated_participant_is_erased(lab: Lab) -> None:
    """What the recogniser heard stayed in room_presence when the participant had been
    unseated before the erasure (only the station they still sat at was cleared)."""
    lab.study = personal_data_study(lab.database)
    enrol_with_data(lab, "P-LEFT")
    heard_in_the_room_then_unseated(lab, "P-LEFT")
    with lab.database.read_session() as db:
        assert db.scalar(select(func.count()).select_from(RoomPresence)) == 1
        # Theirs, so in their own copy too (the registry's "room" section).
        record = subject_access.participant_record(db, study_name=lab.study, code="P-LEFT")
    assert record["room"]["last_said"]["words"] == "yes zebrafish certainly p-left"
    erased = lab.experimenter.post(
        f"/api/v1/studies/{lab.study}/participants/P-LEFT/erase", json={"confirm": "P-LEFT"}
    )
    assert erased.status_code == 200, erased.text
    assert erased.json()["removed"]["room_presence"] == 1
    assert mentions(dump_database(lab.database, lab.app.state.database), "P-LEFT") == []
