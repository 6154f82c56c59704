"""The studies API: listing, creating, enrolling, withdrawing, blinding and clear errors."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import func, select

from app.db import Database
from app.main import create_app
from app.protocol import default_protocol
from app.services import studies
from app.settings import Settings
from app.tables import Participant, Role
from tests.conftest import BLINDED, UserClientFactory, protocol_text, sqlite_only


@sqlite_only("the OpenAPI document comes from the routes")
def test_openapi_document_and_local_docs(client: TestClient) -> None:
    document = client.get("/api/v1/openapi.json").json()
    assert "/api/v1/studies/{name}/participants" in document["paths"]
    docs = client.get("/api/v1/docs")
    assert "/static/vendor/swagger-ui-bundle.js" in docs.text
    assert "cdn" not in docs.text.lower()


@sqlite_only("the OpenAPI document comes from the routes")
def test_openapi_documents_the_robot_routes_bodies(client: TestClient) -> None:
    """The robot routes answer with pre-serialised JSON (app.api.device_work.ModelResponse), so
    their bodies are documented by the routes' declared response models, not by inference."""
    paths = client.get("/api/v1/openapi.json").json()["paths"]

    def body_schema(path: str, method: str, status: str) -> str:
        content = paths[path][method]["responses"][status]["content"]
        return str(content["application/json"]["schema"].get("$ref", ""))

    station = "/api/v1/station"
    assert body_schema(station, "get", "200").endswith("/StationStateOut")
    assert body_schema(f"{station}/prompts", "post", "201").endswith("/PromptOut")
    assert "200" in paths[f"{station}/prompts"]["post"]["responses"]
    assert body_schema(f"{station}/steps/{{step_id}}/answer", "post", "200").endswith("/AnswerOut")
    assert body_schema(f"{station}/runs", "post", "201").endswith("/StationStateOut")


def test_healthz_reports_the_database(client: TestClient) -> None:
    assert client.get("/healthz").json() == {"status": "ok", "database": "ok"}


@pytest.mark.parametrize("engine_name", ["sqlite"], indirect=True)  # the URL below is the point
def test_healthz_reports_an_unreachable_database(settings: Settings) -> None:
    broken = settings.model_copy(
        update={"database_url": "postgresql+psycopg://nobody@127.0.0.1:1/none"}
    )
    with TestClient(create_app(broken)) as unreachable:
        response = unreachable.get("/healthz")
    assert response.status_code == 503
    assert response.json()["status"] == "unavailable"
    assert (
        "cannot reach the database at postgresql+psycopg://nobody@127.0.0.1:1/none"
        in (response.json()["database"])
    )


@pytest.mark.parametrize("engine_name", ["sqlite"], indirect=True)
def test_apps_of_one_process_share_their_routes_and_keep_their_own_state(
    client: TestClient, settings: Settings
) -> None:
    """The routes are built once per process (app.main._routes); each app still answers from
    its own settings and database."""
    unreachable_url = "postgresql+psycopg://nobody@127.0.0.1:1/none"
    broken = settings.model_copy(update={"database_url": unreachable_url})
    other = create_app(broken)
    own = {id(route) for route in client.app.routes}  # type: ignore[attr-defined]
    apart = [getattr(route, "path", route) for route in other.routes if id(route) not in own]  # type: ignore[attr-defined]
    assert sorted(apart) == ["/api/v1/openapi.json", "/static"]  # what FastAPI makes per app
    with TestClient(other) as unreachable:
        assert unreachable.get("/healthz").status_code == 503
    assert client.get("/healthz").json() == {"status": "ok", "database": "ok"}


def test_enrol_list_and_withdraw(user_client: UserClientFactory, study_name: str) -> None:
    client = user_client(Role.EXPERIMENTER)
    base = f"/api/v1/studies/{study_name}/participants"
    created = client.post(base, json={"code": "P100"})
    assert created.status_code == 201
    body = created.json()
    assert body["code"] == "P100"
    assert body["condition"] in {"C1", "C2"}
    assert "allocation_index" not in body  # its place in the sequence is concealed
    listed = client.get(base).json()
    assert [p["code"] for p in listed] == ["P100"]
    withdrawn = client.post(f"{base}/P100/withdraw", json={"reason": "moved away"})
    assert withdrawn.json()["status"] == "withdrawn"
    summary = client.get(f"/api/v1/studies/{study_name}").json()
    assert sum(c["withdrawn"] for c in summary["enrolment"]) == 1


def test_errors_are_clear_and_leave_nothing_behind(
    user_client: UserClientFactory, study_name: str, database: Database
) -> None:
    client = user_client(Role.ADMIN)
    base = f"/api/v1/studies/{study_name}/participants"
    assert client.post(base, json={"code": "P1"}).status_code == 201
    duplicate = client.post(base, json={"code": "P1"})
    assert duplicate.status_code == 409
    assert duplicate.json()["detail"] == "participant code 'P1' is already used in study 'default'"
    unknown = client.post("/api/v1/studies/nope/participants", json={})
    assert unknown.status_code == 404
    assert "no study named 'nope'" in unknown.json()["detail"]
    typo = client.post(base, json={"cod": "P2"})
    assert typo.status_code == 422
    assert typo.json()["detail"] == "cod: Extra inputs are not permitted"
    malformed = client.post(
        base, content=b"{not json", headers={"content-type": "application/json"}
    )
    assert malformed.status_code == 422
    client.post(f"/api/v1/studies/{study_name}/status", json={"status": "closed"})
    closed = client.post(base, json={})
    assert closed.status_code == 409
    assert "closed to enrolment" in closed.json()["detail"]
    with database.read_session() as db:
        assert db.scalar(select(func.count()).select_from(Participant)) == 1


def test_admin_creates_a_study_and_bad_protocols_are_explained(
    user_client: UserClientFactory,
) -> None:
    admin = user_client(Role.ADMIN)
    good = admin.post(
        "/api/v1/studies",
        json={"name": "pilot", "protocol_toml": default_protocol().source_text},
    )
    assert good.status_code == 201
    assert good.json()["protocol_sha256"] == default_protocol().sha256
    bad = admin.post(
        "/api/v1/studies",
        json={
            "name": "pilot-2",
            "protocol_toml": protocol_text(**{"sessions = 4": "sessions = -1", "[2, 4]": "[2, 3]"}),
        },
    )
    assert bad.status_code == 422
    first, second = bad.json()["detail"].splitlines()  # every problem at once (issue 35 item 9)
    assert first.startswith("protocol_toml: schedule.sessions: ")
    assert second.startswith("protocol_toml: allocation.block_sizes[1]: block size 3 is not")
    again = admin.post(
        "/api/v1/studies",
        json={"name": "pilot", "protocol_toml": default_protocol().source_text},
    )
    assert again.status_code == 409


def test_a_study_starts_from_a_shipped_protocol_or_a_copy_over_the_api(
    user_client: UserClientFactory, database: Database
) -> None:
    admin = user_client(Role.ADMIN)
    listed = {row["file"]: row for row in admin.get("/api/v1/protocols").json()}
    swedish = listed["fast_adaptation_trust_sv.toml"]
    assert swedish["languages"] == ["en", "sv"]
    made = admin.post("/api/v1/studies", json={"name": "w1", "shipped": swedish["file"]})
    assert made.status_code == 201 and made.json()["protocol_sha256"] == swedish["sha256"]
    copied = admin.post("/api/v1/studies", json={"name": "w2", "copy_of": "w1"})
    assert copied.status_code == 201 and copied.json()["protocol_sha256"] == swedish["sha256"]
    for body, said in [
        ({}, "give exactly one of protocol_toml, shipped and copy_of"),
        ({"shipped": swedish["file"], "copy_of": "w1"}, "give exactly one of"),
        ({"shipped": "../etc/passwd"}, "trustlab ships no protocol of that name"),
    ]:
        refused = admin.post("/api/v1/studies", json={"name": "w3", **body})
        assert refused.status_code == 422 and said in refused.json()["detail"], refused.text
    assert admin.post("/api/v1/studies", json={"name": "w3", "copy_of": "x"}).status_code == 404
    with database.read_session() as db:
        assert "w3" not in [study.name for study in studies.list_studies(db)]


def test_blinded_study_hides_conditions_from_experimenters(
    user_client: UserClientFactory, database: Database
) -> None:
    admin = user_client(Role.ADMIN)
    blinded = protocol_text(**BLINDED)
    admin.post("/api/v1/studies", json={"name": "blind", "protocol_toml": blinded})
    experimenter = user_client(Role.EXPERIMENTER)
    analyst = user_client(Role.ANALYST)
    revealed = experimenter.post("/api/v1/studies/blind/participants", json={}).json()
    assert revealed["condition"] in {"Group A", "Group B"}
    seen_by_analyst = analyst.get("/api/v1/studies/blind/participants").json()[0]["condition"]
    with database.read_session() as db:  # the study's own draw, not the protocol's order
        labels = studies.get_study(db, "blind").neutral_labels
    assert labels is not None and labels[seen_by_analyst] == revealed["condition"]
    labels = {c["label"] for c in experimenter.get("/api/v1/studies/blind").json()["enrolment"]}
    assert labels == {"Group A", "Group B"}
    page = experimenter.get("/studies/blind").text
    assert "Exp3" not in page and "C1 —" not in page
