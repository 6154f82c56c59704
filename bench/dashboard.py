"""Server time to render the live study dashboard with 24 and 1,000 participants.

For each size: a study is generated (bench/seed.py), then the dashboard page and its data
(``dashboard.json``: every trust measure's mean ± CI by session and the adaptation curves) are
requested in-process through the ASGI app, so the figure is the server's time, not the network's.
The study overview page (the participants table) is measured too. Targets: p95 ≤ 100 ms at 24
participants and ≤ 500 ms at 1,000, on SQLite and PostgreSQL.

Besides wall-clock percentiles, each request's CPU time (this process, all threads) is reported as
a median: on a shared machine it moves far less with the neighbours' load than the wall clock, so
it is the figure to compare versions by (run both in the same sitting).

``--live SECONDS`` then watches each study as a busy lab would, with the sharing the app ships:
``--dashboards`` dashboards each refetch the data 300 ms after their previous fetch while the
study's change count rises ``--changes`` times a second (counted changes only, as
bench/load.py's ~65 answers and ~65 prompts a second would; the data itself stays put). It
reports how many computations the requests cost and the process's CPU seconds per second.

    .venv/bin/python bench/dashboard.py
    .venv/bin/python bench/dashboard.py --postgres postgresql+psycopg://postgres@127.0.0.1:5432/test
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import random
import sys
import tempfile
import time
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from app import schema  # noqa: E402
from app.db import Database  # noqa: E402
from app.main import create_app  # noqa: E402
from app.services import studies, topics  # noqa: E402
from app.services.analysis_views.freshness import FreshnessCache  # noqa: E402
from app.services.staff import users  # noqa: E402
from app.settings import Settings  # noqa: E402
from app.tables import Role  # noqa: E402
from bench.api import bench_database  # noqa: E402
from bench.seed import SYSTEM, seed_study  # noqa: E402

PASSWORD = "benchmark password"
PAGES = {
    "dashboard page": "/studies/{study}/dashboard",
    "dashboard data": "/studies/{study}/dashboard.json",
    "overview page": "/studies/{study}",
}


def percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return 1000.0 * ordered[min(len(ordered) - 1, max(0, round(q * len(ordered)) - 1))]


async def measure(url: str, study: str, repeats: int) -> dict[str, dict[str, float]]:
    app = create_app(Settings(_env_file=None, database_url=url, secret_key="b" * 40))
    # Measure the computation itself, not a result shared between dashboards (app/main.py).
    app.state.dashboard_data = FreshnessCache(max_age=0.0)
    results: dict[str, dict[str, float]] = {}
    async with app.router.lifespan_context(app):
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://bench") as client:
            signed = await client.post(
                "/api/v1/session", json={"username": "bench", "password": PASSWORD}
            )
            assert signed.status_code == 200, signed.text
            for label, path in PAGES.items():
                target = path.format(study=study)
                await client.get(target)  # warm caches, as a dashboard left open would be
                times, cpu = [], []
                for _ in range(repeats):
                    start, start_cpu = time.perf_counter(), time.process_time()
                    response = await client.get(target)
                    times.append(time.perf_counter() - start)
                    cpu.append(time.process_time() - start_cpu)
                    assert response.status_code == 200, (target, response.status_code)
                results[label] = {
                    "p50_ms": round(percentile(times, 0.5), 1),
                    "p95_ms": round(percentile(times, 0.95), 1),
                    "cpu_p50_ms": round(percentile(cpu, 0.5), 1),
                    "bytes": len(response.content),
                }
    return results


async def live(
    url: str,
    study: str,
    seconds: float,
    dashboards: int,
    changes: float,
    min_interval: float | None,
) -> dict[str, float]:
    """Dashboards refetching while the study's change count rises, with the app's own sharing
    (or another minimum interval between computations)."""
    app = create_app(Settings(_env_file=None, database_url=url, secret_key="b" * 40))
    shared: FreshnessCache[bytes] = app.state.dashboard_data
    if min_interval is not None:
        shared = FreshnessCache(max_age=shared.max_age, min_interval=min_interval)
        app.state.dashboard_data = shared
    rng = random.Random(1)
    times: list[float] = []
    counted = 0
    async with app.router.lifespan_context(app):
        with app.state.database.read_session() as db:
            topic = topics.study_topic(studies.get_study(db, study).id)
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://bench") as client:
            signed = await client.post(
                "/api/v1/session", json={"username": "bench", "password": PASSWORD}
            )
            assert signed.status_code == 200, signed.text
            target = f"/studies/{study}/dashboard.json"
            await client.get(target)
            deadline = time.perf_counter() + seconds

            async def change() -> None:
                nonlocal counted
                while time.perf_counter() < deadline:
                    app.state.database.hub.note_changes([topic])
                    counted += 1
                    await asyncio.sleep(1.0 / changes)

            async def dashboard() -> None:
                await asyncio.sleep(rng.uniform(0.0, 0.3))  # dashboards opened at any moment
                while time.perf_counter() < deadline:
                    await asyncio.sleep(0.3)
                    start = time.perf_counter()
                    response = await client.get(target)
                    times.append(time.perf_counter() - start)
                    assert response.status_code == 200, response.status_code

            computed, cpu, wall = shared.computed, time.process_time(), time.perf_counter()
            await asyncio.gather(change(), *(dashboard() for _ in range(dashboards)))
            wall = time.perf_counter() - wall
            cpu = time.process_time() - cpu
            computed = shared.computed - computed
    return {
        "changes_per_s": round(counted / wall, 1),
        "requests": len(times),
        "computations": computed,
        "computations_per_s": round(computed / wall, 2),
        "p50_ms": round(percentile(times, 0.5), 1),
        "p99_ms": round(percentile(times, 0.99), 1),
        "cpu_s_per_s": round(cpu / wall, 3),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--postgres", help="maintenance URL; benchmarks PostgreSQL instead")
    parser.add_argument("--sizes", default="24,1000")
    parser.add_argument("--repeats", type=int, default=40)
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--live", type=float, default=0.0, metavar="SECONDS")
    parser.add_argument("--dashboards", type=int, default=5)
    parser.add_argument("--changes", type=float, default=130.0, metavar="PER_SECOND")
    parser.add_argument("--min-interval", type=float, help="instead of the app's (seconds)")
    args = parser.parse_args()
    report: dict[int, dict[str, object]] = {}
    load_before = os.getloadavg()[0]
    with (
        tempfile.TemporaryDirectory() as tmp,
        bench_database(args.postgres, tmp, "d") as url,
    ):
        database = Database(url)
        schema.upgrade(database)
        with database.writing() as db:
            users.create_user(
                db, username="bench", role=Role.ANALYST, password=PASSWORD, actor=SYSTEM
            )
        for size in (int(s) for s in args.sizes.split(",")):
            started = time.perf_counter()
            seed_study(database, name=f"s{size}", participants=size, seed=size)
            seeded = time.perf_counter() - started
            report[size] = {
                **asyncio.run(measure(url, f"s{size}", args.repeats)),
                "seeded_s": round(seeded, 1),
            }
            if args.live:
                report[size]["live"] = asyncio.run(
                    live(
                        url, f"s{size}", args.live, args.dashboards, args.changes, args.min_interval
                    )
                )
        database.dispose()
    engine = "postgresql" if args.postgres else "sqlite"
    load = {"before": round(load_before, 2), "after": round(os.getloadavg()[0], 2)}
    if args.json:
        summary = {"engine": engine, "cores": os.cpu_count(), "load": load, "sizes": report}
        print(json.dumps(summary))
        return
    print(
        f"engine={engine} repeats={args.repeats} cores={os.cpu_count()} "
        f"load average {load['before']} before, {load['after']} after"
    )
    for size, pages in report.items():
        for label, figures in pages.items():
            if label == "live" and isinstance(figures, dict):
                print(
                    f"{size:>6} participants  live: {args.dashboards} dashboards, "
                    f"{figures['changes_per_s']} changes/s for {args.live:g} s: "
                    f"{figures['requests']} requests, {figures['computations']} computations "
                    f"({figures['computations_per_s']}/s), data p50 {figures['p50_ms']} ms "
                    f"p99 {figures['p99_ms']} ms, CPU {figures['cpu_s_per_s']} s/s"
                )
            elif isinstance(figures, dict):
                print(
                    f"{size:>6} participants  {label:<15} p50 {figures['p50_ms']:>7} ms  "
                    f"p95 {figures['p95_ms']:>7} ms  CPU p50 {figures['cpu_p50_ms']:>7} ms  "
                    f"{figures['bytes']:>8} bytes"
                )


if __name__ == "__main__":
    main()
