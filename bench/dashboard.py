"""Server time to render the live study dashboard with 24 and 1,000 participants.

For each size: a study is generated (bench/seed.py), then the dashboard page and its data
(``dashboard.json``: every trust measure's mean ± CI by session and the adaptation curves) are
requested in-process through the ASGI app, so the figure is the server's time, not the network's.
The study overview page (the participants table) is measured too. Targets: p95 ≤ 100 ms at 24
participants and ≤ 500 ms at 1,000, on SQLite and PostgreSQL.

Besides wall-clock percentiles, each request's CPU time (this process, all threads) is reported as
a median: on a shared machine it moves far less with the neighbours' load than the wall clock, so
it is the figure to compare versions by (run both in the same sitting).

    .venv/bin/python bench/dashboard.py
    .venv/bin/python bench/dashboard.py --postgres postgresql+psycopg://postgres@127.0.0.1:5432/test
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
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
from app.services import users  # noqa: E402
from app.services.freshness import FreshnessCache  # noqa: E402
from app.settings import Settings  # noqa: E402
from app.tables import Role  # noqa: E402
from bench.api import fresh_postgres  # noqa: E402
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--postgres", help="maintenance URL; benchmarks PostgreSQL instead")
    parser.add_argument("--sizes", default="24,1000")
    parser.add_argument("--repeats", type=int, default=40)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    report: dict[int, dict[str, object]] = {}
    load_before = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        url = fresh_postgres(args.postgres) if args.postgres else f"sqlite:///{tmp}/d.sqlite3"
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
            if isinstance(figures, dict):
                print(
                    f"{size:>6} participants  {label:<15} p50 {figures['p50_ms']:>7} ms  "
                    f"p95 {figures['p95_ms']:>7} ms  CPU p50 {figures['cpu_p50_ms']:>7} ms  "
                    f"{figures['bytes']:>8} bytes"
                )


if __name__ == "__main__":
    main()
