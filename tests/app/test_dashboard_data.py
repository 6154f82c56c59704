"""The live dashboard's data: what a blinded experimenter may see of it."""

from __future__ import annotations

import json
from collections.abc import Iterator
from typing import Any

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient

from app.db import Database
from app.protocol import parse_protocol
from app.services import studies
from app.services.audit import Actor
from app.tables import Role
from tests.conftest import EXP3_ONLY, Lab, UserClientFactory, protocol_text

SWAPPED_LABELS = {
    "blinded = false": "blinded = true",
    'neutral_label = "Group A"': 'neutral_label = "Group swap"',
    'neutral_label = "Group B"': 'neutral_label = "Group A"',
    'neutral_label = "Group swap"': 'neutral_label = "Group B"',
}
"""A blinded protocol whose neutral labels run against the conditions' order (C1 is Group B), so
neither the ids nor their order may show through."""


@pytest.fixture
def blind_lab(app: FastAPI, database: Database, user_client: UserClientFactory) -> Iterator[Lab]:
    """A blinded study 'blind' with one participant of each condition through session 1."""
    with database.writing() as db:
        studies.create_study(
            db,
            name="blind",
            loaded=parse_protocol(protocol_text(**EXP3_ONLY, **SWAPPED_LABELS)),
            actor=Actor.system(),
        )
    admin = user_client(Role.ADMIN)
    assert admin.post("/api/v1/stations", json={"name": "lab-b"}).status_code == 201
    key = admin.post("/api/v1/stations/lab-b/devices", json={"label": "pepper"}).json()["key"]
    analyst = user_client(Role.ANALYST)
    with TestClient(app, headers={"Authorization": f"Bearer {key}"}) as robot:
        lab = Lab(app, database, "blind", "lab-b", key, user_client(Role.EXPERIMENTER), robot, {})
        seen: set[str] = set()
        while seen != {"C1", "C2"}:
            code = lab.enrol_and_assign()
            lab.start_session()  # the familiarisation run
            lab.run_session()
            lab.start_session()
            lab.run_session(preferred=1)
            lab.fill_pending_questionnaires()
            participants = analyst.get("/api/v1/studies/blind/participants").json()
            seen |= {p["condition"] for p in participants if p["code"] == code}
        yield lab


def _records(data: dict[str, Any]) -> list[list[dict[str, Any]]]:
    """Every payload's table of numbers (trust cells per measure, then the adaptation curves)."""
    return [m["payload"]["cells"] for m in data["measures"]] + [data["adaptation"]["curves"]]


def test_a_blinded_experimenter_sees_neither_condition_ids_nor_their_order(
    blind_lab: Lab, user_client: UserClientFactory
) -> None:
    response = blind_lab.experimenter.get("/studies/blind/dashboard.json")
    data = response.json()
    assert data["questionnaires"] > 0 and data["answers"] > 0
    for condition in ("C1", "C2", "Exp3", "Meta-learned"):
        assert condition not in response.text
    for table in _records(data):
        groups = [row.get("group", row.get("condition")) for row in table]
        assert set(groups) == {"Group A", "Group B"}
        assert groups == sorted(groups)  # listed by label, not by the hidden condition
        assert all(set(row) & {"condition", "group"} for row in table)
    names = [t["name"] for t in data["measures"][0]["payload"]["data"]]
    assert names == ["Group A", "Group B"]

    analyst = user_client(Role.ANALYST).get("/studies/blind/dashboard.json").json()
    assert [t["name"] for t in analyst["measures"][0]["payload"]["data"]] == ["C1", "C2"]
    assert json.dumps(analyst).count('"Group ') == 0
