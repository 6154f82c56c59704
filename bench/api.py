"""Answer→reply round trip under 1, 10 and 100 concurrent robot clients, next to a no-op endpoint.

Each client is a robot at its own station with its own participant, looping prompt → answer as
fast as the server lets it (a closed loop, no think time); the baseline clients loop on
``GET /api/v1/ping``, which touches nothing, in the same run, at the same concurrency, with the
same client code and the same headers (the device key is sent, and ignored). Baseline and robot
phases alternate (``--rounds``), so a background load that drifts during the run weighs on both
alike. Reported per concurrency: answers per second, p50/p99 of the answer round trip and of the
baseline, and their p99 ratio (target ≤ 3).

    .venv/bin/python bench/api.py                       # SQLite
    .venv/bin/python bench/api.py --postgres postgresql+psycopg://postgres@127.0.0.1:5432/test
    .venv/bin/python bench/api.py --seconds 5 --clients 1,10

Uses the shipped protocol with a longer schedule (50 sessions × 50 runs, no questionnaire gates),
so no client runs out of steps; between sessions the client starts the next one (not timed).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import statistics
import sys
import tempfile
import time
import uuid
from collections.abc import Awaitable, Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import psycopg
import uvloop
from sqlalchemy.engine import make_url

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from app import schema  # noqa: E402
from app.db import Database  # noqa: E402
from app.protocol import default_protocol, parse_protocol  # noqa: E402
from app.services import studies  # noqa: E402
from app.services.audit import Actor  # noqa: E402
from app.services.participants import enrolment, questionnaires  # noqa: E402
from app.services.sessions import stations  # noqa: E402
from app.services.staff import users  # noqa: E402
from app.tables import Role  # noqa: E402
from bench.rawhttp import RawHttp  # noqa: E402
from tests.servers import ServerProcess  # noqa: E402

PASSWORD = "benchmark password"
SYSTEM = Actor.system("bench")


def bench_protocol(exp3_only: bool) -> str:
    """The shipped protocol with room for thousands of answers per participant."""
    text = default_protocol().source_text
    if exp3_only:
        text = text.replace('learner = "meta"', 'learner = "exp3"')
    for old, new in {
        "sessions = 4": "sessions = 50",
        "runs_per_session = 3": "runs_per_session = 50",
        "familiarisation_run = true": "familiarisation_run = false",
        "questionnaire_gates_next_session = true": "questionnaire_gates_next_session = false",
    }.items():
        text = text.replace(old, new)
    return text


def prepare(database_url: str, clients: int, exp3_only: bool) -> list[str]:
    """Migrate, create the study, stations, keys and seated, consenting participants."""
    database = Database(database_url)
    schema.upgrade(database)
    with database.writing() as db:
        users.create_user(db, username="bench", role=Role.ADMIN, password=PASSWORD, actor=SYSTEM)
    with database.writing() as db:
        studies.create_study(
            db, name="bench", loaded=parse_protocol(bench_protocol(exp3_only)), actor=SYSTEM
        )
    keys = []
    for number in range(clients):
        name = f"bench-{number}"
        with database.writing() as db:
            stations.create_station(db, name=name, actor=SYSTEM)
        with database.writing() as db:
            keys.append(
                stations.issue_device_key(db, station_name=name, label="bench", actor=SYSTEM).key
            )
        with database.writing() as db:
            participant = enrolment.enroll_participant(db, study_name="bench", actor=SYSTEM)
        with database.writing() as db:
            seated = db.merge(participant.participant)
            stations.assign_participant(db, station_name=name, participant=seated, actor=SYSTEM)
        with database.writing() as db:
            seated = db.merge(participant.participant)
            protocol = studies.protocol_of(studies.get_study(db, "bench"))
            questionnaires.accept_consent(
                db, participant=seated, protocol=protocol, accepted=True, actor=SYSTEM
            )
    database.dispose()
    return keys


@dataclass
class Samples:
    """Latencies in seconds and failures."""

    answer: list[float] = field(default_factory=list)
    prompt: list[float] = field(default_factory=list)
    ping: list[float] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)


async def robot_loop(
    base: str, key: str, station: str, experimenter: RawHttp, deadline: float, samples: Samples
) -> None:
    robot = RawHttp(base, {"Authorization": f"Bearer {key}"})
    try:
        _, state = await robot.request("GET", "/api/v1/station")
        expected = state["expected"]
        while time.perf_counter() < deadline:
            if expected["action"] == "start_session":
                status, started = await experimenter.request(
                    "POST", f"/api/v1/stations/{station}/sessions", {}
                )
                if status != 201:
                    samples.errors.append(f"start session: {status} {started}")
                    return
                expected = started["expected"]
                continue
            if expected["action"] != "prompt":
                samples.errors.append(f"unexpected: {expected}")
                return
            t0 = time.perf_counter()
            status, step = await robot.request(
                "POST", "/api/v1/station/prompts", {"category": expected["categories"][0]}
            )
            t1 = time.perf_counter()
            if status not in (200, 201):
                samples.errors.append(f"prompt: {status} {step}")
                return
            status, reply = await robot.request(
                "POST",
                f"/api/v1/station/steps/{step['step_id']}/answer",
                {
                    "answer": "yes" if step["action"] == 0 else "no",
                    "idempotency_key": uuid.uuid4().hex,
                },
            )
            t2 = time.perf_counter()
            if status != 200:
                samples.errors.append(f"answer: {status} {reply}")
                return
            samples.prompt.append(t1 - t0)
            samples.answer.append(t2 - t1)
            expected = reply["expected"]
    finally:
        await robot.close()


async def ping_loop(base: str, key: str, deadline: float, samples: Samples) -> None:
    client = RawHttp(base, {"Authorization": f"Bearer {key}"})
    try:
        while time.perf_counter() < deadline:
            t0 = time.perf_counter()
            status, _ = await client.request("GET", "/api/v1/ping")
            samples.ping.append(time.perf_counter() - t0)
            if status != 200:
                samples.errors.append(f"ping: {status}")
    finally:
        await client.close()


def percentile(values: list[float], q: float) -> float:
    """The q-quantile in milliseconds (nearest rank)."""
    if not values:
        return float("nan")
    ordered = sorted(values)
    return 1000.0 * ordered[min(len(ordered) - 1, max(0, round(q * len(ordered)) - 1))]


async def alternate(
    base: str,
    keys: list[str],
    seconds: float,
    rounds: int,
    samples: Samples,
    work: Callable[[int, float], Awaitable[None]],
) -> None:
    """Baseline and the measured loop (``work(client, deadline)``) alternate ``rounds`` times,
    each alone and with one client per key: a background load that drifts weighs on both, and
    the baseline gets half the measured loop's time in total."""
    for _ in range(rounds):
        deadline = time.perf_counter() + seconds / rounds / 2
        await asyncio.gather(*(ping_loop(base, key, deadline, samples) for key in keys))
        deadline = time.perf_counter() + seconds / rounds
        await asyncio.gather(*(work(i, deadline) for i in range(len(keys))))


async def sign_in(base: str) -> dict[str, str]:
    """The benchmark administrator's login: the headers an experimenter's requests carry."""
    login = RawHttp(base)
    status, signed = await login.request(
        "POST", "/api/v1/session", {"username": "bench", "password": PASSWORD}
    )
    await login.close()
    if status != 200:
        raise SystemExit(f"error: could not sign in to the benchmark server: {status} {signed}")
    return {"Cookie": login.headers["Cookie"], "X-CSRF-Token": signed["csrf_token"]}


async def measure(
    base: str, keys: list[str], clients: int, seconds: float, rounds: int
) -> dict[str, object]:
    samples = Samples()
    credentials = await sign_in(base)
    experimenters = [RawHttp(base, credentials) for _ in range(clients)]
    await alternate(
        base,
        keys[:clients],
        seconds,
        rounds,
        samples,
        lambda i, deadline: robot_loop(
            base, keys[i], f"bench-{i}", experimenters[i], deadline, samples
        ),
    )
    for experimenter in experimenters:
        await experimenter.close()
    answer_p99, ping_p99 = percentile(samples.answer, 0.99), percentile(samples.ping, 0.99)
    return {
        "clients": clients,
        "answers": len(samples.answer),
        "answers_per_s": round(len(samples.answer) / seconds, 1),
        "answer_p50_ms": round(percentile(samples.answer, 0.50), 2),
        "answer_p99_ms": round(answer_p99, 2),
        "prompt_p50_ms": round(percentile(samples.prompt, 0.50), 2),
        "prompt_p99_ms": round(percentile(samples.prompt, 0.99), 2),
        "noop_p50_ms": round(percentile(samples.ping, 0.50), 2),
        "noop_p99_ms": round(ping_p99, 2),
        "p99_ratio": round(answer_p99 / ping_p99, 2) if ping_p99 else None,
        "errors": len(samples.errors),
        "first_error": samples.errors[0] if samples.errors else None,
        "server_mean_ms": round(statistics.fmean(samples.answer) * 1000, 2)
        if samples.answer
        else None,
    }


@contextmanager
def bench_database(postgres: str | None, directory: str, name: str) -> Iterator[str]:
    """A fresh, empty database for one benchmark run, and its URL: a SQLite file ``name`` in
    ``directory``, or, given PostgreSQL's maintenance URL, a new database on that server that
    is dropped again when the run ends (also when it fails)."""
    if not postgres:
        yield f"sqlite:///{directory}/{name}.sqlite3"
        return
    database = f"bench_{uuid.uuid4().hex[:10]}"
    conninfo = make_url(postgres).set(drivername="postgresql").render_as_string(False)
    with psycopg.connect(conninfo, autocommit=True) as conn:
        conn.execute(f'CREATE DATABASE "{database}"')
    try:
        yield make_url(postgres).set(database=database).render_as_string(hide_password=False)
    finally:
        with psycopg.connect(conninfo, autocommit=True) as conn:
            conn.execute(f'DROP DATABASE IF EXISTS "{database}" WITH (FORCE)')


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--postgres", help="maintenance URL; benchmarks PostgreSQL instead")
    parser.add_argument("--workers", type=int, default=1, help="uvicorn workers (PostgreSQL)")
    parser.add_argument("--clients", default="1,10,100", help="concurrency levels")
    parser.add_argument("--seconds", type=float, default=10.0, help="robot time per level")
    parser.add_argument(
        "--rounds", type=int, default=4, help="alternations of baseline and robots per level"
    )
    parser.add_argument(
        "--exp3-only",
        action="store_true",
        help="give both conditions Exp3 (isolates the meta-policy's cost)",
    )
    parser.add_argument(
        "--sqlite-synchronous",
        help="the server's PRAGMA synchronous (TRUSTLAB_SQLITE_SYNCHRONOUS); default: its setting",
    )
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    args = parser.parse_args()
    levels = [int(c) for c in args.clients.split(",")]
    load_before = os.getloadavg()[0]
    with (
        tempfile.TemporaryDirectory() as tmp,
        bench_database(args.postgres, tmp, "bench") as url,
    ):
        keys = prepare(url, max(levels), args.exp3_only)
        env = (
            {"TRUSTLAB_SQLITE_SYNCHRONOUS": args.sqlite_synchronous}
            if args.sqlite_synchronous
            else None
        )
        server = ServerProcess(url, Path(tmp) / "var", workers=args.workers, extra_env=env)
        server.start()
        try:
            results = [
                uvloop.run(measure(server.url, keys, c, args.seconds, args.rounds)) for c in levels
            ]
        finally:
            server.stop()
    engine = "postgresql" if args.postgres else "sqlite"
    # The machine's 1-minute load average before and after: latency percentiles mean little
    # when other processes compete for the cores, so every result says how busy it was.
    load = {"before": round(load_before, 2), "after": round(os.getloadavg()[0], 2)}
    if args.json:
        summary = {"engine": engine, "workers": args.workers, "levels": results}
        print(json.dumps({**summary, "sqlite_synchronous": args.sqlite_synchronous, "load": load}))
        return
    synchronous = f" synchronous={args.sqlite_synchronous}" if args.sqlite_synchronous else ""
    print(
        f"engine={engine}{synchronous} workers={args.workers} seconds={args.seconds} "
        f"rounds={args.rounds} load average {load['before']} -> {load['after']} "
        f"on {os.cpu_count()} cores"
    )
    header = (
        "clients",
        "answers/s",
        "answer p50",
        "answer p99",
        "no-op p50",
        "no-op p99",
        "p99 ratio",
        "errors",
        "prompt p50",
        "prompt p99",
    )
    print("  ".join(f"{h:>10}" for h in header))
    for r in results:
        print(
            "  ".join(
                f"{v:>10}"
                for v in (
                    r["clients"],
                    r["answers_per_s"],
                    r["answer_p50_ms"],
                    r["answer_p99_ms"],
                    r["noop_p50_ms"],
                    r["noop_p99_ms"],
                    r["p99_ratio"],
                    r["errors"],
                    r["prompt_p50_ms"],
                    r["prompt_p99_ms"],
                )
            )
        )
        if r["first_error"]:
            print(f"  first error: {r['first_error']}")


if __name__ == "__main__":
    main()
