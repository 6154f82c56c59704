"""bench/pg_floor.py measures what it says: its routes really do an answer's PostgreSQL work.

The benchmark's figures argue that no answer route can meet issue 4's target on PostgreSQL on a
2-core machine (docs/performance.md); that argument holds only if the floor route sends the
answer's statements and commits them, and the write route commits its row. This checks both
against a real server, in-process.
"""

from __future__ import annotations

from typing import Any

import psycopg
import pytest
from fastapi.testclient import TestClient
from sqlalchemy.engine import make_url

from app.settings import Settings
from bench.api import prepare
from bench.pg_floor import _FLOOR_TABLE, _open_steps, floor_app

pytestmark = pytest.mark.parametrize(
    "engine_name", [pytest.param("postgresql", marks=pytest.mark.postgres)], indirect=True
)


def _counts(url: str, learner_participant: int) -> dict[str, Any]:
    dsn = make_url(url).set(drivername="postgresql").render_as_string(hide_password=False)
    with psycopg.connect(dsn) as conn:
        return {
            "answers": conn.execute(f"SELECT count(*) FROM {_FLOOR_TABLE}").fetchone()[0],  # type: ignore[index]
            "audits": conn.execute(
                "SELECT count(*) FROM audit_event WHERE action = 'answer.recorded'"
            ).fetchone()[0],  # type: ignore[index]
            "versions": conn.execute(
                "SELECT sum(version) FROM learner WHERE participant_id = %s",
                (learner_participant,),
            ).fetchone()[0],  # type: ignore[index]
        }


def test_the_floor_routes_do_and_commit_an_answers_work(
    database_url: str, settings: Settings
) -> None:
    keys = prepare(database_url, 1, exp3_only=True)
    body = _open_steps(database_url, 1)[0]
    before = _counts(database_url, body["participant"])
    assert before["answers"] == 0
    headers = {"Authorization": f"Bearer {keys[0]}"}
    with TestClient(floor_app(settings)) as client:
        for number in range(2):
            reply = client.post(
                "/bench/floor", json={**body, "idempotency_key": f"floor-{number}"}, headers=headers
            )
            assert reply.status_code == 200, reply.text
        after_floor = _counts(database_url, body["participant"])
        assert after_floor == {
            "answers": 2,
            "audits": before["audits"] + 2,
            "versions": before["versions"] + 2,
        }
        reply = client.post(
            "/bench/write", json={**body, "idempotency_key": "write"}, headers=headers
        )
        assert reply.status_code == 200, reply.text
        assert _counts(database_url, body["participant"]) == {**after_floor, "answers": 3}
        reply = client.post(
            "/bench/body", json={**body, "idempotency_key": "body"}, headers=headers
        )
        assert reply.status_code == 200, reply.text
        assert _counts(database_url, body["participant"]) == {**after_floor, "answers": 3}
