"""Limits, throttling, the audit log, and backups that `trustlab verify` accepts after a restore."""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path

from fastapi.testclient import TestClient
from sqlalchemy import func, select
from typer.testing import CliRunner

from app.cli import cli
from app.db import Database
from app.tables import AuditEvent, Participant, Role, Study
from tests.conftest import (
    CSRF_INPUT,
    PASSWORD,
    TRUST_ANSWERS,
    Lab,
    UserClientFactory,
    make_user,
    sqlite_only,
)


@sqlite_only("the body limit answers before any route runs")
def test_oversized_bodies_get_a_json_413(client: TestClient) -> None:
    declared = client.post(
        "/api/v1/session",
        content=b"x" * (1024 * 1024 + 1),
        headers={"content-type": "application/json"},
    )
    assert declared.status_code == 413
    assert declared.json() == {"detail": "the request body is larger than 1024 KiB"}

    def chunks():  # no Content-Length: counted as it arrives
        for _ in range(20):
            yield b"y" * 65536

    streamed = client.post(
        "/api/v1/session", content=chunks(), headers={"content-type": "application/json"}
    )
    assert streamed.status_code == 413


@sqlite_only("the body is refused by its schema, before any query")
def test_malformed_wrong_typed_unknown_and_overlong_input_get_one_clear_422(
    user_client: UserClientFactory,
) -> None:
    client = user_client("admin", Role.ADMIN)
    cases = {
        "malformed JSON": (b'{"name": "x", ', "JSON decode error"),
        "wrong type": (json.dumps({"name": 7, "protocol_toml": "x"}).encode(), "name: "),
        "unknown field": (
            json.dumps({"name": "x", "protocol_toml": "x", "colour": "red"}).encode(),
            "colour: Extra inputs are not permitted",
        ),
        "text too long": (
            json.dumps({"name": "n" * 65, "protocol_toml": "x"}).encode(),
            "name: String should have at most 64 characters",
        ),
    }
    with client.app.state.database.read_session() as db:  # type: ignore[attr-defined]
        studies_before = db.scalar(select(func.count()).select_from(Study))
    for case, (body, says) in cases.items():
        response = client.post(
            "/api/v1/studies", content=body, headers={"content-type": "application/json"}
        )
        assert response.status_code == 422, case
        detail = response.json()["detail"]
        assert says in detail and "\n" not in detail, (case, detail)
    with client.app.state.database.read_session() as db:  # type: ignore[attr-defined]
        assert db.scalar(select(func.count()).select_from(Study)) == studies_before


def _login_form(client: TestClient, username: str, password: str) -> int:
    token = CSRF_INPUT.search(client.get("/login").text)
    assert token
    return client.post(
        "/login",
        data={"username": username, "password": password, "csrf_token": token.group(1)},
        follow_redirects=False,
    ).status_code


def test_repeated_failures_throttle_the_account(client: TestClient, database: Database) -> None:
    make_user(database, "ada", Role.EXPERIMENTER)
    make_user(database, "bob", Role.EXPERIMENTER)
    assert [_login_form(client, "ada", "wrong password") for _ in range(5)] == [401] * 5
    assert _login_form(client, "ada", PASSWORD) == 429  # even the right password, for a while
    page = client.post("/api/v1/session", json={"username": "ada", "password": PASSWORD})
    assert page.status_code == 429
    assert page.json()["detail"].startswith("too many failed sign-ins from this account; try")
    assert _login_form(client, "bob", PASSWORD) == 303  # other accounts are unaffected


def test_every_kind_of_change_is_audited_and_admins_can_export_it(
    lab: Lab, app: object, user_client: UserClientFactory, database: Database
) -> None:
    code = lab.enrol_and_assign()
    lab.start_session()
    lab.run_session()
    lab.start_session()
    lab.run_session()
    tablet = lab.tablets[code]
    tablet.post(
        "/api/v1/tablet/questionnaires/trust",
        json={"session": 1, "answers": {**TRUST_ANSWERS, "trust_1": "5"}},
    )
    tablet.post(
        "/api/v1/tablet/questionnaires/trust",
        json={"session": 1, "answers": {**TRUST_ANSWERS, "trust_1": "1"}},
    )
    lab.experimenter.post(f"/api/v1/studies/rt/participants/{code}/lock")
    admin = user_client(Role.ADMIN)
    device = admin.get("/api/v1/stations").json()[0]["devices"][0]["id"]
    admin.post(f"/api/v1/devices/{device}/revoke")
    admin.get("/studies/rt/exports/wide-csv")
    with database.read_session() as db:
        actions = set(db.scalars(select(AuditEvent.action)))
    assert {
        "user.signed_in",
        "participant.enrolled",
        "allocation.revealed",
        "station.assigned",
        "session.started",
        "session.ended",
        "answer.recorded",
        "participant.consented",
        "questionnaire.edited",
        "participant.locked",
        "participant.token_issued",
        "device.key_issued",
        "device.key_revoked",
        "export.downloaded",
    } <= actions
    page = admin.get("/admin/audit?action=questionnaire.")
    # the action breaks only at its dots on a narrow screen (<wbr>), and reads whole
    assert page.status_code == 200 and "questionnaire.<wbr>edited" in page.text
    exported = admin.get("/admin/audit.csv?action=participant.")
    rows = list(csv.DictReader(io.StringIO(exported.text)))
    assert {row["action"] for row in rows} >= {"participant.enrolled", "participant.locked"}
    assert all(row["action"].startswith("participant.") for row in rows)
    assert lab.experimenter.get("/admin/audit").status_code == 403


def test_backup_and_restore_round_trip(lab: Lab, database_url: str, tmp_path: Path) -> None:
    code = lab.enrol_and_assign()
    lab.start_session()
    lab.run_session()
    runner = CliRunner()
    env = {"TRUSTLAB_DATABASE_URL": database_url}
    target = tmp_path / "backup.dump"
    made = runner.invoke(cli, ["db", "backup", "--out", str(target)], env=env)
    assert made.exit_code == 0, made.output
    assert target.stat().st_size > 0
    again = runner.invoke(cli, ["db", "backup", "--out", str(target)], env=env)
    assert again.exit_code == 2 and "choose a new file name" in again.stderr
    # After the backup: more happens (a new participant), which the restore must undo.
    lab.experimenter.post("/api/v1/studies/rt/participants", json={"code": "LATER"})
    with lab.database.read_session() as db:
        assert db.scalar(select(func.count()).select_from(Participant)) == 2
    lab.database.dispose()
    unconfirmed = runner.invoke(cli, ["db", "restore", str(target)], env=env)
    assert unconfirmed.exit_code == 2 and "add --yes to confirm" in unconfirmed.stderr
    restored = runner.invoke(cli, ["db", "restore", str(target), "--yes"], env=env)
    assert restored.exit_code == 0, restored.output
    with lab.database.read_session() as db:
        codes = db.scalars(select(Participant.code)).all()
    assert codes == [code]
    checked = runner.invoke(cli, ["verify", "--study", "rt", "--json"], env=env)
    assert checked.exit_code == 0, checked.output
    report = json.loads(checked.stdout)
    assert report["ok"] and report["answers"] == 3
    bogus = tmp_path / "bogus.dump"
    bogus.write_bytes(b"not a backup")
    refused = runner.invoke(cli, ["db", "restore", str(bogus), "--yes"], env=env)
    assert refused.exit_code != 0
    assert refused.stderr.startswith("error: ")
