"""Shared fixtures: a fresh, migrated database per test on SQLite and on PostgreSQL.

Every database test runs twice, once per engine. The PostgreSQL variant needs
TRUSTLAB_TEST_POSTGRES_URL (CI sets it); without it the variant is skipped with a reason, and with
it an unreachable server fails the run. Migrations run once per engine into a template; each test
gets a copy (a file copy for SQLite, CREATE DATABASE … TEMPLATE for PostgreSQL), so tests are
isolated and cheap.
"""

from __future__ import annotations

import os
import re
import shutil
import uuid
from collections.abc import Callable, Collection, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import psycopg
import pytest
from argon2 import PasswordHasher
from fastapi import FastAPI
from fastapi.testclient import TestClient
from sqlalchemy.engine import make_url

from app import schema, security
from app.db import Database
from app.main import create_app
from app.protocol import default_protocol, parse_protocol
from app.services import studies
from app.services.audit import Actor
from app.services.participants import questionnaires
from app.services.staff import users
from app.settings import Settings
from app.tables import Participant, Role

POSTGRES_URL = os.environ.get("TRUSTLAB_TEST_POSTGRES_URL", "")
POSTGRES_SKIP_REASON = "PostgreSQL variant: set TRUSTLAB_TEST_POSTGRES_URL to run it"
PASSWORD = "correct horse battery"


def _admin_conninfo() -> str:
    """A libpq URL for the maintenance database named in TRUSTLAB_TEST_POSTGRES_URL."""
    url = make_url(POSTGRES_URL).set(drivername="postgresql")
    return url.render_as_string(hide_password=False)


def _postgres_url_for(database: str) -> str:
    return make_url(POSTGRES_URL).set(database=database).render_as_string(hide_password=False)


def _pg_execute(sql: str) -> None:
    with psycopg.connect(_admin_conninfo(), autocommit=True, connect_timeout=5) as conn:
        conn.execute(sql)  # type: ignore[arg-type]


@pytest.fixture(autouse=True, scope="session")
def _cheap_password_hashing() -> Iterator[None]:
    """Argon2id with test-sized cost (production uses RFC 9106 parameters: ~0.4 s a hash here)."""
    production = security._hasher
    security._hasher = PasswordHasher(time_cost=1, memory_cost=1024, parallelism=1)
    yield
    security._hasher = production


@pytest.fixture(scope="session")
def sqlite_template(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A SQLite file migrated to head, copied for each test."""
    path = tmp_path_factory.mktemp("template") / "template.sqlite3"
    database = Database(f"sqlite:///{path}")
    schema.upgrade(database)
    with database.engine.connect() as connection:
        connection.exec_driver_sql("PRAGMA wal_checkpoint(TRUNCATE)")
    database.dispose()
    return path


@pytest.fixture(scope="session")
def postgres_session_database() -> Iterator[str]:
    """A PostgreSQL database migrated to head for this test session (wiped before each test)."""
    if not POSTGRES_URL:
        pytest.skip(POSTGRES_SKIP_REASON)
    try:
        _pg_execute("SELECT 1")
    except psycopg.OperationalError as exc:
        pytest.fail(
            f"TRUSTLAB_TEST_POSTGRES_URL is set but PostgreSQL is unreachable: {exc}", pytrace=False
        )
    yield from _fresh_postgres(None, migrate=True)


def _fresh_postgres(template: str | None, *, migrate: bool = False) -> Iterator[str]:
    name = f"tl_test_{uuid.uuid4().hex[:12]}"
    _pg_execute(f'CREATE DATABASE "{name}"' + (f' TEMPLATE "{template}"' if template else ""))
    url = _postgres_url_for(name)
    if migrate:
        database = Database(url)
        schema.upgrade(database)
        database.dispose()
    try:
        yield url
    finally:
        _pg_execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')


def _wipe_postgres(url: str) -> None:
    """Empty every table and restart every sequence (the append-only guards and the foreign
    keys' triggers paused for this one transaction).

    DELETE, not TRUNCATE: a test leaves a few rows, and TRUNCATE's new files for each of the
    tables took 0.45 s a test where DELETE takes 0.05 s (a test on PostgreSQL in three)."""
    conninfo = make_url(url).set(drivername="postgresql").render_as_string(hide_password=False)
    with psycopg.connect(conninfo, autocommit=True) as conn:
        tables = [
            row[0]
            for row in conn.execute(
                "SELECT tablename FROM pg_tables WHERE schemaname = 'public' "
                "AND tablename <> 'alembic_version'"
            )
        ]
        sequences = [
            row[0]
            for row in conn.execute(
                "SELECT sequencename FROM pg_sequences WHERE schemaname = 'public'"
            )
        ]
        # Close what earlier tests may have left connected, so nothing holds a lock.
        conn.execute(
            "SELECT pg_terminate_backend(pid) FROM pg_stat_activity "
            "WHERE datname = current_database() AND pid <> pg_backend_pid()"
        )
        with conn.transaction():
            conn.execute("SET LOCAL session_replication_role = replica")
            for table in tables:
                conn.execute(f'DELETE FROM "{table}"')  # type: ignore[arg-type]
            for sequence in sequences:
                conn.execute(f'ALTER SEQUENCE "{sequence}" RESTART')  # type: ignore[arg-type]


ENGINES = ["sqlite", pytest.param("postgresql", marks=pytest.mark.postgres)]


@pytest.fixture(params=ENGINES)
def engine_name(request: pytest.FixtureRequest) -> str:
    """Which database engine this variant of the test uses."""
    name: str = request.param
    if name == "postgresql" and not POSTGRES_URL:
        pytest.skip(POSTGRES_SKIP_REASON)
    return name


def sqlite_only(why: str) -> pytest.MarkDecorator:
    """Run the test on SQLite only, because (``why``) the database has no say in what it checks:
    the request is refused before any query, or only rendering or parsing is looked at.

    A PostgreSQL variant costs a wiped database and a slower start each; it belongs wherever
    SQL, transactions, locking, JSON columns, NOTIFY or concurrency matter."""
    assert why, "say why the database has no say"
    return pytest.mark.parametrize("engine_name", ["sqlite"], indirect=True)


def postgres_for_some(
    argnames: str, values: Sequence[Any], *, ids: Sequence[str], postgres: Collection[str]
) -> pytest.MarkDecorator:
    """``parametrize(argnames, values)`` on SQLite for every value, on PostgreSQL only for the
    values whose id is in ``postgres`` (the cases where the engine could answer differently;
    the others are refused before any query)."""
    assert set(postgres) <= set(ids), set(postgres) - set(ids)
    names = ["engine_name", *(name.strip() for name in argnames.split(","))]
    params = []
    for value, id_ in zip(values, ids, strict=True):
        args = tuple(value) if len(names) > 2 else (value,)
        params.append(pytest.param("sqlite", *args, id=f"sqlite-{id_}"))
        if id_ in postgres:
            params.append(
                pytest.param(
                    "postgresql", *args, id=f"postgresql-{id_}", marks=pytest.mark.postgres
                )
            )
    return pytest.mark.parametrize(names, params, indirect=["engine_name"])


@pytest.fixture
def database_url(engine_name: str, request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[str]:
    """The URL of a fresh database, migrated to head."""
    if engine_name == "sqlite":
        template: Path = request.getfixturevalue("sqlite_template")
        path = tmp_path / "trustlab.sqlite3"
        shutil.copyfile(template, path)
        yield f"sqlite:///{path}"
    else:
        url = request.getfixturevalue("postgres_session_database")
        _wipe_postgres(url)
        yield url


@pytest.fixture
def blank_database_url(engine_name: str, tmp_path: Path) -> Iterator[str]:
    """The URL of an empty, never-migrated database."""
    if engine_name == "sqlite":
        yield f"sqlite:///{tmp_path / 'blank.sqlite3'}"
    else:
        yield from _fresh_postgres(None)


@pytest.fixture
def database(database_url: str) -> Iterator[Database]:
    """The test's database."""
    db = Database(database_url, sqlite_synchronous="NORMAL")
    yield db
    db.dispose()


@pytest.fixture
def settings(database_url: str, tmp_path: Path) -> Settings:
    """Settings pointing at the test's database, ignoring any .env of the developer."""
    return Settings(
        _env_file=None,  # type: ignore[call-arg]
        database_url=database_url,
        var_dir=tmp_path / "var",
        secret_key="test-secret-key-test-secret-key-0123456789",
        sqlite_synchronous="NORMAL",
        freeze_heap_at_start=False,  # a worker starts a thousand apps: 0.3 s of collection each
        # Fits in a thread of the app (no worker processes to start per app), and a page waits
        # for its fit: the tests of the background itself inject a runner (test_fit_runner.py).
        analysis_processes=0,
        analysis_wait_seconds=120.0,
    )


@pytest.fixture
def app(settings: Settings) -> FastAPI:
    """A trustlab application on the test's database."""
    return create_app(settings)


@pytest.fixture
def client(app: FastAPI) -> Iterator[TestClient]:
    """An anonymous HTTP client; it runs the app's lifespan (the listener, the writer thread, the
    activity flusher) for the whole test, on its event loop, which every ``client_of`` shares."""
    with TestClient(app) as test_client:
        yield test_client


def client_of(served: TestClient, **options: Any) -> TestClient:
    """Another client of the app ``served`` runs (its own cookies and headers): its requests go
    through ``served``'s event loop, as a second browser's reach the one server process.

    Each client used to start the app's lifespan anew on an event loop of its own: two to four
    start-ups and shut-downs a test (0.1-0.2 s each on SQLite, about twice that on PostgreSQL,
    where each also starts a listener), and no server runs so."""
    other = TestClient(served.app, **options)
    other.portal = served.portal
    return other


def make_user(database: Database, username: str, role: Role) -> None:
    """Create an account with the shared test password."""
    with database.writing() as db:
        users.create_user(db, username=username, role=role, password=PASSWORD, actor=Actor.system())


CSRF_INPUT = re.compile(r'name="csrf_token" value="([^"]+)"')


def sign_in(client: TestClient, username: str, password: str = PASSWORD) -> str:
    """Sign ``client`` in through the login form; returns the login's CSRF token."""
    form = client.get("/login")
    token = CSRF_INPUT.search(form.text)
    assert token, "login form has no CSRF token"
    response = client.post(
        "/login",
        data={"username": username, "password": password, "csrf_token": token.group(1)},
        follow_redirects=False,
    )
    assert response.status_code == 303, response.text
    page = client.get("/")
    csrf = CSRF_INPUT.search(page.text)
    assert csrf, "signed-in page has no CSRF token"
    client.headers["X-CSRF-Token"] = csrf.group(1)
    return csrf.group(1)


def sign_in_api(client: TestClient, username: str, password: str = PASSWORD) -> str:
    """Sign ``client`` in through the JSON API (``POST /api/v1/session``); returns the login's
    CSRF token, also set as the client's X-CSRF-Token header.

    For tests where signing in is a step, not the subject: the form's three requests (the login
    page, the post, the page it leads to, two of them rendered) made every signed-in client of
    every test dearer. The form itself is tested through ``sign_in``."""
    response = client.post("/api/v1/session", json={"username": username, "password": password})
    assert response.status_code == 200, response.text
    csrf: str = response.json()["csrf_token"]
    client.headers["X-CSRF-Token"] = csrf
    return csrf


UserClientFactory = Callable[..., TestClient]


@pytest.fixture
def user_client(client: TestClient, database: Database) -> UserClientFactory:
    """A factory: ``user_client(role)`` gives a signed-in client with the CSRF header set (a
    ``client_of`` the test's app)."""
    clients: list[TestClient] = []

    def factory(role: Role, username: str | None = None) -> TestClient:
        name = username or f"{role.value}{len(clients)}"
        make_user(database, name, role)
        new_client = client_of(client)
        clients.append(new_client)
        sign_in_api(new_client, name)
        return new_client

    return factory


@pytest.fixture
def study_name(database: Database) -> str:
    """The shipped default protocol as a study named 'default'."""
    with database.writing() as db:
        studies.create_study(
            db, name="default", loaded=default_protocol(), actor=Actor.system("tests")
        )
    return "default"


def protocol_text(**replacements: str) -> str:
    """The shipped protocol's TOML with literal text replacements (for variant protocols)."""
    text = default_protocol().source_text
    for old, new in replacements.items():
        assert old in text, f"{old!r} not in the default protocol"
        text = text.replace(old, new)
    return text


EXP3_ONLY = {'learner = "meta"': 'learner = "exp3"'}
"""Protocol replacement giving both conditions Exp3 (fast, torch-free runtime tests)."""
BLINDED = {"blinded = false": "blinded = true"}
"""Protocol replacement making the study blinded (conditions sealed until it is unblinded)."""


@pytest.fixture
def exp3_study(database: Database) -> str:
    """A study named 'rt' whose conditions both use Exp3."""
    with database.writing() as db:
        studies.create_study(
            db, name="rt", loaded=parse_protocol(protocol_text(**EXP3_ONLY)), actor=Actor.system()
        )
    return "rt"


def create_blinded_study(database: Database, name: str = "sealed", **replacements: str) -> str:
    """A blinded study ``name`` whose conditions both use Exp3 (``replacements``: further
    changes to the shipped protocol's text); returns its name."""
    loaded = parse_protocol(protocol_text(**EXP3_ONLY, **BLINDED, **replacements))
    with database.writing() as db:
        studies.create_study(db, name=name, loaded=loaded, actor=Actor.system())
    return name


@pytest.fixture
def sealed_study(database: Database) -> str:
    """A blinded study named 'sealed' whose conditions both use Exp3."""
    return create_blinded_study(database)


@dataclass
class Lab:
    """A station with a device key and an experimenter, ready to run sessions.

    ``enrol_and_assign(..., questionnaires=True)`` also plays the participant's tablet part
    (consent, pre-study, and each session's questionnaire before the next session starts), so
    runtime tests are not blocked by the questionnaire gates.
    """

    app: FastAPI
    database: Database
    study: str
    station: str
    key: str
    experimenter: TestClient
    robot: TestClient
    tablets: dict[str, TestClient]

    def enrol_and_assign(self, code: str | None = None, *, questionnaires: bool = True) -> str:
        enrolled = self.experimenter.post(
            f"/api/v1/studies/{self.study}/participants", json={"code": code}
        )
        assert enrolled.status_code == 201, enrolled.text
        participant = str(enrolled.json()["code"])
        seated = self.experimenter.put(
            f"/api/v1/stations/{self.station}/participant",
            json={"study": self.study, "code": participant},
        )
        assert seated.status_code == 200, seated.text
        if questionnaires:
            self.tablets[participant] = tablet_client(self.app, self, participant)
            fill_pre_study(self.tablets[participant])
        return participant

    def fill_pending_questionnaires(self) -> None:
        """Answer whatever session questionnaire the seated participant's tablet shows."""
        seated = self.robot.get("/api/v1/station").json()["participant"]
        tablet = self.tablets.get(seated)
        if tablet is None:
            return
        page = tablet.get("/api/v1/tablet").json()
        while page["kind"] == "questionnaire" and page["instrument"]["when"] == "session":
            page = tablet.post(
                f"/api/v1/tablet/questionnaires/{page['instrument']['key']}",
                json={"session": page["session"], "answers": TRUST_ANSWERS},
            ).json()

    def start_session(self) -> dict[str, object]:
        self.fill_pending_questionnaires()
        response = self.experimenter.post(f"/api/v1/stations/{self.station}/sessions")
        assert response.status_code == 201, response.text
        return dict(response.json())

    def prompt(self, category: str) -> dict[str, object]:
        response = self.robot.post("/api/v1/station/prompts", json={"category": category})
        assert response.status_code in (200, 201), response.text
        return dict(response.json())

    def answer(self, step_id: object, answer: str, key: str | None = None) -> dict[str, object]:
        response = self.robot.post(
            f"/api/v1/station/steps/{step_id}/answer",
            json={"answer": answer, "idempotency_key": key or uuid.uuid4().hex},
        )
        assert response.status_code == 200, response.text
        return dict(response.json())

    def run_session(self, preferred: int = 0) -> int:
        """Answer every run of the started session; yes to arm ``preferred``. Returns steps."""
        steps = 0
        expected = self.robot.get("/api/v1/station").json()["expected"]
        pending = list(expected["categories"]) if expected["action"] == "prompt" else []
        while pending:
            step = self.prompt(pending[0])
            reply = self.answer(step["step_id"], "yes" if step["action"] == preferred else "no")
            steps += 1
            expected = reply["expected"]
            assert isinstance(expected, dict)
            pending = list(expected["categories"]) if expected["action"] == "prompt" else []
        return steps


@pytest.fixture
def lab(
    app: FastAPI,
    client: TestClient,
    database: Database,
    exp3_study: str,
    user_client: UserClientFactory,
) -> Lab:
    """Station 'lab-1' with a device key, an experimenter client and a robot client."""
    admin = user_client(Role.ADMIN)
    assert admin.post("/api/v1/stations", json={"name": "lab-1"}).status_code == 201
    issued = admin.post("/api/v1/stations/lab-1/devices", json={"label": "pepper"})
    key = issued.json()["key"]
    experimenter = user_client(Role.EXPERIMENTER)
    robot = client_of(client, headers={"Authorization": f"Bearer {key}"})
    return Lab(app, database, exp3_study, "lab-1", key, experimenter, robot, {})


PRE_STUDY_ANSWERS = {
    "demographics": {"age": "27", "gender": "female"},
    "background": {"bg_robot_experience": "2", "bg_vr_familiarity": "3", "bg_digital_skills": "4"},
    "tipi": {f"tipi_{n}": str(1 + n % 7) for n in range(1, 11)},
    "nars": {f"nars_{n}": str(1 + n % 5) for n in range(1, 15)},
}
TRUST_ANSWERS = {f"trust_{n}": str(1 + n % 5) for n in range(1, 6)}
POST_ANSWERS = {"overall_experience": "4", "interaction_quality": "5"}


def tablet_client(app: FastAPI, lab: Lab, code: str) -> TestClient:
    """A JSON tablet client for a participant (issues their link)."""
    link = lab.experimenter.post(f"/api/v1/studies/{lab.study}/participants/{code}/link")
    assert link.status_code == 200, link.text
    client = TestClient(app, headers={"Authorization": f"Bearer {link.json()['token']}"})
    return client


def give_pre_study(
    database: Database, *, study: str, participant: Participant, actor: Actor
) -> Participant:
    """Consent and every pre-study questionnaire, straight through the service (no tablet);
    returns the participant as merged into that unit of work."""
    with database.writing() as db:
        participant = db.merge(participant)
        protocol = studies.protocol_of(studies.get_study(db, study))
        questionnaires.accept_consent(
            db, participant=participant, protocol=protocol, accepted=True, actor=actor
        )
        for instrument, answers in PRE_STUDY_ANSWERS.items():
            questionnaires.submit(
                db,
                participant=participant,
                protocol=protocol,
                instrument_key=instrument,
                session=None,
                answers=answers,
                actor=actor,
            )
    return participant


def fill_pre_study(tablet: TestClient) -> None:
    """Consent and every pre-study questionnaire, through the JSON tablet API."""
    assert tablet.post("/api/v1/tablet/consent", json={"accept": True}).status_code == 200
    for instrument, answers in PRE_STUDY_ANSWERS.items():
        response = tablet.post(
            f"/api/v1/tablet/questionnaires/{instrument}", json={"answers": answers}
        )
        assert response.status_code == 200, response.text
