"""The live dashboard's data: the same payloads as the computation it replaced (the analysis
builders' DataFrame path, tests/app/dashboard_reference.py) on seeded studies, and what a blinded
experimenter may see of it."""

from __future__ import annotations

import json
import math
from typing import Any

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient
from sqlalchemy import delete, select, update
from sqlalchemy.orm import Session

from app.db import Database
from app.protocol import parse_protocol
from app.services import studies
from app.services.analysis_views import dashboard
from app.services.analysis_views.freshness import FreshnessCache
from app.services.audit import Actor
from app.tables import (
    ActorKind,
    Answer,
    Participant,
    ParticipantStatus,
    Prompt,
    Response,
    Role,
    Run,
    StudySession,
)
from bench.seed import seed_study
from tests.app import dashboard_reference
from tests.conftest import (
    EXP3_ONLY,
    Lab,
    UserClientFactory,
    client_of,
    create_blinded_study,
    protocol_text,
)

EXPERIMENTER = Actor(ActorKind.USER, "exp", Role.EXPERIMENTER)
ANALYST = Actor(ActorKind.USER, "ana", Role.ANALYST)


def assert_same(fast: Any, reference: Any, path: str = "data") -> None:
    """Equal payloads: same keys in the same order, same strings and integers, floats equal up to
    the order in which the database summed them (PostgreSQL may pick another plan)."""
    assert type(fast) is type(reference), (path, fast, reference)
    if isinstance(fast, dict):
        assert list(fast) == list(reference), path
        for key in fast:
            assert_same(fast[key], reference[key], f"{path}.{key}")
    elif isinstance(fast, list):
        assert len(fast) == len(reference), path
        for index, (a, b) in enumerate(zip(fast, reference, strict=True)):
            assert_same(a, b, f"{path}[{index}]")
    elif isinstance(fast, float):
        assert math.isclose(fast, reference, rel_tol=1e-12, abs_tol=1e-15), (path, fast, reference)
    else:
        assert fast == reference, (path, fast, reference)


def _both(database: Database, name: str, actor: Actor) -> tuple[dict[str, Any], dict[str, Any]]:
    with database.read_session() as db:
        study = studies.get_study(db, name)
        fast = json.loads(dashboard.encode(dashboard.dashboard_data(db, study=study, actor=actor)))
        reference = dashboard_reference.dashboard_data(db, study=study, actor=actor)
    return fast, reference


@pytest.mark.parametrize("participants", [1, 2, 40])
def test_fast_path_equals_the_previous_computation_on_seeded_studies(
    database: Database, participants: int
) -> None:
    seed_study(database, name="seeded", participants=participants, seed=participants)
    for actor in (EXPERIMENTER, ANALYST):
        fast, reference = _both(database, "seeded", actor)
        assert fast["answers"] > 0 and fast["questionnaires"] > 0
        assert_same(fast, reference)


def test_fast_path_equals_the_previous_computation_on_gaps_and_withdrawals(
    database: Database,
) -> None:
    """Withdrawn participants, a session answered by one participant only (n = 1: no SD, no CI),
    an item nobody answered in a session, and steps without p(preferred)."""
    seed_study(database, name="gappy", participants=24, seed=5)
    with database.writing() as db:
        ids = db.scalars(select(Participant.id).order_by(Participant.id)).all()
        db.execute(
            update(Participant)
            .where(Participant.id.in_(ids[:3]))
            .values(status=ParticipantStatus.WITHDRAWN)
        )
        db.execute(
            delete(Response).where(Response.session == 4, Response.participant_id.in_(ids[3:-1]))
        )
        db.execute(delete(Response).where(Response.item == "trust_2", Response.session == 3))
        # Steps without p(preferred) (a category without a preferred question records none):
        # a first prompt and a later version, both of which must count for nothing.
        session_id = db.scalar(select(StudySession.id).where(StudySession.participant_id == ids[4]))
        run = Run(session_id=session_id, participant_id=ids[4], number=99, status="completed")
        db.add(run)
        db.flush()
        for version, category in ((0, "conation"), (57, "affection")):
            prompt = Prompt(
                participant_id=ids[4],
                run_id=run.id,
                category=category,
                action=1,
                question="?",
                probabilities=[0.25] * 4,
                learner_version=version,
                adapts=True,
                p_preferred=None,
            )
            db.add(prompt)
            db.flush()
            db.add(
                Answer(
                    prompt_id=prompt.id,
                    participant_id=ids[4],
                    answer=True,
                    reward=1.0,
                    probabilities_after=[0.25] * 4,
                    p_preferred=None,
                    probability=0.25,
                    confidence_level=0,
                    confidence="low",
                    reply="fine",
                    learner_version=version + 1,
                    idempotency_key=f"k{version}",
                    processing_ms=1.0,
                )
            )
        db.commit()
    fast, reference = _both(database, "gappy", ANALYST)
    assert_same(fast, reference)
    session_4 = [c for c in fast["measures"][0]["payload"]["cells"] if c["session"] == 4]
    assert [c["n"] for c in session_4] == [1] and session_4[0]["sd"] is None
    # adapting answers (4 sessions × 3 runs × 3 categories) of those not withdrawn, with p
    assert fast["answers"] == (24 - 3) * 36


def test_an_empty_study_gives_empty_figures(database: Database) -> None:
    with database.writing() as db:
        studies.create_study(
            db,
            name="empty",
            loaded=parse_protocol(protocol_text(**EXP3_ONLY)),
            actor=Actor.system(),
        )
    fast, reference = _both(database, "empty", EXPERIMENTER)
    assert_same(fast, reference)
    assert (fast["answers"], fast["questionnaires"]) == (0, 0)
    assert all(m["payload"]["data"] == [] for m in fast["measures"])


SWAPPED_LABELS = {
    'neutral_label = "Group A"': 'neutral_label = "Group swap"',
    'neutral_label = "Group B"': 'neutral_label = "Group A"',
    'neutral_label = "Group swap"': 'neutral_label = "Group B"',
}
"""Neutral labels against the conditions' order (C1 is Group B) for a blinded study, so neither
the ids nor their order may show through."""


@pytest.fixture
def blind_lab(
    app: FastAPI, client: TestClient, database: Database, user_client: UserClientFactory
) -> Lab:
    """A blinded study 'blind' with one participant of each condition through session 1."""
    create_blinded_study(database, "blind", **SWAPPED_LABELS)
    admin = user_client(Role.ADMIN)
    assert admin.post("/api/v1/stations", json={"name": "lab-b"}).status_code == 201
    key = admin.post("/api/v1/stations/lab-b/devices", json={"label": "pepper"}).json()["key"]
    analyst = user_client(Role.ANALYST)
    robot = client_of(client, headers={"Authorization": f"Bearer {key}"})
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
    return lab


def _records(data: dict[str, Any]) -> list[list[dict[str, Any]]]:
    """Every payload's table of numbers (the trust cells per measure: a blinded study has no
    adaptation curves until it is unblinded, and then no neutral labels)."""
    assert data["adaptation"] is None and data["learners_hidden"]
    return [m["payload"]["cells"] for m in data["measures"]]


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


def test_dashboards_share_one_computation_until_the_study_changes(lab: Lab) -> None:
    lab.app.state.dashboard_data = shared = FreshnessCache[bytes](max_age=60.0)
    lab.enrol_and_assign()
    lab.start_session()
    lab.run_session()
    lab.start_session()
    first = lab.experimenter.get("/studies/rt/dashboard.json")
    assert first.headers["content-type"] == "application/json"
    again = lab.experimenter.get("/studies/rt/dashboard.json")
    assert (again.content, shared.computed) == (first.content, 1)  # nothing changed in between
    step = lab.prompt("conation")
    lab.answer(step["step_id"], "yes")
    after = lab.experimenter.get("/studies/rt/dashboard.json")
    assert shared.computed == 2
    assert after.json()["answers"] == first.json()["answers"] + 1  # the reader's own change


def test_the_computation_takes_a_snapshot_younger_than_the_change_count(
    lab: Lab, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The request's transaction began with its sign-in check: had the computation kept it, a
    # change committed in between would be counted in the version yet missing from the data.
    seen: list[bool] = []
    real = dashboard.compute

    def compute(db: Session, plan: dashboard.Plan) -> dict[str, Any]:
        seen.append(db.in_transaction())
        return real(db, plan)

    monkeypatch.setattr(dashboard, "compute", compute)
    assert lab.experimenter.get("/studies/rt/dashboard.json").status_code == 200
    assert seen == [False]


def test_the_body_is_strict_json() -> None:
    body = dashboard.encode({"mean": float("nan"), "high": [float("inf"), 1.5], "range": "1–5"})
    assert body == '{"mean":null,"high":[null,1.5],"range":"1–5"}'.encode()
