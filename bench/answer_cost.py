"""Where an answer's time goes: SQL statements, CPU per request, and a profile, in-process.

Drives the real ASGI application (no sockets, no client) through prompt → answer cycles for one
robot and counts, per request kind, the SQL statements sent, the database round trips (statements
plus BEGIN/COMMIT), and the server's CPU time; the no-op (``GET /api/v1/ping``) is measured the
same way. CPU time does not depend on what else the machine runs, so it compares versions fairly
on a busy machine where wall-clock percentiles do not.

    .venv/bin/python bench/answer_cost.py                   # SQLite, 2000 answers
    .venv/bin/python bench/answer_cost.py --postgres postgresql+psycopg://postgres@127.0.0.1:5432/test
    .venv/bin/python bench/answer_cost.py --profile 30      # also the top 30 functions (cProfile)
    .venv/bin/python bench/answer_cost.py --sql             # also every statement of one answer
"""

from __future__ import annotations

import argparse
import asyncio
import cProfile
import json
import pstats
import sys
import tempfile
import time
import uuid
from collections import Counter, defaultdict
from pathlib import Path
from typing import Any

import uvloop
from sqlalchemy import event

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from app.main import create_app  # noqa: E402
from app.settings import Settings  # noqa: E402
from bench.api import bench_database, prepare  # noqa: E402


class Asgi:
    """Calls the application like a server would, one request at a time."""

    def __init__(self, app: Any, key: str) -> None:
        self.app = app
        self.headers = [
            (b"host", b"bench"),
            (b"authorization", f"Bearer {key}".encode()),
        ]

    async def request(self, method: str, path: str, body: Any = None) -> tuple[int, Any]:
        payload = b"" if body is None else json.dumps(body).encode()
        headers = list(self.headers)
        if body is not None:
            headers += [
                (b"content-type", b"application/json"),
                (b"content-length", str(len(payload)).encode()),
            ]
        scope = {
            "type": "http",
            "asgi": {"version": "3.0"},
            "http_version": "1.1",
            "method": method,
            "scheme": "http",
            "path": path,
            "raw_path": path.encode(),
            "query_string": b"",
            "root_path": "",
            "headers": headers,
            "client": ("127.0.0.1", 1),
            "server": ("127.0.0.1", 80),
            "state": {},
        }
        sent = False
        status = 0
        chunks: list[bytes] = []

        async def receive() -> dict[str, Any]:
            nonlocal sent
            if not sent:
                sent = True
                return {"type": "http.request", "body": payload, "more_body": False}
            await asyncio.sleep(3600)
            return {"type": "http.disconnect"}

        async def send(message: dict[str, Any]) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
            elif message["type"] == "http.response.body":
                chunks.append(message.get("body", b""))

        await self.app(scope, receive, send)
        raw = b"".join(chunks)
        return status, json.loads(raw) if raw else None


class Statements:
    """Counts SQL statements and transactions per request kind, and the CPU time of the
    database work (the thread-pool part of a request, app.api.device_work._work).

    BEGIN (sent as a statement on SQLite, by the driver on PostgreSQL) and COMMIT are counted as
    transactions, not statements: round trips = statements + 2 × transactions on both.
    """

    def __init__(self, engine: Any) -> None:
        self.kind = "other"
        self.statements: Counter[str] = Counter()
        self.transactions: Counter[str] = Counter()
        self.work_cpu: dict[str, float] = defaultdict(float)
        self.log: list[str] | None = None
        event.listen(engine, "before_cursor_execute", self._statement)
        event.listen(engine, "begin", self._begin)

    def _statement(self, _conn: Any, _cursor: Any, statement: str, *_: Any) -> None:
        if self.log is not None:
            self.log.append(" ".join(statement.split())[:160])
        if not statement.startswith("BEGIN"):
            self.statements[self.kind] += 1

    def _begin(self, _conn: Any) -> None:
        self.transactions[self.kind] += 1


async def drive(app: Any, key: str, answers: int, counter: Statements) -> dict[str, Any]:
    """Warm up, then ``answers`` prompt → answer cycles and as many pings; CPU per request."""
    robot = Asgi(app, key)
    experimenter_start = app.state.bench_start_session
    cpu: dict[str, float] = dict.fromkeys(("answer", "prompt", "ping"), 0.0)
    wall: dict[str, list[float]] = {kind: [] for kind in ("answer", "prompt", "ping")}
    counts: Counter[str] = Counter()

    async def timed(kind: str, method: str, path: str, body: Any = None) -> tuple[int, Any]:
        counter.kind = kind
        c0, w0 = time.process_time(), time.perf_counter()
        status, data = await robot.request(method, path, body)
        cpu[kind] += time.process_time() - c0
        wall[kind].append(time.perf_counter() - w0)
        counts[kind] += 1
        counter.kind = "other"
        return status, data

    _, state = await robot.request("GET", "/api/v1/station")
    expected = state["expected"]
    done = 0
    while done < answers:
        if expected["action"] == "start_session":
            expected = await experimenter_start()
            continue
        assert expected["action"] == "prompt", expected
        status, step = await timed(
            "prompt", "POST", "/api/v1/station/prompts", {"category": expected["categories"][0]}
        )
        assert status in (200, 201), step
        status, reply = await timed(
            "answer",
            "POST",
            f"/api/v1/station/steps/{step['step_id']}/answer",
            {"answer": "yes" if step["action"] == 0 else "no", "idempotency_key": uuid.uuid4().hex},
        )
        assert status == 200, reply
        status, _ = await timed("ping", "GET", "/api/v1/ping")
        assert status == 200
        expected = reply["expected"]
        done += 1
    return {
        kind: {
            "requests": counts[kind],
            "cpu_us": round(1e6 * cpu[kind] / counts[kind], 1),
            "wall_us": round(1e6 * sum(wall[kind]) / counts[kind], 1),
            "wall_p99_us": round(1e6 * sorted(wall[kind])[int(0.99 * (counts[kind] - 1))], 1),
            "db_work_cpu_us": round(1e6 * counter.work_cpu[kind] / counts[kind], 1),
            "statements": round(counter.statements[kind] / counts[kind], 2),
            "transactions": round(counter.transactions[kind] / counts[kind], 2),
        }
        for kind in ("answer", "prompt", "ping")
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--postgres", help="maintenance URL; measures PostgreSQL instead")
    parser.add_argument("--answers", type=int, default=2000)
    parser.add_argument("--profile", type=int, default=0, help="print the top N functions")
    parser.add_argument(
        "--profile-db",
        type=int,
        default=0,
        help="print the top N functions of the database work, by its thread's CPU time",
    )
    parser.add_argument(
        "--profile-out", help="also save the database work's profile here (for pstats)"
    )
    parser.add_argument("--sql", action="store_true", help="print one answer's statements")
    parser.add_argument("--synchronous", default="FULL", help="SQLite PRAGMA synchronous")
    args = parser.parse_args()
    with (
        tempfile.TemporaryDirectory() as tmp,
        bench_database(args.postgres, tmp, "cost") as url,
    ):
        key = prepare(url, 1, exp3_only=True)[0]
        settings = Settings(
            database_url=url,
            var_dir=Path(tmp) / "var",
            secret_key="answer-cost-secret-0123456789abcdef",
            sqlite_synchronous=args.synchronous,
        )
        app = create_app(settings)
        counter = Statements(app.state.database.engine)
        # The thread's CPU time, not the wall clock: on PostgreSQL the wall clock is mostly the
        # wait for the server, which hides where the worker's own CPU goes.
        worker_profile = cProfile.Profile(time.thread_time) if args.profile_db else None
        from app.api import device_work

        work = device_work._work

        def measured_work(*work_args: Any) -> Any:
            kind, c0 = counter.kind, time.thread_time()
            if worker_profile is not None:
                worker_profile.enable()
            try:
                return work(*work_args)
            finally:
                if worker_profile is not None:
                    worker_profile.disable()
                counter.work_cpu[kind] += time.thread_time() - c0

        device_work._work = measured_work  # type: ignore[assignment]

        async def run() -> dict[str, Any]:
            from app.services.audit import Actor
            from app.services.sessions import runtime

            database = app.state.database

            async def start_session() -> dict[str, Any]:
                def start() -> None:
                    with database.write_session() as db:
                        runtime.start_session(
                            db, station_name="bench-0", actor=Actor.system("bench")
                        )

                await asyncio.to_thread(start)
                robot = Asgi(app, key)
                return dict((await robot.request("GET", "/api/v1/station"))[1]["expected"])

            app.state.bench_start_session = start_session
            async with app.router.lifespan_context(app):
                await drive(app, key, min(200, args.answers), counter)  # warm-up
                counter.statements.clear()
                counter.transactions.clear()
                counter.work_cpu.clear()
                if args.sql:
                    counter.log = []
                    await drive(app, key, 1, counter)
                    for line in counter.log:
                        print(line)
                    counter.log = None
                    counter.statements.clear()
                    counter.transactions.clear()
                    counter.work_cpu.clear()
                profiler = cProfile.Profile() if args.profile else None
                if worker_profile is not None:
                    worker_profile.clear()
                if profiler is not None:
                    profiler.enable()
                result = await drive(app, key, args.answers, counter)
                if profiler is not None:
                    profiler.disable()
                    stats = pstats.Stats(profiler)
                    stats.sort_stats("cumulative").print_stats(args.profile)
                    stats.sort_stats("tottime").print_stats(args.profile)
                if worker_profile is not None:
                    if args.profile_out:
                        worker_profile.dump_stats(args.profile_out)
                    stats = pstats.Stats(worker_profile)
                    stats.sort_stats("cumulative").print_stats(args.profile_db)
                    stats.sort_stats("tottime").print_stats(args.profile_db)
                return result

        result = uvloop.run(run())
    engine = "postgresql" if args.postgres else "sqlite"
    print(json.dumps({"engine": engine, **result}, indent=1))


if __name__ == "__main__":
    main()
