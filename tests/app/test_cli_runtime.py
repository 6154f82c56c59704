"""``trustlab station|device|verify`` against a real database."""

from __future__ import annotations

import json

from sqlalchemy import select, update

from app.tables import LearnerState
from tests.app.test_cli import run
from tests.conftest import Lab, sqlite_only


def test_device_create_makes_the_station_and_prints_one_json_object(database_url: str) -> None:
    code, out, _ = run(database_url, "device", "create", "--station", "lab-9", "--json")
    assert code == 0
    issued = json.loads(out)
    assert issued["station"] == "lab-9" and issued["station_created"] is True
    assert issued["key"].startswith("tlk_")
    code, out, _ = run(
        database_url, "device", "create", "--station", "lab-9", "--label", "hololens"
    )
    assert code == 0
    assert "created station" not in out and "tlk_" in out
    code, out, _ = run(database_url, "station", "list", "--json")
    assert json.loads(out) == {"stations": [{"name": "lab-9", "site": None, "participant": None}]}
    code, out, _ = run(database_url, "device", "revoke", str(issued["device_id"]))
    assert (code, out.strip()) == (0, f"revoked device {issued['device_id']}")
    code, _, err = run(database_url, "device", "revoke", str(issued["device_id"]))
    assert (code, err.strip()) == (1, f"error: device {issued['device_id']} is already revoked")
    code, _, err = run(database_url, "station", "create", "Bad Name")
    assert code == 2 and "station name 'Bad Name'" in err
    code, _, err = run(database_url, "station", "create", "lab-9\n")
    assert code == 2 and "station name 'lab-9\\n'" in err


@sqlite_only("the argument is refused before any query")
def test_an_id_no_row_can_have_is_refused_in_one_line(database_url: str) -> None:
    """30 digits used to reach SQLite's driver (OverflowError, a traceback)."""
    code, out, err = run(database_url, "device", "revoke", "1" + "0" * 29)
    assert code == 2 and "Traceback" not in out + err
    assert "device_id" in err.lower() or "DEVICE_ID" in err


def test_verify_is_clean_then_flags_tampering(lab: Lab, database_url: str) -> None:
    lab.enrol_and_assign()
    lab.start_session()
    lab.run_session()
    lab.start_session()
    lab.run_session()
    code, out, _ = run(database_url, "verify", "--study", lab.study, "--json")
    assert code == 0
    report = json.loads(out)
    assert report["ok"] is True and report["answers"] == 12 and report["findings"] == []
    code, out, _ = run(database_url, "verify", "--study", lab.study)
    assert code == 0 and out.strip().endswith("ok: every learner matches its replay")
    assert out.startswith(
        f"study {lab.study!r}: 1 participant, 3 learners, "
    )  # not "1 participants"
    with lab.database.writing() as db:
        db.execute(
            update(LearnerState).where(LearnerState.category == "conation").values(version=7)
        )
        db.commit()
    code, out, _ = run(database_url, "verify", "--study", lab.study, "--json")
    assert code == 1
    findings = json.loads(out)["findings"]
    assert findings[0]["check"] == "replay"
    assert "stored version 7 but 3 answers" in findings[0]["detail"]
    with lab.database.read_session() as db:
        assert (
            db.scalar(select(LearnerState.version).where(LearnerState.category == "affection")) == 3
        )
    code, out, _ = run(database_url, "verify", "--study", lab.study)
    assert code == 1 and out.strip().endswith(
        f"{len(findings)} problem{'s' * (len(findings) > 1)} found"
    )
    assert "(s)" not in out
