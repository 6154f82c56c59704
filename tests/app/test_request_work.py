"""How requests meet the database (app/deps.py): who is asking is read first, the handler's work is
one write transaction, and no transaction — on SQLite, the single write lock — waits through a
thread-pool hop. Plus the statement counts of the lab's busiest non-robot requests."""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any, TypeVar

import anyio.to_thread
import pytest
from fastapi import APIRouter, Depends, FastAPI
from fastapi.testclient import TestClient
from sqlalchemy import event, select, update
from sqlalchemy.engine import Engine

from app.api import station_ops
from app.db import WRITE_OPTION, WriterThread
from app.deps import OneHopRouter, SecondWrite, SessionDep
from app.errors import Conflict
from app.services import studies
from app.services.audit import Actor
from app.services.participants import questionnaires, tablet_tokens
from app.services.sessions import runtime, stations
from app.sql import Cursor, Statement
from app.tables import Participant, Role, User, utcnow
from app.tablet import TABLET_COOKIE
from tests.conftest import (
    CSRF_INPUT,
    PASSWORD,
    TRUST_ANSWERS,
    Lab,
    UserClientFactory,
    make_user,
)

T = TypeVar("T")
BACKGROUND = ("trustlab-activity", "trustlab-checkpoint")


class Watch:
    """Transactions and thread hops (the thread pool's, SQLite's writer thread's) of the
    requests sent while it watches.

    A write transaction is open from BEGIN (``BEGIN IMMEDIATE`` on SQLite) to COMMIT or ROLLBACK;
    a hop that begins meanwhile kept the transaction (on SQLite, every other writer) waiting for
    a thread. The activity recorder's and WAL checkpointer's threads are left out.
    """

    def __init__(self, engine: Engine) -> None:
        self.engine = engine
        self.open_writes: set[int] = set()
        self.open_any: set[int] = set()
        self.writes = 0
        self.hops = 0
        self.held_hops = 0
        self.statements: list[str] = []

    def reset(self) -> None:
        self.writes = self.hops = self.held_hops = 0
        self.statements = []

    def _begin(self, conn: Any) -> None:
        if threading.current_thread().name in BACKGROUND:
            return
        self.open_any.add(id(conn))
        if conn.get_execution_options().get(WRITE_OPTION, False):
            self.writes += 1
            self.open_writes.add(id(conn))

    def _end(self, conn: Any) -> None:
        self.open_writes.discard(id(conn))
        self.open_any.discard(id(conn))

    def _statement(self, _conn: Any, _cursor: Any, statement: str, *_: Any) -> None:
        if threading.current_thread().name not in BACKGROUND and not statement.startswith("BEGIN"):
            self.statements.append(statement)

    @contextmanager
    def watching(self) -> Iterator[Watch]:
        run_sync = anyio.to_thread.run_sync
        run_on_writer = WriterThread.run

        def hop() -> None:
            self.hops += 1
            if self.open_writes:
                self.held_hops += 1

        async def counted(func: Callable[..., T], *args: Any, **kwargs: Any) -> T:
            hop()
            return await run_sync(func, *args, **kwargs)

        async def counted_on_writer(writer: WriterThread, func: Callable[..., T], *args: Any) -> T:
            hop()
            return await run_on_writer(writer, func, *args)

        listeners: list[tuple[str, Callable[..., None]]] = [
            ("begin", self._begin),
            ("commit", self._end),
            ("rollback", self._end),
            ("before_cursor_execute", self._statement),
        ]
        for name, listener in listeners:
            event.listen(self.engine, name, listener)
        anyio.to_thread.run_sync = counted  # type: ignore[assignment]
        WriterThread.run = counted_on_writer  # type: ignore[method-assign]
        try:
            yield self
        finally:
            anyio.to_thread.run_sync = run_sync
            WriterThread.run = run_on_writer  # type: ignore[method-assign]
            for name, listener in listeners:
                event.remove(self.engine, name, listener)

    def request(self, send: Callable[[], Any], *, most_writes: int = 1) -> Any:
        """Send one request; check it wrote at most ``most_writes`` times (once, but for a
        password check, which counts its attempt first: app.services.staff.login_throttle) and never
        across a hop."""
        self.reset()
        response = send()
        assert self.held_hops == 0, f"{self.held_hops} hop(s) with a write transaction open"
        assert self.writes <= most_writes, f"{self.writes} write transactions in one request"
        assert not self.open_any, "a transaction outlived its request"
        return response


@pytest.fixture
def watch(app: FastAPI) -> Iterator[Watch]:
    with Watch(app.state.database.engine).watching() as watching:
        yield watching


def _tablet(lab: Lab, code: str) -> TestClient:
    return lab.tablets[code]


def test_no_write_transaction_waits_through_a_hop(
    lab: Lab, watch: Watch, user_client: UserClientFactory
) -> None:
    """The lab's requests, API and pages, successes and refusals: one write transaction at most,
    none open while a thread-pool hop begins, none left open afterwards."""
    code = lab.enrol_and_assign()
    tablet = _tablet(lab, code)
    station = f"/api/v1/stations/{lab.station}"
    staff = lab.experimenter

    started = watch.request(lambda: staff.post(f"{station}/sessions"))
    assert started.status_code == 201 and started.json()["session"]["number"] == 0
    assert watch.writes == 1
    refused = watch.request(lambda: staff.post(f"{station}/sessions"))
    assert refused.status_code == 409
    assert watch.request(lambda: staff.get(f"{station}/state")).status_code == 200
    step = watch.request(lambda: staff.post(f"{station}/prompts", json={"category": "conation"}))
    assert step.status_code == 201
    answered = watch.request(
        lambda: staff.post(
            f"{station}/steps/{step.json()['step_id']}/answer",
            json={"answer": "yes", "idempotency_key": "watched"},
        )
    )
    assert answered.status_code == 200
    robot_step = watch.request(
        lambda: lab.robot.post("/api/v1/station/prompts", json={"category": "affection"})
    )
    assert robot_step.status_code == 201 and watch.writes == 1 and watch.hops == 1
    robot_answer = watch.request(
        lambda: lab.robot.post(
            f"/api/v1/station/steps/{robot_step.json()['step_id']}/answer",
            json={"answer": "no", "idempotency_key": "watched-robot"},
        )
    )
    assert robot_answer.status_code == 200 and watch.writes == 1 and watch.hops == 1
    ended = watch.request(lambda: staff.post(f"{station}/sessions/current/end"))
    assert ended.status_code == 200 and ended.json()["expected"]["action"] == "start_session"

    assert watch.request(lambda: tablet.get("/api/v1/tablet")).json()["kind"] == "wait"
    assert watch.request(lambda: staff.post(f"{station}/sessions")).status_code == 201
    watch.request(lambda: staff.post(f"{station}/sessions/current/end"))
    page = watch.request(lambda: tablet.get("/api/v1/tablet")).json()
    assert (page["kind"], page["session"]) == ("questionnaire", 1)
    path = f"/api/v1/tablet/questionnaires/{page['instrument']['key']}"
    invalid = watch.request(lambda: tablet.post(path, json={"session": 1, "answers": {}}))
    assert invalid.status_code == 422
    submitted = watch.request(
        lambda: tablet.post(path, json={"session": 1, "answers": TRUST_ANSWERS})
    )
    assert submitted.status_code == 200
    assert submitted.json() == tablet.get("/api/v1/tablet").json()
    revised = watch.request(
        lambda: tablet.post(path, json={"session": 1, "answers": {**TRUST_ANSWERS, "trust_1": "5"}})
    )
    assert revised.status_code == 200 and revised.json()["kind"] == "wait"

    # The pages: the operator console and the tablet's forms.
    console = f"/stations/{lab.station}"
    assert watch.request(lambda: staff.post(f"{console}/session/start")).status_code == 200
    assert watch.request(lambda: staff.post(f"{console}/session/start")).status_code == 409
    assert watch.request(lambda: staff.post(f"{console}/session/end")).status_code == 200
    browser = TestClient(lab.app)
    browser.cookies.set(TABLET_COOKIE, tablet.headers["Authorization"].removeprefix("Bearer "))
    form_page = watch.request(lambda: browser.get("/tablet/q/trust/2"))
    assert form_page.status_code == 200
    token = CSRF_INPUT.search(form_page.text)
    assert token
    posted = watch.request(
        lambda: browser.post(
            "/tablet/q/trust/2",
            data={"csrf_token": token.group(1), **TRUST_ANSWERS},
            follow_redirects=False,
        )
    )
    assert posted.status_code == 303

    # Signing in and out, through the API and the sign-in page.
    make_user(lab.database, "watched", Role.EXPERIMENTER)
    api = TestClient(lab.app)
    # A sign-in counts its attempt in a write of its own before the password is checked, then
    # records the outcome: two short writes, neither open while the password is checked.
    signed = watch.request(
        lambda: api.post("/api/v1/session", json={"username": "watched", "password": PASSWORD}),
        most_writes=2,
    )
    assert signed.status_code == 200 and watch.writes == 2
    wrong = watch.request(
        lambda: api.post("/api/v1/session", json={"username": "watched", "password": "wrong"}),
        most_writes=2,
    )
    assert wrong.status_code == 401 and watch.writes == 2
    api.headers["X-CSRF-Token"] = signed.json()["csrf_token"]
    assert watch.request(lambda: api.delete("/api/v1/session")).status_code == 204
    browser_login = TestClient(lab.app)
    form = CSRF_INPUT.search(browser_login.get("/login").text)
    assert form
    page_login = watch.request(
        lambda: browser_login.post(
            "/login",
            data={"username": "watched", "password": PASSWORD, "csrf_token": form.group(1)},
            follow_redirects=False,
        ),
        most_writes=2,
    )
    assert page_login.status_code == 303

    # Account changes (app/web/accounts.py), and one's own password (counted like a sign-in).
    admin = user_client(Role.ADMIN)
    renewed = "a brand new passphrase"
    for change, data in (
        ("password", {"password": renewed, "confirm": renewed}),
        ("role", {"role": "analyst"}),
        ("disable", {}),
        ("enable", {}),
        ("unlock", {}),
    ):
        done = watch.request(
            lambda change=change, data=data: admin.post(  # type: ignore[misc]
                f"/admin/users/watched/{change}", data=data, follow_redirects=False
            )
        )
        assert done.status_code == 303 and watch.writes == 1, change
    own = watch.request(
        lambda: admin.post(
            "/account/password",
            data={"current_password": PASSWORD, "new_password": renewed, "confirm": renewed},
            follow_redirects=False,
        ),
        most_writes=2,
    )
    assert own.status_code == 303 and watch.writes == 2


def test_the_watch_sees_a_write_waiting_through_a_hop(app: FastAPI, watch: Watch) -> None:
    """The check above can fail: a sync dependency that begins the write transaction holds it
    through the hops to the handler and to the session's closing."""
    router = APIRouter()

    def begins_writing(db: SessionDep) -> None:
        db.execute(select(1))

    @router.post("/test/multi-hop")
    def multi_hop(db: SessionDep, _: None = Depends(begins_writing)) -> dict[str, bool]:
        return {"ok": True}

    app.include_router(router)
    with TestClient(app) as client:
        watch.reset()
        assert client.post("/test/multi-hop").status_code == 200
    assert watch.writes == 1 and watch.held_hops >= 2


def test_a_second_write_in_one_request_is_refused(app: FastAPI) -> None:
    """After its write transaction committed, a request session reads; writing again is a bug."""
    router = OneHopRouter()

    @router.post("/test/two-writes")
    def two_writes(db: SessionDep) -> dict[str, bool]:
        db.execute(update(User).where(User.id == -1).values(is_active=False))
        db.commit()
        db.execute(select(User.id))  # reading afterwards is fine
        db.execute(update(User).where(User.id == -1).values(is_active=True))
        return {"ok": True}

    @router.post("/test/raw-second-write")
    def raw_second_write(db: SessionDep) -> dict[str, bool]:
        db.execute(update(User).where(User.id == -1).values(is_active=False))
        db.commit()
        cursor = Cursor.of(db)
        cursor.rows(Statement('SELECT id FROM "user"'), {})  # reading afterwards is fine
        cursor.write(Statement('UPDATE "user" SET is_active = :on WHERE id = -1'), {"on": True})
        return {"ok": True}

    app.include_router(router)
    with TestClient(app) as client:
        with pytest.raises(SecondWrite):
            client.post("/test/two-writes")
        with pytest.raises(SecondWrite):  # the step store's statements are held to it too
            client.post("/test/raw-second-write")


def _sql(statements: list[str]) -> str:
    return "\n".join(" ".join(s.split())[:120] for s in statements)


def test_session_start_and_station_state_add_only_the_login_lookup(lab: Lab, watch: Watch) -> None:
    """The experimenter's routes cost the services' own statements plus one: the login (with its
    user). Measured against the services called directly, so it holds whatever they query."""
    lab.enrol_and_assign()
    database = lab.app.state.database  # the watched engine
    actor = Actor.system("tests")

    def direct_start() -> int:
        with database.write_session() as db:
            watch.reset()
            runtime.start_session(db, station_name=lab.station, actor=actor)  # with the state
            return len(watch.statements)

    def direct_end() -> None:
        with database.write_session() as db:
            runtime.end_session(db, station_name=lab.station, actor=actor)

    def direct_state() -> int:
        with database.read_session() as db:
            watch.reset()
            station_ops.state(db, station=lab.station)
            return len(watch.statements)

    # Measured where the route will be: after an ended session (the first start reads no run).
    direct_start()
    direct_end()
    lab.fill_pending_questionnaires()
    service_start = direct_start()
    direct_end()
    lab.fill_pending_questionnaires()
    service_state = direct_state()
    route = watch.request(lambda: lab.experimenter.post(f"/api/v1/stations/{lab.station}/sessions"))
    assert route.status_code == 201
    assert len(watch.statements) == service_start + 1, _sql(watch.statements)
    assert watch.statements[0].startswith("SELECT login_session.")
    direct_end()
    lab.fill_pending_questionnaires()
    assert direct_state() == service_state
    read = watch.request(lambda: lab.experimenter.get(f"/api/v1/stations/{lab.station}/state"))
    assert read.status_code == 200
    assert len(watch.statements) == service_state + 1, _sql(watch.statements)


def test_the_tablet_page_takes_two_statements(lab: Lab, watch: Watch) -> None:
    """A tablet's poll: its token with participant and study, then where the participant stands
    (submitted pages and ended sessions in one query). A kiosk token costs the same."""
    code = lab.enrol_and_assign()
    tablet = _tablet(lab, code)
    assert watch.request(lambda: tablet.get("/api/v1/tablet")).json()["kind"] == "wait"
    assert len(watch.statements) == 2, _sql(watch.statements)
    with lab.database.writing() as db:
        kiosk = tablet_tokens.issue_kiosk_token(
            db,
            station=stations.get_station(db, lab.station),
            secret=lab.app.state.settings.secret,
            actor=Actor.system("tests"),
        )
    kiosk_tablet = TestClient(lab.app, headers={"Authorization": f"Bearer {kiosk}"})
    page = watch.request(lambda: kiosk_tablet.get("/api/v1/tablet"))
    assert page.json()["participant"] == code
    assert len(watch.statements) == 2, _sql(watch.statements)


def test_a_questionnaire_submission_takes_few_statements(lab: Lab, watch: Watch) -> None:
    """A first submission: the token (before the write); then the participant as it is now (with
    their station), where they stand, all the page's responses in one INSERT, the submission;
    PostgreSQL adds its one pg_notify. Its response, the next page, needs nothing more."""
    code = lab.enrol_and_assign()
    tablet = _tablet(lab, code)
    lab.start_session()
    lab.run_session()
    path = "/api/v1/tablet/questionnaires/trust"
    lab.start_session()
    lab.run_session()
    submitted = watch.request(
        lambda: tablet.post(path, json={"session": 1, "answers": TRUST_ANSWERS})
    )
    assert submitted.status_code == 200 and submitted.json()["kind"] == "wait"
    postgres = not lab.database.is_sqlite
    assert len(watch.statements) == 5 + postgres, _sql(watch.statements)
    inserts = [s for s in watch.statements if s.startswith("INSERT INTO response")]
    assert len(inserts) == 1
    revised = watch.request(
        lambda: tablet.post(path, json={"session": 1, "answers": {**TRUST_ANSWERS, "trust_2": "1"}})
    )
    assert revised.status_code == 200
    # A revision also reads the page's stored values and its submission, and audits the change.
    assert len(watch.statements) == 8 + postgres, _sql(watch.statements)


def test_a_lock_committed_after_the_tablet_was_identified_refuses_the_submission(
    lab: Lab,
) -> None:
    """The submission decides on the participant as stored inside its own transaction, not as the
    tablet's identification read them a moment before."""
    code = lab.enrol_and_assign()
    lab.start_session()
    lab.run_session()
    lab.start_session()
    lab.run_session()
    database = lab.database
    with database.write_session() as db:
        participant = db.scalar(select(Participant).where(Participant.code == code))
        assert participant is not None and participant.locked_at is None
        protocol = studies.protocol_of(participant.study)
        db.commit()  # the identification's read is over; the object stays loaded
        with database.writing() as other:
            other.execute(
                update(Participant)
                .where(Participant.id == participant.id)
                .values(locked_at=utcnow())
            )
            other.commit()
        assert participant.locked_at is None  # what the identification saw
        with pytest.raises(Conflict, match="locked"):
            questionnaires.submit(
                db,
                participant=participant,
                protocol=protocol,
                instrument_key="trust",
                session=1,
                answers=TRUST_ANSWERS,
                actor=Actor.system("tests"),
            )


def test_the_station_lists_take_as_many_statements_for_many_stations_as_for_one(
    lab: Lab, watch: Watch, user_client: UserClientFactory
) -> None:
    """Seated participants and devices are read for all stations at once (was: per station)."""
    admin = user_client(Role.ADMIN)
    lab.enrol_and_assign("P1")

    def counted(path: str) -> tuple[int, Any]:
        response = watch.request(lambda: admin.get(path))
        assert response.status_code == 200
        return len(watch.statements), response

    one_api, _ = counted("/api/v1/stations")
    one_page, _ = counted("/stations")
    for number in (2, 3, 4):
        name = f"lab-{number}"
        assert admin.post("/api/v1/stations", json={"name": name}).status_code == 201
        assert admin.post(f"/api/v1/stations/{name}/devices", json={}).status_code == 201
        code = f"P{number}"
        assert admin.post("/api/v1/studies/rt/participants", json={"code": code}).status_code == 201
        seated = admin.put(
            f"/api/v1/stations/{name}/participant", json={"study": "rt", "code": code}
        )
        assert seated.status_code == 200 and seated.json()["participant"] == code
    many_api, listed = counted("/api/v1/stations")
    many_page, page = counted("/stations")
    assert (many_api, many_page) == (one_api, one_page), _sql(watch.statements)
    assert [
        (s["name"], s["participant"], s["study"], len(s["devices"])) for s in listed.json()
    ] == [
        ("lab-1", "P1", "rt", 1),
        *((f"lab-{n}", f"P{n}", "rt", 1) for n in (2, 3, 4)),
    ]
    assert all(f"P{n}" in page.text for n in (1, 2, 3, 4))
