"""The least an answer can cost on PostgreSQL here: its statements alone, served beside the no-op.

Issue 4's target is an answer p99 at most 3 × the no-op's p99 (bench/api.py). This benchmark asks
whether *any* answer route on this stack could meet it on this machine. It serves trustlab's own
application (the same middleware, routing, thread pool and ``GET /api/v1/ping``) with three extra
routes, each measured against the no-op in the same run, as bench/api.py measures the answer:

- ``body``: the answer's request (a JSON body validated by Pydantic, the device key's header, the
  thread-pool hop) and a fixed reply, no database at all: what the HTTP side of an answer costs;
- ``write``: the same, plus the cheapest durable record of an answer there is: one answer row
  inserted and committed, in one round trip;
- ``floor``: the same, plus everything else every answer must do on PostgreSQL, with the product's
  own SQL (app.services.sessions.step_store) and nothing more: the device key's seat, the
  participant's timeline lock, the step's run, the run's prompts and the learner's version, all five
  and the BEGIN in one pipelined round trip (as if every id were known in advance: the product
  learns the participant from the seat, so it cannot do better); then the learner's new state (the
  stored Exp3 state again, the same size), the audit row, one ``pg_notify``, the answer row and the
  COMMIT in a second round trip.

Answer rows go to a copy of the ``answer`` table without its indexes and constraints, so a step can
be "answered" again and again and each route stays a lower bound of the real one. No ORM session,
no learner arithmetic, no response model. If a route's p99 ratio already exceeds 3, no answer that
does at least that much can meet the target on this machine, however it is written.

    .venv/bin/python bench/pg_floor.py --postgres postgresql+psycopg://postgres@127.0.0.1:5432/test
    .venv/bin/python bench/pg_floor.py --postgres URL --routes floor --async-commit   # diagnosis

``--async-commit`` sets ``synchronous_commit = off`` on the routes' connections: COMMIT no longer
waits for the WAL to reach the disk. trustlab cannot run so (an acknowledged answer could be lost),
but it separates the disk's share of the latency from the CPU's.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import threading
import time
import uuid
from datetime import UTC, datetime
from pathlib import Path
from typing import Annotated, Any

import psycopg
import uvloop
from fastapi import FastAPI, Header
from fastapi.responses import Response
from pydantic import BaseModel
from sqlalchemy.engine import make_url

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from app import events  # noqa: E402
from app.db import Database  # noqa: E402
from app.main import create_app  # noqa: E402
from app.security import token_digest  # noqa: E402
from app.services.sessions import runtime, step_store  # noqa: E402
from app.settings import Settings  # noqa: E402
from app.sql import Cursor  # noqa: E402
from bench.api import SYSTEM, Samples, alternate, bench_database, percentile, prepare  # noqa: E402
from bench.rawhttp import RawHttp  # noqa: E402
from tests.servers import ServerProcess  # noqa: E402

_FLOOR_TABLE = "bench_floor_answer"
ASYNC_COMMIT = "BENCH_FLOOR_ASYNC_COMMIT"
ROUTES = ("body", "write", "floor")
# The product's statements, verbatim (their PostgreSQL text).
_READS = (
    step_store._DEVICE_SEAT,
    step_store._LOCK_PARTICIPANT,
    step_store._RUN_OF_STEP,
    step_store._STEPS_OF_RUN,
    step_store._LEARNER,
)
_INSERT_FLOOR_ANSWER = step_store._INSERT_ANSWER.text(True).replace(
    "INSERT INTO answer", f"INSERT INTO {_FLOOR_TABLE}"
)
_NOTIFY_PAYLOADS = json.dumps([events.Event("bench", "answer_recorded", {"step_id": 0}).to_json()])
_REPLY = b'{"reply":"I am fairly sure.","confidence_level":1,"probability":0.5}'


class FloorAnswer(BaseModel):
    """What the client sends: the answer, and the ids the product would have to look up."""

    step: int
    participant: int
    run: int
    category: str
    study: int
    answer: bool
    idempotency_key: str


_local = threading.local()
_states: dict[int, Any] = {}
"""Every learner's stored state, read at start-up: the floor writes it back unchanged."""


def _connection(conninfo: str) -> psycopg.Connection[Any]:
    """This thread's own connection (the thread pool's threads live as long as the worker)."""
    conn: psycopg.Connection[Any] | None = getattr(_local, "conn", None)
    if conn is None:
        conn = _local.conn = psycopg.connect(conninfo)
        if os.environ.get(ASYNC_COMMIT):
            conn.execute("SET synchronous_commit = off")
            conn.commit()
    return conn


def _floor_answer(conninfo: str, key: str, body: FloorAnswer) -> None:
    """An answer's PostgreSQL work and nothing else, in two round trips."""
    conn = _connection(conninfo)
    # A pipeline sends everything queued in it, and a Sync, when it ends: one round trip each.
    with conn.pipeline():
        cursors = [conn.cursor() for _ in _READS]
        params: list[dict[str, Any]] = [
            {"digest": token_digest(key)},
            {"participant": body.participant},
            {"step": body.step, "participant": body.participant},
            {"run": body.run},
            {"participant": body.participant, "category": body.category},
        ]
        for cursor, statement, values in zip(cursors, _READS, params, strict=True):
            cursor.execute(statement.text(True), values)
    rows = [cursor.fetchall() for cursor in cursors]  # BEGIN and the five reads: round trip 1
    learner_id, version = rows[4][0][0], rows[4][0][5]
    state = _states[learner_id]
    now = time.time()
    with conn.pipeline():
        writes = conn.cursor()
        writes.execute(
            step_store._SAVE_LEARNER.text(True),
            {
                "state": psycopg.types.json.Jsonb(state),
                "version": version + 1,
                "now": _timestamp(now),
                "learner": learner_id,
                "was": version,
            },
        )
        writes.execute(
            step_store._INSERT_AUDIT.text(True),
            {
                "now": _timestamp(now),
                "kind": "device",
                "actor": "bench/floor",
                "action": "answer.recorded",
                "study": body.study,
                "subject": "P-FLOOR",
                "details": psycopg.types.json.Jsonb({"step_id": body.step, "answer": body.answer}),
            },
        )
        writes.execute(
            events._NOTIFY_ALL.text(True),
            {"c": events.CHANNEL, "payloads": _NOTIFY_PAYLOADS},
        )
        writes.execute(_INSERT_FLOOR_ANSWER, _answer_row(body, version + 1, now))
        _commit_in(writes)  # round trip 2: the writes and the COMMIT


def _commit_in(cursor: psycopg.Cursor[Any]) -> None:
    """Queue the COMMIT in the cursor's pipeline. ``connection.commit()`` there would wait for the
    server once more before the pipeline's own Sync; psycopg reads the transaction's status from
    the server, so its ``commit()`` afterwards sees nothing left to commit."""
    cursor.execute("COMMIT")


def _answer_row(body: FloorAnswer, learner_version: int, now: float) -> dict[str, Any]:
    """The answer row's values (as many and as large as the product's)."""
    return {
        "prompt": body.step,
        "participant": body.participant,
        "answer": body.answer,
        "reward": 1.0 if body.answer else 0.0,
        "after": psycopg.types.json.Jsonb([0.25, 0.25, 0.25, 0.25]),
        "p_preferred": 0.25,
        "probability": 0.25,
        "level": 1,
        "confidence": "medium",
        "reply": "I am fairly sure.",
        "learner_version": learner_version,
        "key": body.idempotency_key,
        "now": _timestamp(now),
        "processing_ms": 0.0,
        "device": None,
        "actor": "bench/floor",
        "modality": "button",
        "transcript": None,
        "transcript_confidence": None,
        "transcript_engine": None,
    }


def _timestamp(now: float) -> datetime:
    return datetime.fromtimestamp(now, UTC)


def floor_app(settings: Settings | None = None) -> FastAPI:
    """trustlab's application with the three routes added (uvicorn ``--factory``)."""
    settings = settings or Settings()
    app = create_app(settings)
    conninfo = make_url(settings.database_url).set(drivername="postgresql")
    dsn = conninfo.render_as_string(hide_password=False)
    with psycopg.connect(dsn) as conn:
        _states.update(dict(conn.execute("SELECT id, state FROM learner").fetchall()))

    @app.post("/bench/floor")
    def floor(body: FloorAnswer, authorization: Annotated[str, Header()]) -> Response:
        _floor_answer(dsn, authorization.removeprefix("Bearer "), body)
        return Response(_REPLY, media_type="application/json")

    @app.post("/bench/write")
    def write_only(body: FloorAnswer, authorization: Annotated[str, Header()]) -> Response:
        conn = _connection(dsn)
        with conn.pipeline():  # one round trip: BEGIN, the row and the COMMIT
            cursor = conn.cursor()
            cursor.execute(_INSERT_FLOOR_ANSWER, _answer_row(body, 1, time.time()))
            _commit_in(cursor)
        return Response(_REPLY, media_type="application/json")

    @app.post("/bench/body")
    def body_only(body: FloorAnswer, authorization: Annotated[str, Header()]) -> Response:
        return Response(_REPLY, media_type="application/json")

    return app


def _open_steps(url: str, clients: int) -> list[dict[str, Any]]:
    """Start a session at every bench station and open one prompt there: the floor's bodies."""
    database = Database(url)
    bodies = []
    for number in range(clients):
        station = f"bench-{number}"
        with database.write_session() as db:
            runtime.start_session(db, station_name=station, actor=SYSTEM)
        with database.write_session() as db:
            category = runtime.station_view(db, station_name=station).expected.categories[0]
            step = runtime.request_prompt(
                db, station_name=station, category=category, actor=SYSTEM
            ).prompt
        with database.read_session() as db:
            cursor = Cursor.of(db)
            seat = step_store.station_seat(cursor, name=station)
            assert seat is not None and seat.participant is not None
            run = step_store.run_of_step(
                cursor, step_id=step.id, participant_id=step.participant_id
            )
            assert run is not None
        bodies.append(
            {
                "step": step.id,
                "participant": step.participant_id,
                "run": run.run_id,
                "category": category,
                "study": seat.participant.study_id,
                "answer": True,
            }
        )
    database.dispose()
    dsn = make_url(url).set(drivername="postgresql").render_as_string(hide_password=False)
    with psycopg.connect(dsn, autocommit=True) as conn:
        conn.execute(f"CREATE TABLE {_FLOOR_TABLE} (LIKE answer INCLUDING DEFAULTS)")
    return bodies


async def route_loop(
    base: str,
    route: str,
    key: str,
    body: dict[str, Any],
    deadline: float,
    samples: list[float],
    errors: list[str],
) -> None:
    client = RawHttp(base, {"Authorization": f"Bearer {key}"})
    try:
        while time.perf_counter() < deadline:
            t0 = time.perf_counter()
            status, reply = await client.request(
                "POST", f"/bench/{route}", {**body, "idempotency_key": uuid.uuid4().hex}
            )
            samples.append(time.perf_counter() - t0)
            if status != 200:
                errors.append(f"{route}: {status} {reply}")
                return
    finally:
        await client.close()


async def measure(
    base: str,
    route: str,
    keys: list[str],
    bodies: list[dict[str, Any]],
    clients: int,
    seconds: float,
    rounds: int,
) -> dict[str, Any]:
    """One route at one concurrency: no-op and route phases alternating, as in bench/api.py."""
    samples = Samples()
    await alternate(
        base,
        keys[:clients],
        seconds,
        rounds,
        samples,
        lambda i, deadline: route_loop(
            base, route, keys[i], bodies[i], deadline, samples.answer, samples.errors
        ),
    )
    route_p99, ping_p99 = percentile(samples.answer, 0.99), percentile(samples.ping, 0.99)
    return {
        "route": route,
        "clients": clients,
        "per_s": round(len(samples.answer) / seconds, 1),
        "p50_ms": round(percentile(samples.answer, 0.50), 2),
        "p99_ms": round(route_p99, 2),
        "noop_p50_ms": round(percentile(samples.ping, 0.50), 2),
        "noop_p99_ms": round(ping_p99, 2),
        "p99_ratio": round(route_p99 / ping_p99, 2),
        "errors": len(samples.errors),
        "first_error": samples.errors[0] if samples.errors else None,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--postgres", required=True, help="maintenance URL")
    parser.add_argument("--workers", type=int, default=2, help="uvicorn workers")
    parser.add_argument("--clients", default="1,10,100", help="concurrency levels")
    parser.add_argument("--routes", default=",".join(ROUTES), help="which routes, in order")
    parser.add_argument("--seconds", type=float, default=10.0, help="route time per level")
    parser.add_argument("--rounds", type=int, default=4, help="alternations per level")
    parser.add_argument(
        "--async-commit", action="store_true", help="COMMIT without waiting for the disk"
    )
    args = parser.parse_args()
    levels = [int(c) for c in args.clients.split(",")]
    routes = args.routes.split(",")
    if unknown := set(routes) - set(ROUTES):
        parser.error(f"unknown routes {sorted(unknown)}; choose from {', '.join(ROUTES)}")
    load_before = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp, bench_database(args.postgres, tmp, "floor") as url:
        keys = prepare(url, max(levels), exp3_only=True)
        bodies = _open_steps(url, max(levels))
        server = ServerProcess(
            url,
            Path(tmp) / "var",
            workers=args.workers,
            # The server imports this module: from the checkout, whatever the current directory.
            extra_env={
                "PYTHONPATH": str(ROOT),
                **({ASYNC_COMMIT: "1"} if args.async_commit else {}),
            },
            factory="bench.pg_floor:floor_app",
        )
        server.start()
        try:
            results = [
                uvloop.run(measure(server.url, route, keys, bodies, c, args.seconds, args.rounds))
                for route in routes
                for c in levels
            ]
        finally:
            server.stop()
    commit = "asynchronous (diagnosis)" if args.async_commit else "synchronous"
    print(
        f"engine=postgresql commit={commit} workers={args.workers} seconds={args.seconds} "
        f"rounds={args.rounds} load average {load_before:.2f} -> {os.getloadavg()[0]:.2f} "
        f"on {os.cpu_count()} cores"
    )
    columns = ("route", "clients", "per_s", "p50_ms", "p99_ms", "noop_p50_ms", "noop_p99_ms")
    header = (*columns, "p99_ratio", "errors")
    print("  ".join(f"{h:>11}" for h in header))
    for r in results:
        print("  ".join(f"{r[h]!s:>11}" for h in header))
        if r["first_error"]:
            print(f"  first error: {r['first_error']}")


if __name__ == "__main__":
    main()
