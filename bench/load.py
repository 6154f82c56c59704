"""A whole lab at once: 200 robots, 24 tablets and 5 live dashboards against one server for 60 s.

- Each **robot** is a station with its own seated participant. It is paced like a person talking
  to a robot: it asks (prompt), the participant thinks for ``--think`` seconds (uniform between
  half and one and a half times it), the robot posts the answer, then asks the next question.
  Between sessions its experimenter starts the next one.
- Each **tablet** belongs to one of those participants and polls its page every 2 s, as a tablet
  left on the wait screen does, filling each questionnaire the server shows (the trust
  questionnaire after every session).
- Each **dashboard** is a signed-in experimenter's browser on the study's live dashboard: it holds
  the server-sent event stream open and, like static/js/dashboard.js, refetches the dashboard data
  300 ms after a change (coalescing the changes in between).

Reported per operation: count, rate, p50/p99 and errors (any unexpected status or failure). Then
``trustlab verify`` runs over the study and must be clean.

    .venv/bin/python -m bench.load                                   # SQLite, 1 worker
    .venv/bin/python -m bench.load --postgres postgresql+psycopg://postgres@127.0.0.1:5432/test
    .venv/bin/python -m bench.load --seconds 10 --robots 20          # a quick look

The study is the shipped protocol with a schedule long enough that nobody finishes at the default
pace (50 sessions of 4 runs, no familiarisation run, questionnaires not gating the next session),
so the load stays the same for the whole run.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import random
import sys
import tempfile
import time
import uuid
from collections import defaultdict
from contextlib import suppress
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import uvloop

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from app import schema  # noqa: E402
from app.bots import ResponseModel, questionnaire_answers  # noqa: E402
from app.db import Database  # noqa: E402
from app.protocol import default_protocol, parse_protocol  # noqa: E402
from app.services import studies  # noqa: E402
from app.services.audit import Actor  # noqa: E402
from app.services.participants import enrolment, questionnaires, tablet_tokens  # noqa: E402
from app.services.sessions import stations, verify  # noqa: E402
from app.services.staff import users  # noqa: E402
from app.tables import Role  # noqa: E402
from bench.api import PASSWORD, bench_database, percentile, sign_in  # noqa: E402
from bench.rawhttp import RawHttp  # noqa: E402
from tests.servers import ServerProcess  # noqa: E402

SYSTEM = Actor.system("bench")
STUDY = "load"
SERVER_SECRET = b"subprocess-test-secret-0123456789abcdef"  # what ServerProcess configures


def load_protocol(exp3_only: bool) -> str:
    """The shipped protocol with a schedule nobody finishes within the run."""
    text = default_protocol().source_text
    if exp3_only:
        text = text.replace('learner = "meta"', 'learner = "exp3"')
    for old, new in {
        "sessions = 4": "sessions = 50",
        "runs_per_session = 3": "runs_per_session = 4",
        "familiarisation_run = true": "familiarisation_run = false",
        "questionnaire_gates_next_session = true": "questionnaire_gates_next_session = false",
    }.items():
        if old not in text:
            raise SystemExit(f"error: the shipped protocol no longer says {old!r}; update bench")
        text = text.replace(old, new)
    return text


@dataclass(frozen=True)
class Lab:
    """Credentials of everything the run drives."""

    robot_keys: list[str]
    tablet_tokens: list[str]
    conditions: list[str]


def prepare(url: str, robots: int, tablets: int, exp3_only: bool) -> Lab:
    """Migrate; create the study, one station + robot key + consenting participant per robot."""
    database = Database(url)
    schema.upgrade(database)
    with database.writing() as db:
        users.create_user(db, username="bench", role=Role.ADMIN, password=PASSWORD, actor=SYSTEM)
    with database.writing() as db:
        studies.create_study(
            db, name=STUDY, loaded=parse_protocol(load_protocol(exp3_only)), actor=SYSTEM
        )
    keys, tokens, conditions = [], [], []
    for number in range(robots):
        name = f"robot-{number:03d}"
        with database.writing() as db:
            stations.create_station(db, name=name, actor=SYSTEM)
        with database.writing() as db:
            keys.append(
                stations.issue_device_key(db, station_name=name, label="bench", actor=SYSTEM).key
            )
        with database.writing() as db:
            enrolled = enrolment.enroll_participant(db, study_name=STUDY, actor=SYSTEM)
            conditions.append(enrolled.condition)
        with database.writing() as db:
            participant = db.merge(enrolled.participant)
            stations.assign_participant(
                db, station_name=name, participant=participant, actor=SYSTEM
            )
        with database.writing() as db:
            participant = db.merge(enrolled.participant)
            protocol = studies.protocol_of(studies.get_study(db, STUDY))
            questionnaires.accept_consent(
                db, participant=participant, protocol=protocol, accepted=True, actor=SYSTEM
            )
        if number < tablets:
            with database.writing() as db:
                participant = db.merge(enrolled.participant)
                tokens.append(
                    tablet_tokens.issue_participant_token(
                        db, participant=participant, secret=SERVER_SECRET, actor=SYSTEM
                    )
                )
    database.dispose()
    return Lab(keys, tokens, conditions)


@dataclass
class Record:
    """Latencies (seconds) per operation, and what went wrong."""

    latencies: dict[str, list[float]] = field(default_factory=lambda: defaultdict(list))
    steady: dict[str, list[float]] = field(default_factory=lambda: defaultdict(list))
    """Latencies of requests sent after the warm-up (every robot connected, first sessions on)."""
    steady_from: float = math.inf
    errors: dict[str, list[str]] = field(default_factory=lambda: defaultdict(list))

    async def timed(
        self,
        operation: str,
        client: RawHttp,
        method: str,
        path: str,
        body: Any = None,
        ok: tuple[int, ...] = (200, 201),
    ) -> tuple[int, Any]:
        started = time.perf_counter()
        try:
            status, payload = await client.request(method, path, body)
        except (OSError, asyncio.IncompleteReadError) as failure:
            self.errors[operation].append(repr(failure))
            return 0, None
        latency = time.perf_counter() - started
        self.latencies[operation].append(latency)
        if started >= self.steady_from:
            self.steady[operation].append(latency)
        if status not in ok:
            self.errors[operation].append(f"{status} {str(payload)[:200]}")
        return status, payload


async def robot(
    base: str,
    key: str,
    station: str,
    staff: dict[str, str],
    think: float,
    deadline: float,
    record: Record,
    rng: random.Random,
) -> None:
    device = RawHttp(base, {"Authorization": f"Bearer {key}"})
    experimenter = RawHttp(base, staff)
    try:
        await asyncio.sleep(rng.uniform(0, think))  # robots do not all start in the same instant
        status, state = await record.timed("station state", device, "GET", "/api/v1/station")
        if status != 200:
            return
        expected = state["expected"]
        while time.perf_counter() < deadline:
            if expected["action"] == "start_session":
                status, started = await record.timed(
                    "start session",
                    experimenter,
                    "POST",
                    f"/api/v1/stations/{station}/sessions",
                    {},
                )
                if status != 201:
                    return
                expected = started["expected"]
                continue
            if expected["action"] != "prompt":
                record.errors["robot"].append(f"unexpected state {expected}")
                return
            status, step = await record.timed(
                "prompt",
                device,
                "POST",
                "/api/v1/station/prompts",
                {"category": rng.choice(expected["categories"])},
            )
            if status not in (200, 201):
                return
            await asyncio.sleep(rng.uniform(0.5 * think, 1.5 * think))
            status, reply = await record.timed(
                "answer",
                device,
                "POST",
                f"/api/v1/station/steps/{step['step_id']}/answer",
                {"answer": rng.choice(["yes", "no"]), "idempotency_key": uuid.uuid4().hex},
            )
            if status != 200:
                return
            expected = reply["expected"]
    finally:
        await device.close()
        await experimenter.close()


async def tablet(
    base: str, token: str, condition: str, deadline: float, record: Record, rng: random.Random
) -> None:
    client = RawHttp(base, {"Authorization": f"Bearer {token}"})
    model = ResponseModel()
    try:
        while time.perf_counter() < deadline:
            status, page = await record.timed("tablet page", client, "GET", "/api/v1/tablet")
            if status == 200 and page["kind"] == "questionnaire":
                await record.timed(
                    "questionnaire",
                    client,
                    "POST",
                    f"/api/v1/tablet/questionnaires/{page['instrument']['key']}",
                    {
                        "session": page["session"],
                        "answers": questionnaire_answers(page, model, condition, rng),
                    },
                )
                continue
            await asyncio.sleep(2.0)
    finally:
        await client.close()


async def dashboard(base: str, staff: dict[str, str], deadline: float, record: Record) -> None:
    """The live dashboard: an SSE stream, and a data refetch 300 ms after each burst of changes."""
    data = RawHttp(base, staff)
    host, port = data.host, data.port
    reader, writer = await asyncio.open_connection(host, port)
    headers = "".join(f"{name}: {value}\r\n" for name, value in staff.items())
    writer.write(
        f"GET /studies/{STUDY}/events HTTP/1.1\r\nHost: {host}:{port}\r\n{headers}"
        "Accept: text/event-stream\r\n\r\n".encode()
    )
    changed = asyncio.Event()

    async def listen() -> None:
        head = await reader.readuntil(b"\r\n\r\n")
        if b" 200 " not in head.split(b"\r\n", 1)[0]:
            record.errors["dashboard events"].append(head.split(b"\r\n", 1)[0].decode())
            return
        while True:
            line = await reader.readline()
            if not line:
                record.errors["dashboard events"].append("stream closed by the server")
                return
            if line.startswith(b"event: changed"):
                record.latencies["dashboard events"].append(0.0)
                changed.set()

    listener = asyncio.create_task(listen())
    try:
        await record.timed("dashboard data", data, "GET", f"/studies/{STUDY}/dashboard.json")
        while time.perf_counter() < deadline:
            with suppress(TimeoutError):
                await asyncio.wait_for(changed.wait(), timeout=deadline - time.perf_counter())
            if not changed.is_set():
                break
            await asyncio.sleep(0.3)
            changed.clear()
            await record.timed("dashboard data", data, "GET", f"/studies/{STUDY}/dashboard.json")
    finally:
        listener.cancel()
        with suppress(asyncio.CancelledError):
            await listener
        writer.close()
        await data.close()


async def run(
    base: str, lab: Lab, dashboards: int, think: float, seconds: float, warmup: float
) -> Record:
    record = Record()
    staff = await sign_in(base)
    rng = random.Random(2026)
    began = time.perf_counter()
    deadline = began + seconds
    record.steady_from = began + warmup
    tasks = [
        robot(
            base, key, f"robot-{n:03d}", staff, think, deadline, record, random.Random(rng.random())
        )
        for n, key in enumerate(lab.robot_keys)
    ]
    tasks += [
        tablet(base, token, lab.conditions[n], deadline, record, random.Random(rng.random()))
        for n, token in enumerate(lab.tablet_tokens)
    ]
    tasks += [dashboard(base, staff, deadline, record) for _ in range(dashboards)]
    await asyncio.gather(*tasks)
    return record


def summarise(record: Record, seconds: float) -> list[dict[str, Any]]:
    rows = []
    for operation in sorted(set(record.latencies) | set(record.errors)):
        samples = record.latencies.get(operation, [])
        steady = record.steady.get(operation, [])
        timed = operation != "dashboard events"
        rows.append(
            {
                "operation": operation,
                "count": len(samples),
                "per_s": round(len(samples) / seconds, 1),
                "p50_ms": round(percentile(samples, 0.50), 2) if timed and samples else None,
                "p99_ms": round(percentile(samples, 0.99), 2) if timed and samples else None,
                "steady_count": len(steady),
                "steady_p50_ms": round(percentile(steady, 0.50), 2) if timed and steady else None,
                "steady_p99_ms": round(percentile(steady, 0.99), 2) if timed and steady else None,
                "errors": len(record.errors.get(operation, [])),
                "first_error": next(iter(record.errors.get(operation, [])), None),
            }
        )
    return rows


def verify_clean(url: str) -> dict[str, Any]:
    database = Database(url)
    try:
        with database.read_session() as db:
            report = verify.verify_study(db, study_name=STUDY)
        return {"ok": report.ok, "findings": [str(f) for f in report.findings][:5]}
    finally:
        database.dispose()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--postgres", help="maintenance URL; runs against PostgreSQL instead")
    parser.add_argument("--workers", type=int, help="uvicorn workers (default 1 SQLite, 2 PG)")
    parser.add_argument("--robots", type=int, default=200)
    parser.add_argument("--tablets", type=int, default=24)
    parser.add_argument("--dashboards", type=int, default=5)
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument(
        "--think",
        type=float,
        default=3.0,
        help="mean seconds a participant takes to answer (default 3)",
    )
    parser.add_argument(
        "--warmup",
        type=float,
        default=10.0,
        help="seconds before the steady-state columns start counting (default 10: every robot "
        "has connected and had its first session started)",
    )
    parser.add_argument(
        "--exp3-only",
        action="store_true",
        help="give both conditions Exp3 (isolates the meta-policy's cost)",
    )
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    args = parser.parse_args()
    if not 0 <= args.warmup < args.seconds:
        raise SystemExit("error: --warmup must be at least 0 and shorter than --seconds")
    if args.tablets > args.robots:
        raise SystemExit("error: --tablets cannot exceed --robots (each tablet is a robot's)")
    workers = args.workers or (2 if args.postgres else 1)
    engine = "postgresql" if args.postgres else "sqlite"
    with (
        tempfile.TemporaryDirectory() as tmp,
        bench_database(args.postgres, tmp, "load") as url,
    ):
        print(f"preparing {args.robots} stations on {engine}…", file=sys.stderr)
        lab = prepare(url, args.robots, args.tablets, args.exp3_only)
        server = ServerProcess(url, Path(tmp) / "var", workers=workers)
        server.start()
        print(f"running {args.seconds:.0f} s…", file=sys.stderr)
        try:
            record = uvloop.run(
                run(server.url, lab, args.dashboards, args.think, args.seconds, args.warmup)
            )
        finally:
            server.stop()
        rows = summarise(record, args.seconds)
        checked = verify_clean(url)
    result = {
        "engine": engine,
        "workers": workers,
        "robots": args.robots,
        "tablets": args.tablets,
        "dashboards": args.dashboards,
        "seconds": args.seconds,
        "think_s": args.think,
        "warmup_s": args.warmup,
        "operations": rows,
        "verify": checked,
    }
    if args.json:
        print(json.dumps(result))
        return
    print(
        f"engine={engine} workers={workers} robots={args.robots} tablets={args.tablets} "
        f"dashboards={args.dashboards} seconds={args.seconds:g} think={args.think:g}s "
        f"warmup={args.warmup:g}s"
    )
    print(
        f"{'operation':<18}{'count':>8}{'per s':>8}{'p50 ms':>9}{'p99 ms':>9}{'errors':>8}"
        f"   after warm-up: {'count':>6}{'p50 ms':>9}{'p99 ms':>9}"
    )

    def cell(value: float | None) -> str:
        return "" if value is None else str(value)

    for row in rows:
        print(
            f"{row['operation']:<18}{row['count']:>8}{row['per_s']:>8}{cell(row['p50_ms']):>9}"
            f"{cell(row['p99_ms']):>9}{row['errors']:>8}{'':>18}{row['steady_count']:>6}"
            f"{cell(row['steady_p50_ms']):>9}{cell(row['steady_p99_ms']):>9}"
        )
        if row["first_error"]:
            print(f"  first error: {row['first_error']}")
    print(
        f"trustlab verify: {'clean' if checked['ok'] else 'FINDINGS ' + str(checked['findings'])}"
    )


if __name__ == "__main__":
    main()
