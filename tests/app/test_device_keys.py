"""Device keys: the REST dependency and the key lookup agree on which bearer values can be keys."""

from __future__ import annotations

from fastapi.testclient import TestClient
from sqlalchemy import select

from app.security import token_digest
from app.services.sessions.stations import KEY_MAX_LENGTH
from app.tables import Device, Station
from tests.conftest import Lab


def _store_key(lab: Lab, key: str) -> None:
    """A device of the lab's station holding ``key`` (longer than issued keys: probes limits)."""
    with lab.database.writing() as db:
        station_id = db.scalar(select(Station.id).where(Station.name == lab.station))
        db.add(
            Device(
                station_id=station_id,
                label="long-key",
                key_hash=token_digest(key),
                key_prefix=key[:10],
                created_by="tests",
            )
        )
        db.commit()


def test_the_longest_key_the_api_lets_through_authenticates(lab: Lab) -> None:
    longest = "tlk_" + "a" * (KEY_MAX_LENGTH - 4)
    _store_key(lab, longest)
    with TestClient(lab.app, headers={"Authorization": f"Bearer {longest}"}) as robot:
        assert robot.get("/api/v1/station").status_code == 200
        with robot.websocket_connect("/api/v1/station/ws") as ws:
            assert ws.receive_json()["type"] == "hello"


def test_a_longer_bearer_value_is_refused_before_the_body_is_read(lab: Lab) -> None:
    too_long = "tlk_" + "a" * (KEY_MAX_LENGTH - 3)
    _store_key(lab, too_long)
    with TestClient(lab.app, headers={"Authorization": f"Bearer {too_long}"}) as robot:
        refused = robot.post("/api/v1/station/prompts", json={"category": 7})
        assert refused.status_code == 401
        assert refused.json()["detail"] == (
            "send the device key as the header 'Authorization: Bearer tlk_…'"
        )
        assert robot.get("/api/v1/station").status_code == 401
