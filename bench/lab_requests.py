"""What the lab's other requests cost: sessions, tablets, station states and sign-in, in-process.

``bench/load.py`` offers, beside the robots' prompts and answers, session starts, tablet page polls,
questionnaire submissions and station reads. This drives those requests through the real ASGI
application one at a time (no sockets, no concurrency) the way the load benchmark's clients send
them, and counts per request kind:

- the server's CPU time (process time: it does not depend on what else the machine runs);
- SQL statements (BEGIN/COMMIT excluded), transactions, and write transactions (on SQLite
  ``BEGIN IMMEDIATE``: the single write lock);
- thread-pool hops, and how many of them began while the request held a write transaction open
  (on SQLite: while it held the write lock, so every other writer waited for that hop too);
- how long the write lock was held, from queueing for BEGIN IMMEDIATE to the end of the driver's
  COMMIT or ROLLBACK (PostgreSQL: how long a write transaction was open, until COMMIT is sent).

The flow per cycle, at one of ``--stations`` stations: the robot reads its state, the experimenter
reads it too and starts the next session; every other session ends with its last answer (as in the
load benchmark), the rest are ended early by the experimenter; then the participant's tablet shows
the session's questionnaire, which is submitted, and shows the wait page. Every few cycles the
experimenter signs in again (Argon2id with the production cost dominates that request's CPU).

    .venv/bin/python bench/lab_requests.py                       # SQLite, median of 3 runs
    .venv/bin/python bench/lab_requests.py --postgres postgresql+psycopg://postgres@127.0.0.1:5432/test
    .venv/bin/python bench/lab_requests.py --runs 1 --sql        # also each kind's statements
"""

from __future__ import annotations

import argparse
import json
import random
import statistics
import sys
import tempfile
import threading
import time
import uuid
from collections import Counter, defaultdict
from collections.abc import Callable
from datetime import timedelta
from pathlib import Path
from typing import Any, TypeVar

import anyio.to_thread
import uvloop
from sqlalchemy import event, select

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from app import db as app_db  # noqa: E402
from app.bots import ResponseModel, questionnaire_answers  # noqa: E402
from app.main import create_app  # noqa: E402
from app.services.staff import users  # noqa: E402
from app.settings import Settings  # noqa: E402
from app.tables import User  # noqa: E402
from bench.answer_cost import Asgi, Statements  # noqa: E402
from bench.api import bench_database  # noqa: E402
from bench.load import PASSWORD, SERVER_SECRET, prepare  # noqa: E402

T = TypeVar("T")

KINDS = (
    "start session",
    "answer (ends session)",
    "end session",
    "questionnaire",
    "tablet page",
    "station state (robot)",
    "station state (experimenter)",
    "sign in",
)
"""The request kinds reported (prompts and ordinary answers are driven but not reported: see
bench/answer_cost.py for those)."""
BACKGROUND_THREADS = ("trustlab-activity", "trustlab-checkpoint")


def _background() -> bool:
    return threading.current_thread().name in BACKGROUND_THREADS


class LabCounter(Statements):
    """:class:`bench.answer_cost.Statements` plus write transactions, hops and write-lock time.

    Requests run one at a time, so whatever a request thread does while ``kind`` is set belongs
    to that request; the activity recorder's and the WAL checkpointer's threads are left out.
    """

    def __init__(self, engine: Any) -> None:
        super().__init__(engine)
        self.reset()
        self.capture: list[str] | None = None
        self._open: dict[int, tuple[str, float]] = {}
        # First in line, so the time includes queueing for the lock and BEGIN IMMEDIATE itself.
        event.listen(engine, "begin", self._write_begins, insert=True)
        if engine.dialect.name != "sqlite":
            event.listen(engine, "commit", self._pg_write_ends)
            event.listen(engine, "rollback", self._pg_write_ends)

    def reset(self) -> None:
        """Forget everything counted so far (after the warm-up)."""
        self.statements.clear()
        self.transactions.clear()
        self.writes: Counter[str] = Counter()
        self.hops: Counter[str] = Counter()
        self.held_hops: Counter[str] = Counter()
        self.held_seconds: dict[str, float] = defaultdict(float)
        self.longest_hold: dict[str, float] = defaultdict(float)
        self.sql: dict[str, list[str]] = {}

    def _statement(self, conn: Any, cursor: Any, statement: str, *rest: Any) -> None:
        if _background():
            return
        if self.capture is not None and not statement.startswith("BEGIN"):
            self.capture.append(" ".join(statement.split())[:200])
        super()._statement(conn, cursor, statement, *rest)

    def _begin(self, conn: Any) -> None:
        if not _background():
            super()._begin(conn)

    def _write_begins(self, conn: Any) -> None:
        if _background() or not conn.get_execution_options().get(app_db.WRITE_OPTION, False):
            return
        self.writes[self.kind] += 1
        self._open[id(conn.connection.driver_connection)] = (self.kind, time.perf_counter())

    def write_ends(self, driver_connection: Any) -> None:
        """A write transaction ended on this driver connection (if one was open there)."""
        began = self._open.pop(id(driver_connection), None)
        if began is not None:
            kind, started = began
            held = time.perf_counter() - started
            self.held_seconds[kind] += held
            self.longest_hold[kind] = max(self.longest_hold[kind], held)

    def _pg_write_ends(self, conn: Any) -> None:
        self.write_ends(conn.connection.driver_connection)

    def hop(self) -> None:
        """A thread-pool hop begins."""
        self.hops[self.kind] += 1
        if self._open:
            self.held_hops[self.kind] += 1


def instrument(counter: LabCounter) -> Callable[[], None]:
    """Count thread-pool hops and SQLite lock releases; returns the undo."""
    run_sync = anyio.to_thread.run_sync
    release = app_db._GatedConnection.release_writer

    async def counted(func: Callable[..., T], *args: Any, **kwargs: Any) -> T:
        counter.hop()
        return await run_sync(func, *args, **kwargs)

    def released(connection: app_db._GatedConnection) -> None:
        if connection.holds_writer:
            release(connection)
            counter.write_ends(connection)
        else:
            release(connection)

    anyio.to_thread.run_sync = counted  # type: ignore[assignment]
    app_db._GatedConnection.release_writer = released  # type: ignore[method-assign,assignment]

    def undo() -> None:
        anyio.to_thread.run_sync = run_sync
        app_db._GatedConnection.release_writer = release  # type: ignore[method-assign]

    return undo


def client(app: Any, headers: dict[str, str]) -> Asgi:
    """An in-process client sending these headers."""
    asgi = Asgi(app, "")
    asgi.headers = [(b"host", b"bench")] + [(k.encode(), v.encode()) for k, v in headers.items()]
    return asgi


class Driver:
    """Sends the lab's requests one at a time and measures the reported kinds."""

    def __init__(self, app: Any, counter: LabCounter) -> None:
        self.app = app
        self.counter = counter
        self.cpu: dict[str, float] = defaultdict(float)
        self.wall: dict[str, float] = defaultdict(float)
        self.requests: Counter[str] = Counter()
        self.rng = random.Random(2026)
        self.model = ResponseModel()

    async def timed(
        self,
        kind: str,
        asgi: Asgi,
        method: str,
        path: str,
        body: Any = None,
        ok: tuple[int, ...] = (200,),
    ) -> Any:
        counter = self.counter
        counter.kind = kind
        counter.capture = [] if kind in KINDS and kind not in counter.sql else None
        c0, w0 = time.process_time(), time.perf_counter()
        status, data = await asgi.request(method, path, body)
        self.cpu[kind] += time.process_time() - c0
        self.wall[kind] += time.perf_counter() - w0
        self.requests[kind] += 1
        if counter.capture is not None:
            counter.sql[kind] = counter.capture
            counter.capture = None
        counter.kind = "other"
        if status not in ok:
            raise SystemExit(f"error: {kind}: HTTP {status}: {data}")
        return data

    async def cycle(
        self,
        number: int,
        robot: Asgi,
        staff: Asgi,
        tablet: Asgi,
        station: str,
        condition: str,
    ) -> None:
        """One session at ``station``, its questionnaire, and the reads around it."""
        state = await self.timed("station state (robot)", robot, "GET", "/api/v1/station")
        await self.timed(
            "station state (experimenter)", staff, "GET", f"/api/v1/stations/{station}/state"
        )
        expected = state["expected"]
        if expected["action"] != "start_session":
            raise SystemExit(f"error: {station} expects {expected}, not a session start")
        started = await self.timed(
            "start session", staff, "POST", f"/api/v1/stations/{station}/sessions", {}, (201,)
        )
        expected = started["expected"]
        if number % 2 == 0:
            await self.finish_by_answers(robot, expected)
        else:
            await self.timed(
                "end session", staff, "POST", f"/api/v1/stations/{station}/sessions/current/end"
            )
        # The tablet fills in whatever it is shown (the pre-study questionnaires first, which the
        # warm-up takes care of), then shows the wait page.
        page = await self.timed("tablet page", tablet, "GET", "/api/v1/tablet")
        while page["kind"] == "questionnaire":
            answers = questionnaire_answers(page, self.model, condition, self.rng)
            body = {"session": page["session"], "answers": answers}
            path = f"/api/v1/tablet/questionnaires/{page['instrument']['key']}"
            page = await self.timed("questionnaire", tablet, "POST", path, body)
        if page["kind"] != "wait":
            raise SystemExit(f"error: after the questionnaires the tablet shows {page['kind']}")
        await self.timed("tablet page", tablet, "GET", "/api/v1/tablet")

    async def finish_by_answers(self, robot: Asgi, expected: dict[str, Any]) -> None:
        """Prompt and answer until the session's last answer ends it (the load's robots)."""
        while True:
            if expected["action"] != "prompt":
                raise SystemExit(f"error: the robot expected to prompt, not {expected}")
            body = {"category": self.rng.choice(expected["categories"])}
            step = await self.timed(
                "prompt", robot, "POST", "/api/v1/station/prompts", body, (201,)
            )
            # The answer to the last pending category of the session's last run ends it.
            ends = step["run"] == RUNS_PER_SESSION and expected["categories"] == [body["category"]]
            answer = {"answer": self.rng.choice(["yes", "no"]), "idempotency_key": uuid.uuid4().hex}
            path = f"/api/v1/station/steps/{step['step_id']}/answer"
            kind = "answer (ends session)" if ends else "answer"
            reply = await self.timed(kind, robot, "POST", path, answer)
            if reply["session_completed"] != ends:
                raise SystemExit("error: the session ended at another answer than foreseen")
            if ends:
                return
            expected = reply["expected"]

    async def sign_in(self) -> None:
        """The experimenter signs in through the API (as bench/load.py's dashboards do)."""
        anonymous = client(self.app, {})
        credentials = {"username": "bench", "password": PASSWORD}
        await self.timed("sign in", anonymous, "POST", "/api/v1/session", credentials)


def staff_headers(app: Any) -> dict[str, str]:
    """Cookie and CSRF header of a login made directly in the database (not measured)."""
    database = app.state.database
    with database.writing() as db:
        user = db.scalar(select(User).where(User.username == "bench"))
        assert user is not None
        login = users.sign_in(db, user=user, lifetime=timedelta(hours=8))
    return {"cookie": f"tl_session={login.token}", "x-csrf-token": login.session.csrf_token}


async def drive(app: Any, lab: Any, counter: LabCounter, cycles: int, sign_ins: int) -> Driver:
    """``cycles`` session cycles round-robin over the stations, with ``sign_ins`` sign-ins."""
    driver = Driver(app, counter)
    staff = client(app, staff_headers(app))
    stations = len(lab.robot_keys)
    every = max(1, cycles // max(1, sign_ins))
    for number in range(cycles):
        n = number % stations
        robot = client(app, {"authorization": f"Bearer {lab.robot_keys[n]}"})
        tablet = client(app, {"authorization": f"Bearer {lab.tablet_tokens[n]}"})
        await driver.cycle(number, robot, staff, tablet, f"robot-{n:03d}", lab.conditions[n])
        if sign_ins and number % every == every - 1:
            await driver.sign_in()
    return driver


def summary(driver: Driver, counter: LabCounter) -> dict[str, dict[str, float]]:
    """Per reported kind: means per request."""
    rows = {}
    for kind in KINDS:
        n = driver.requests[kind]
        if not n:
            continue
        rows[kind] = {
            "requests": n,
            "cpu_us": 1e6 * driver.cpu[kind] / n,
            "wall_us": 1e6 * driver.wall[kind] / n,
            "statements": counter.statements[kind] / n,
            "transactions": counter.transactions[kind] / n,
            "write_transactions": counter.writes[kind] / n,
            "hops": counter.hops[kind] / n,
            "hops_holding_write": counter.held_hops[kind] / n,
            "write_held_us": 1e6 * counter.held_seconds[kind] / n,
            "write_held_max_us": 1e6 * counter.longest_hold[kind],
        }
    return rows


def one_run(args: argparse.Namespace, run: int) -> tuple[dict[str, Any], dict[str, list[str]]]:
    """A fresh database and application, a warm-up, then the measured cycles."""
    with (
        tempfile.TemporaryDirectory() as tmp,
        bench_database(args.postgres, tmp, "lab") as url,
    ):
        lab = prepare(url, args.stations, args.stations, exp3_only=True)
        settings = Settings(
            _env_file=None,
            database_url=url,
            var_dir=Path(tmp) / "var",
            secret_key=SERVER_SECRET.decode(),
            sqlite_synchronous=args.synchronous,
        )
        app = create_app(settings)
        counter = LabCounter(app.state.database.engine)
        undo = instrument(counter)

        async def measure() -> Driver:
            async with app.router.lifespan_context(app):
                await drive(app, lab, counter, args.warmup, 0)
                counter.reset()
                return await drive(app, lab, counter, args.cycles, args.sign_ins)

        try:
            driver = uvloop.run(measure())
        finally:
            undo()
            app.state.database.engine.dispose()
        print(f"run {run}: {sum(driver.requests.values())} requests", file=sys.stderr)
        return summary(driver, counter), counter.sql


RUNS_PER_SESSION = 4
"""bench/load.py's schedule (``load_protocol``): 4 runs of 3 categories per session."""


def median_rows(runs: list[dict[str, Any]]) -> dict[str, dict[str, float]]:
    """Each figure's median over the runs."""
    kinds = [k for k in KINDS if all(k in run for run in runs)]
    return {
        kind: {
            field: statistics.median(run[kind][field] for run in runs) for field in runs[0][kind]
        }
        for kind in kinds
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--postgres", help="maintenance URL; measures PostgreSQL instead")
    parser.add_argument("--runs", type=int, default=3, help="fresh databases; medians reported")
    parser.add_argument("--stations", type=int, default=4)
    parser.add_argument("--cycles", type=int, default=60, help="sessions measured per run")
    parser.add_argument("--warmup", type=int, default=8, help="sessions before measuring")
    parser.add_argument("--sign-ins", type=int, default=4, help="sign-ins measured per run")
    parser.add_argument("--synchronous", default="FULL", help="SQLite PRAGMA synchronous")
    parser.add_argument("--sql", action="store_true", help="print each kind's statements")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    args = parser.parse_args()
    if args.warmup < args.stations:
        raise SystemExit("error: --warmup must visit every station (pre-study questionnaires)")
    if (args.warmup + args.cycles) > 50 * args.stations:
        raise SystemExit("error: each participant has 50 sessions: add --stations")
    runs: list[dict[str, Any]] = []
    sql: dict[str, list[str]] = {}
    for run in range(1, args.runs + 1):
        rows, sql = one_run(args, run)
        runs.append(rows)
    rows = median_rows(runs)
    engine = "postgresql" if args.postgres else f"sqlite (synchronous={args.synchronous})"
    if args.json:
        print(json.dumps({"engine": engine, "runs": runs, "median": rows}))
        return
    print(f"engine: {engine}; medians of {args.runs} run(s), per request")
    header = (
        f"{'request':<30}{'CPU µs':>8}{'wall µs':>9}{'stmts':>7}{'txns':>6}{'write':>6}"
        f"{'hops':>6}{'held':>6}{'lock µs':>9}{'max µs':>8}"
    )
    print(header)
    for kind, row in rows.items():
        print(
            f"{kind:<30}{row['cpu_us']:>8.0f}{row['wall_us']:>9.0f}{row['statements']:>7.2f}"
            f"{row['transactions']:>6.2f}{row['write_transactions']:>6.2f}{row['hops']:>6.2f}"
            f"{row['hops_holding_write']:>6.2f}{row['write_held_us']:>9.0f}"
            f"{row['write_held_max_us']:>8.0f}"
        )
    print(
        "stmts: SQL statements (BEGIN/COMMIT not counted); txns: transactions; write: write "
        "transactions; hops: thread-pool hops; held: hops begun while holding a write "
        "transaction; lock µs: write lock (PostgreSQL: write transaction) held, mean and max"
    )
    if args.sql:
        for kind in KINDS:
            print(f"\n-- {kind}")
            for line in sql.get(kind, []):
                print(line)


if __name__ == "__main__":
    main()
