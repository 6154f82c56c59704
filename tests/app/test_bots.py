"""The bots drive whole participants through a real server over HTTP and WebSockets."""

from __future__ import annotations

import asyncio
import dataclasses
import json
import logging
from importlib import resources
from pathlib import Path

import pytest
from click.testing import Result
from sqlalchemy import func, select
from typer.testing import CliRunner

from app import bots, demo
from app.bots import BotConfig, BotSummary, ResponseModel, run_bots
from app.cli import cli
from app.client import ApiError, ExperimenterClient
from app.db import Database
from app.protocol import parse_protocol
from app.services import studies
from app.services.audit import Actor
from app.services.participants import enrolment
from app.services.sessions import stations, verify
from app.services.staff import accounts, users
from app.settings import Settings
from app.tables import Answer, Device, Participant, Prompt, Response, Role, Station
from tests.conftest import PASSWORD, make_user, sqlite_only
from tests.servers import ServerProcess


@pytest.fixture
def server(database: Database, database_url: str, tmp_path: Path) -> ServerProcess:
    make_user(database, "botmaster", Role.ADMIN)
    process = ServerProcess(database_url, tmp_path / "var")
    process.start()
    yield process  # type: ignore[misc]
    process.stop()


@pytest.mark.slow
@pytest.mark.parametrize("transport", ["ws", "rest"])
def test_bots_complete_the_protocol(
    server: ServerProcess, database: Database, exp3_study: str, transport: str
) -> None:
    config = BotConfig(
        url=server.url,
        study=exp3_study,
        participants=3,
        username="botmaster",
        password=PASSWORD,
        concurrency=2,
        noise=0.1,
        seed=7,
        transport=transport,  # type: ignore[arg-type]
    )
    ticks: list[int] = []
    summary = asyncio.run(run_bots(config, tick=lambda: ticks.append(1)))
    assert summary.errors == []
    assert (summary.participants, summary.completed, summary.sessions) == (3, 3, 15)
    assert summary.steps == len(ticks) == 3 * 39
    assert summary.questionnaires == 3 * 10
    with database.read_session() as db:
        assert db.scalar(select(func.count()).select_from(Answer)) == 3 * 39
        report = verify.verify_study(db, study_name=exp3_study)
        trust = db.scalars(select(Response.value).where(Response.instrument == "trust")).all()
    assert report.ok, report.findings
    assert len(trust) == 3 * 4 * 5


def _bot_keys(database: Database) -> list[tuple[str, bool]]:
    """(station, revoked?) of every key the bots issued."""
    with database.read_session() as db:
        devices = db.scalars(select(Device).where(Device.label == "bots").order_by(Device.id))
        return [(d.station.name, d.revoked_at is not None) for d in devices]


def _config(server: ServerProcess, study: str, participants: int) -> BotConfig:
    return BotConfig(
        url=server.url,
        study=study,
        participants=participants,
        username="botmaster",
        password=PASSWORD,
        concurrency=2,
        transport="rest",
    )


@pytest.mark.slow
def test_bots_revoke_their_keys_after_a_run_an_error_and_an_interruption(
    server: ServerProcess, database: Database, exp3_study: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    summary = asyncio.run(run_bots(_config(server, exp3_study, 2)))
    assert summary.errors == [] and summary.completed == 2
    assert sorted(_bot_keys(database)) == [("bot-1", True), ("bot-2", True)]

    async def interrupted() -> None:
        answered = asyncio.Event()
        run = asyncio.ensure_future(run_bots(_config(server, exp3_study, 2), tick=answered.set))
        await asyncio.wait_for(answered.wait(), 60)
        run.cancel()  # what Ctrl-C does to asyncio.run's task
        with pytest.raises(asyncio.CancelledError):
            await run

    asyncio.run(interrupted())
    # The second lane may or may not have got its key before the first one's answer ended the
    # run (that is up to the scheduler): whatever was issued is revoked.
    keys = _bot_keys(database)
    assert 3 <= len(keys) <= 4 and all(revoked for _, revoked in keys), keys
    with database.read_session() as db:  # stopped mid-session, the stations were still freed
        seated = db.scalars(select(Station.name).where(Station.participant_id.is_not(None)))
        assert list(seated) == []

    monkeypatch.setattr(bots._Lane, "run_participant", _crash)
    with pytest.raises(RuntimeError, match="lane crashed"):
        asyncio.run(run_bots(_config(server, exp3_study, 2)))
    after_crash = _bot_keys(database)
    assert len(after_crash) > len(keys) and all(revoked for _, revoked in after_crash), after_crash


def test_a_lane_stopped_while_it_seats_waits_for_the_seating_then_stops() -> None:
    """A seating cancelled in flight may still be carried out by the server: the lane waits for
    its answer (so its cleanup sees the participant seated and unseats them), then stops."""
    sent, answer, done = asyncio.Event(), asyncio.Event(), []

    async def seat() -> str:
        sent.set()
        await answer.wait()
        done.append("seated")
        return "seated"

    async def stopped_while_seating() -> None:
        lane = asyncio.ensure_future(bots._to_its_end(seat()))
        await sent.wait()
        lane.cancel()  # Ctrl-C, twice: neither cuts the request short
        await asyncio.sleep(0)
        lane.cancel()
        await asyncio.sleep(0)
        assert not lane.done() and done == []
        answer.set()
        with pytest.raises(asyncio.CancelledError):
            await lane
        assert done == ["seated"]

    asyncio.run(stopped_while_seating())

    async def not_stopped() -> str:
        return await bots._to_its_end(seat())

    assert asyncio.run(not_stopped()) == "seated"


def test_a_stopping_lane_looks_again_when_its_station_changed_in_between() -> None:
    """The lane's last answer, still on its way when the run was stopped, ends the session
    after the lane saw it running: ending it is refused (409), so the lane looks again and
    unseats the participant instead of leaving them seated."""
    calls: list[str] = []

    class Experimenter:
        def __init__(self) -> None:
            self.running = True

        async def station_state(self, station: str) -> dict[str, object]:
            calls.append("state")
            status = "running" if self.running else "completed"
            return {"participant": "P001", "session": {"status": status}}

        async def end_session(self, station: str) -> None:
            calls.append("end")
            self.running = False  # the answer in flight ended it first
            raise ApiError(409, "no session is running at bot-1")

        async def unassign(self, station: str) -> None:
            calls.append("unassign")

    lane = bots._Lane.__new__(bots._Lane)
    lane.experimenter = Experimenter()  # type: ignore[assignment]
    lane.station = "bot-1"
    asyncio.run(lane._leave_station("P001"))
    assert calls == ["state", "end", "state", "unassign"]


def test_a_lane_stopped_while_it_seats_gives_up_on_a_server_that_never_answers() -> None:
    cancelled = []

    async def seat_forever() -> None:
        try:
            await asyncio.Event().wait()
        except asyncio.CancelledError:
            cancelled.append(True)
            raise

    async def stopped() -> None:
        lane = asyncio.ensure_future(bots._to_its_end(seat_forever(), settle=0.01))
        await asyncio.sleep(0)
        lane.cancel()
        with pytest.raises(asyncio.CancelledError):
            await lane

    asyncio.run(stopped())
    assert cancelled == [True]


@pytest.mark.slow
def test_a_station_left_seated_is_reported_beside_the_run(
    server: ServerProcess, exp3_study: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    async def cannot_leave(self: object, code: str) -> None:
        raise ApiError(503, "the database is unavailable right now")

    monkeypatch.setattr(bots._Lane, "_leave_station", cannot_leave)
    summary = asyncio.run(run_bots(_config(server, exp3_study, 1)))
    assert summary.completed == 1
    assert summary.errors == [
        "bot-1: P001 was left seated: 503: the database is unavailable right now"
    ]


async def _crash(self: object) -> None:
    raise RuntimeError("lane crashed")


@pytest.mark.slow
def test_a_run_stopped_right_after_seating_frees_the_station(
    server: ServerProcess, database: Database, exp3_study: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Ctrl-C while the seating's response is on its way (the server has seated the participant,
    the bots have not heard so): the station is freed all the same, or the next run is refused."""
    seated, arrived = asyncio.Event(), asyncio.Event()
    assign = ExperimenterClient.assign

    async def assign_then_wait(
        self: ExperimenterClient, station: str, study: str, code: str
    ) -> None:
        await assign(self, station, study, code)
        seated.set()
        await arrived.wait()  # the response is still on its way when Ctrl-C comes

    monkeypatch.setattr(ExperimenterClient, "assign", assign_then_wait)

    async def interrupted() -> None:
        config = dataclasses.replace(_config(server, exp3_study, 1), concurrency=1)
        run = asyncio.ensure_future(run_bots(config))
        await asyncio.wait_for(seated.wait(), 60)
        run.cancel()
        await asyncio.sleep(0)
        arrived.set()
        with pytest.raises(asyncio.CancelledError):
            await run

    asyncio.run(interrupted())
    with database.read_session() as db:
        assert (
            list(db.scalars(select(Station.name).where(Station.participant_id.is_not(None)))) == []
        )


def test_response_model_shifts_and_mirrors() -> None:
    import random

    model = ResponseModel(mean=3.0, sd=0.0, effect={"C2": 1.0}, slope={})
    rng = random.Random(1)
    assert model.likert(rng, 1, 5, reverse=False, shift=0.0) == 3
    assert model.likert(rng, 1, 5, reverse=False, shift=1.0) == 4
    assert model.likert(rng, 1, 5, reverse=True, shift=1.0) == 2
    assert model.likert(rng, 1, 7, reverse=False, shift=0.0) == 4
    assert model.likert(rng, 1, 5, reverse=False, shift=9.0) == 5


@pytest.mark.slow
@pytest.mark.parametrize("engine_name", ["sqlite"])  # the command's plumbing is engine-free
def test_bots_command_prints_one_json_summary(
    server: ServerProcess,
    database: Database,
    database_url: str,
    exp3_study: str,
    engine_name: str,
) -> None:
    def run_bots_command(*options: str) -> Result:
        return CliRunner().invoke(
            cli,
            [
                *("bots", "--url", server.url, "--study", exp3_study, "--participants", "1"),
                *("--username", "botmaster", "--password-stdin", "--json", *options),
            ],
            input=PASSWORD + "\n",
            env={"TRUSTLAB_DATABASE_URL": database_url},
        )

    result = run_bots_command()
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    assert summary["completed"] == 1 and summary["errors"] == []

    # Someone sits at bot-1 (another run's participant, or one a hard stop left there): the
    # run is refused before it enrols anyone, and another prefix runs beside it.
    with database.writing() as db:
        seated = enrolment.enroll_participant(db, study_name=exp3_study, actor=Actor.system())
        stations.assign_participant(
            db, station_name="bot-1", participant=seated.participant, actor=Actor.system()
        )
    busy = run_bots_command()
    assert busy.exit_code == 2
    assert (
        f"error: station bot-1 already has participant {seated.participant.code} seated"
        in busy.stderr
    )
    with database.read_session() as db:
        assert db.scalar(select(func.count()).select_from(Participant)) == 2
    beside = run_bots_command("--station-prefix", "second")
    assert beside.exit_code == 0, beside.output
    assert json.loads(beside.stdout)["completed"] == 1

    # A lab's own station (a robot's key) is never the bots', whatever the prefix says.
    with database.writing() as db:
        stations.create_station(db, name="room-1", actor=Actor.system())
    with database.writing() as db:
        stations.issue_device_key(db, station_name="room-1", label="pepper", actor=Actor.system())
    robots = run_bots_command("--station-prefix", "room")
    assert robots.exit_code == 2
    assert "error: station room-1 has device keys of its own (pepper)" in robots.stderr
    with database.read_session() as db:
        assert db.scalar(select(func.count()).select_from(Participant)) == 3  # nobody enrolled
    refused = CliRunner().invoke(
        cli,
        [
            "bots",
            "--url",
            server.url,
            "--study",
            "nope",
            "--participants",
            "1",
            "--username",
            "botmaster",
            "--password-stdin",
        ],
        input=PASSWORD + "\n",
    )
    assert refused.exit_code == 2
    assert "error: the server refused: no study named 'nope'" in refused.stderr


@pytest.mark.slow
def test_the_demo_fills_its_study_once_then_retires_its_account(
    database: Database,
    database_url: str,
    exp3_study: str,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    settings = Settings(database_url=database_url, var_dir=tmp_path / "var")
    make_user(database, "admin", Role.ADMIN)  # as `trustlab init` does first
    with database.writing() as db:
        plan = demo.plan_demo(db, settings, Actor.system("test"))
    assert demo.pending_demo(settings) == plan
    # The demo study is the shipped protocol; fill the Exp3 test study instead to stay fast.
    plan = dataclasses.replace(plan, study=exp3_study, participants=2)
    server = ServerProcess(database_url, tmp_path / "server")
    server.start()
    said: list[str] = []
    quiet = demo.QuietWhileFilling()
    record = logging.LogRecord("uvicorn.access", logging.INFO, "", 0, "GET / 200", None, None)
    dropped_while_filling: list[bool] = []
    bots = demo.run_bots

    async def watched(config: BotConfig) -> BotSummary:
        dropped_while_filling.append(not quiet.filter(record))
        return await bots(config)

    monkeypatch.setattr(demo, "run_bots", watched)
    try:
        summary = demo.run_demo(plan, server.url, settings, said.append, quiet)
    finally:
        server.stop()
    # The request log is quiet while the bots run, and speaks again when they are done.
    assert "the request log resumes when it is done" in said[0]
    assert dropped_while_filling == [True] and quiet.filter(record)
    assert summary is not None and summary.errors == []
    assert summary.completed == 2
    assert said[-1].startswith("demo: done in") and "2 participants" in said[-1]
    assert demo.pending_demo(settings) is None, "the demo must run only once"
    with database.read_session() as db:
        assert users.authenticate(db, username=demo.DEMO_ACCOUNT, password=plan.password) is None
        assert db.scalar(select(func.count()).select_from(Answer)) == 2 * 39


def test_the_demo_keeps_its_account_if_it_became_the_only_active_admin(
    database: Database, database_url: str, tmp_path: Path
) -> None:
    """Retiring the bots' account must not leave no admin (the real one was disabled since)."""
    settings = Settings(database_url=database_url, var_dir=tmp_path / "var")
    make_user(database, "admin", Role.ADMIN)
    with database.writing() as db:
        plan = demo.plan_demo(db, settings, Actor.system("test"))
    with database.writing() as db:
        accounts.disable_user(db, username="admin", actor=Actor.system("test"))
    said: list[str] = []
    demo.retire(plan, settings, said.append)
    assert said == [
        "demo: the bots' account stays enabled: 'demo-bots' is the last active admin and cannot "
        "be disabled: make another account admin first"
    ]
    assert demo.pending_demo(settings) is None
    with database.read_session() as db:
        assert users.named(db, demo.DEMO_ACCOUNT).is_active


def test_retiring_the_demo_archives_the_bots_stations_only(
    database: Database, database_url: str, tmp_path: Path
) -> None:
    """A lab's station list shows its own stations after the demo: the bots' free stations are
    archived, a lab's station named like them but outside the demo's range is not."""
    settings = Settings(database_url=database_url, var_dir=tmp_path / "var")
    make_user(database, "admin", Role.ADMIN)
    with database.writing() as db:
        plan = demo.plan_demo(db, settings, Actor.system("test"))
        for name in ("demo-1", "demo-4", "demo-5", "lab-1"):
            stations.create_station(db, name=name, actor=Actor.system("test"))
    demo.retire(plan, settings, lambda _: None)
    with database.read_session() as db:
        shown = [s.name for s in stations.list_stations(db, archived=False)]
        hidden = [s.name for s in stations.list_stations(db, archived=True)]
    assert shown == ["demo-5", "lab-1"]
    assert hidden == ["demo-1", "demo-4"]


@pytest.mark.slow
@sqlite_only("the language's SQL runs on both engines in tests/app/test_languages.py")
def test_bots_take_part_in_swedish_and_choose_a_language_where_the_tablet_asks(
    server: ServerProcess, database: Database
) -> None:
    """A whole participant in Swedish (consent, pre-study, every prompt and reply, the trust
    and post questionnaires), and one who chooses on the tablet's language page."""
    text = (resources.files("app.protocols") / "fast_adaptation_trust_sv.toml").read_text()
    text = text.replace('learner = "meta"', 'learner = "exp3"')
    protocol = parse_protocol(text)
    with database.writing() as db:
        studies.create_study(db, name="sv", loaded=protocol, actor=Actor.system())
    swedish = protocol.protocol.in_language("sv")
    for language in ("sv", None):
        config = dataclasses.replace(_config(server, "sv", 1), language=language)
        summary = asyncio.run(run_bots(config))
        assert summary.errors == [] and summary.completed == 1
    with database.read_session() as db:
        chosen = dict(db.execute(select(Participant.code, Participant.language)).all())
        first = min(chosen)
        questions = db.execute(
            select(Prompt.category, Prompt.action, Prompt.question, Answer.reply)
            .join(Answer, Answer.prompt_id == Prompt.id)
            .join(Participant, Participant.id == Prompt.participant_id)
            .where(Participant.code == first)
        ).all()
        consent = db.scalar(
            select(Response.value).where(
                Response.instrument == "consent", Response.item == "consent_language"
            )
        )
        report = verify.verify_study(db, study_name="sv")
    assert chosen[first] == "sv" and set(chosen.values()) <= {"sv", "en"}
    assert None not in chosen.values()  # the second chose on the tablet
    lines = {level.line(answer) for level in swedish.replies.levels for answer in (True, False)}
    assert len(questions) == 39
    for category, action, question, reply in questions:
        assert question == swedish.category(category).questions[action]
        assert reply in lines
    assert consent == "sv"
    assert report.ok, report.findings
