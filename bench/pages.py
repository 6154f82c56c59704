"""Every staff page of a 100-participant study, cold and warm, p50/p95 (issue 49).

A trustlab server (a subprocess, as in production, with its default fit processes) serves a
study filled by bots (app/bots.py: enrolled, consented, every session run over the station
WebSocket and every questionnaire filled, meta-learners and all; ``--filler seed`` writes the
same shape of data in bulk with bench/seed.py, in seconds). Each page is fetched over HTTP by a
signed-in admin:

- **cold**: the study's fitted analyses emptied first (``DELETE FROM fitted_analysis``: every
  worker's memory copy is refused with its row), so the page fits what it shows. For a page that
  shows "fitting…" (app/services/analysis_views/fit_runner.py), ``first`` is that answer and
  ``result`` is when a poll (every second, as the page's htmx asks again) gets the result;
- **warm**: the same page asked again ``--warm`` times, after one request of each page that
  fitted what the last cold requests' emptying had removed;
- **restarted**: once after a server restart with the fits kept in the database (a new
  worker's first view).

``--contention`` then measures what a fit costs the server's other requests: the study page is
fetched ``--samples`` times while every measure's mixed models are being fitted (the
``mixed_models.json`` export, cold), with the fits in worker processes (the default) and in a
thread of the server (``TRUSTLAB_ANALYSIS_PROCESSES=0``).

    .venv/bin/python bench/pages.py                      # bots fill 100 participants (minutes)
    .venv/bin/python bench/pages.py --filler seed        # bulk-filled, seconds
    .venv/bin/python bench/pages.py --database /tmp/pages.sqlite3   # keep the filled study
"""

from __future__ import annotations

import argparse
import asyncio
import os
import sys
import tempfile
import threading
import time
from contextlib import closing
from pathlib import Path
from typing import Any

import httpx

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from sqlalchemy import delete, func, select  # noqa: E402

from app import schema  # noqa: E402
from app.bots import BotConfig, run_bots  # noqa: E402
from app.db import Database  # noqa: E402
from app.protocol import default_protocol  # noqa: E402
from app.services import studies  # noqa: E402
from app.services.staff import users  # noqa: E402
from app.tables import FittedAnalysis, Participant, Role, Study  # noqa: E402
from bench.seed import SYSTEM, seed_study  # noqa: E402
from tests.servers import ServerProcess  # noqa: E402

STUDY = "pages"
USER = "bench"
PASSWORD = "benchmark password"
BUSY = 'class="fitting"'
"""What a page shows while its fit runs (templates/_fitting.html)."""

PAGES: dict[str, tuple[str, bool]] = {
    "studies": ("/", False),
    "study overview": ("/studies/{study}", False),
    "participant record": ("/studies/{study}/participants/{code}", False),
    "dashboard page": ("/studies/{study}/dashboard", False),
    "dashboard data": ("/studies/{study}/dashboard.json", False),
    "analysis page": ("/studies/{study}/analysis", False),
    "mixed section": ("/studies/{study}/analysis/mixed", True),
    "mixed, slope": ("/studies/{study}/analysis/mixed?measure=trust_3&slope=true", True),
    "power page": ("/studies/{study}/analysis/power", False),
    "mixed_models.json": ("/studies/{study}/exports/mixed-json", False),
    "report.html": ("/studies/{study}/exports/html", False),
    "wide csv": ("/studies/{study}/exports/wide-csv", False),
    "stations": ("/stations", False),
    "audit log": ("/admin/audit", False),
    "accounts": ("/admin/users", False),
    "new study": ("/admin/studies/new", False),
    "account": ("/account", False),
}
"""Label → (path, asked by htmx as the page asks it)."""


def percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, max(0, round(q * len(ordered)) - 1))]


def fill(database: Database, how: str, participants: int, tmp: Path) -> None:
    """Create the study and its participants (bots through a server, or bulk rows)."""
    with database.writing() as db:
        users.create_user(db, username=USER, role=Role.ADMIN, password=PASSWORD, actor=SYSTEM)
    if how == "seed":
        seed_study(database, name=STUDY, participants=participants, seed=1)
        return
    with database.writing() as db:
        studies.create_study(db, name=STUDY, loaded=default_protocol(), actor=SYSTEM)
    server = ServerProcess(database.url, tmp / "fill", preload=False)
    server.start()
    try:
        config = BotConfig(
            url=server.url,
            study=STUDY,
            participants=participants,
            username=USER,
            password=PASSWORD,
            concurrency=8,
            noise=0.1,
            seed=1,
        )
        began = time.perf_counter()
        summary = asyncio.run(run_bots(config))
        print(
            f"bots: {summary.completed}/{summary.participants} completed, {summary.steps} steps, "
            f"{len(summary.errors)} errors, {time.perf_counter() - began:.0f} s"
        )
    finally:
        server.stop()


def forget_fits(database: Database) -> None:
    with database.writing() as db:
        db.execute(delete(FittedAnalysis))
        db.commit()


def signed_in(url: str) -> httpx.Client:
    client = httpx.Client(base_url=url, timeout=600)
    answer = client.post("/api/v1/session", json={"username": USER, "password": PASSWORD})
    if answer.status_code != 200:
        raise RuntimeError(f"sign-in: {answer.status_code} {answer.text}")
    client.headers["X-CSRF-Token"] = answer.json()["csrf_token"]
    return client


def fetch(client: httpx.Client, path: str, htmx: bool) -> tuple[float, str]:
    headers = {"HX-Request": "true"} if htmx else {}
    began = time.perf_counter()
    answer = client.get(path, headers=headers)
    seconds = time.perf_counter() - began
    if answer.status_code != 200:
        raise RuntimeError(f"{path}: {answer.status_code} {answer.text[:300]}")
    return seconds, answer.text


def until_result(client: httpx.Client, path: str, htmx: bool) -> tuple[float, float]:
    """Seconds to the first answer, and to the answer with the result (polling)."""
    began = time.perf_counter()
    first, text = fetch(client, path, htmx)
    while BUSY in text:
        time.sleep(1.0)  # as the page polls (templates/_fitting.html)
        _, text = fetch(client, path, True)
    return first, time.perf_counter() - began


def measure(url: str, database: Database, code: str, warm: int, cold: int) -> dict[str, Any]:
    paths = {label: (p.format(study=STUDY, code=code), h) for label, (p, h) in PAGES.items()}
    figures: dict[str, Any] = {
        label: {"cold_first": [], "cold_result": [], "warm": []} for label in PAGES
    }
    with closing(signed_in(url)) as client:
        for _ in range(cold):
            for label, (path, htmx) in paths.items():
                forget_fits(database)
                first, result = until_result(client, path, htmx)
                figures[label]["cold_first"].append(first)
                figures[label]["cold_result"].append(result)
        for path, htmx in paths.values():  # the cold requests' fits were emptied after them
            until_result(client, path, htmx)
        for _ in range(warm):
            for label, (path, htmx) in paths.items():
                figures[label]["warm"].append(fetch(client, path, htmx)[0])
    return figures


def contention(database: Database, tmp: Path, samples: int) -> dict[str, list[float]]:
    """The study page's times while every measure's mixed models are fitted, per fit mode."""
    found: dict[str, list[float]] = {}
    for mode, processes in (("worker processes", "2"), ("server thread", "0")):
        forget_fits(database)
        server = ServerProcess(
            database.url,
            tmp / mode.replace(" ", "-"),
            extra_env={"TRUSTLAB_ANALYSIS_PROCESSES": processes},
            preload=False,
        )
        server.start()
        try:
            with closing(signed_in(server.url)) as client, closing(signed_in(server.url)) as other:
                fetch(client, f"/studies/{STUDY}", False)
                fetch(other, f"/studies/{STUDY}/analysis", False)  # the ANOVAs: fitted first
                done = threading.Event()

                def export(other: httpx.Client = other, done: threading.Event = done) -> None:
                    fetch(other, f"/studies/{STUDY}/exports/mixed-json", False)
                    done.set()

                worker = threading.Thread(target=export)
                worker.start()
                times: list[float] = []
                while not done.is_set() and len(times) < samples:
                    times.append(fetch(client, f"/studies/{STUDY}", False)[0])
                worker.join()
                found[mode] = times
        finally:
            server.stop()
    return found


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--participants", type=int, default=100)
    parser.add_argument("--filler", choices=("bots", "seed"), default="bots")
    parser.add_argument("--warm", type=int, default=20, help="warm requests per page")
    parser.add_argument("--cold", type=int, default=3, help="cold requests per page")
    parser.add_argument("--database", type=Path, help="SQLite file to keep the filled study in")
    parser.add_argument("--contention", action="store_true")
    parser.add_argument("--samples", type=int, default=40)
    args = parser.parse_args()
    load_before = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as scratch:
        tmp = Path(scratch)
        path = args.database or tmp / "pages.sqlite3"
        url = f"sqlite:///{path}"
        filled = path.exists()
        database = Database(url)
        schema.upgrade(database)
        if not filled:
            fill(database, args.filler, args.participants, tmp)
        with database.read_session() as db:
            study_id = db.scalar(select(Study.id).where(Study.name == STUDY))
            code = db.scalar(
                select(Participant.code).where(Participant.study_id == study_id).limit(1)
            )
            count = db.scalar(
                select(func.count())
                .select_from(Participant)
                .where(Participant.study_id == study_id)
            )
        server = ServerProcess(url, tmp / "var", preload=False)
        server.start()
        try:
            figures = measure(server.url, database, str(code), args.warm, args.cold)
        finally:
            server.stop()
        server = ServerProcess(url, tmp / "var2", preload=False)  # fits kept in the database
        server.start()
        try:
            with closing(signed_in(server.url)) as client:
                for label, (page, htmx) in PAGES.items():
                    figures[label]["restarted"] = fetch(
                        client, page.format(study=STUDY, code=code), htmx
                    )[0]
        finally:
            server.stop()
        crowded = contention(database, tmp, args.samples) if args.contention else {}
        database.dispose()
    print(
        f"{count} participants ({args.filler}), {os.cpu_count()} cores, load average "
        f"{load_before:.2f} before, {os.getloadavg()[0]:.2f} after; seconds"
    )
    print(
        f"{'page':<20} {'cold first':>10} {'cold result':>11} {'restarted':>9} "
        f"{'warm p50':>8} {'warm p95':>8}"
    )
    for label, row in figures.items():
        print(
            f"{label:<20} {max(row['cold_first']):>10.3f} {max(row['cold_result']):>11.3f} "
            f"{row['restarted']:>9.3f} {percentile(row['warm'], 0.5):>8.3f} "
            f"{percentile(row['warm'], 0.95):>8.3f}"
        )
    print("(cold: the slowest of the cold requests; result: until the page shows the result)")
    for mode, times in crowded.items():
        print(
            f"study overview while the mixed models are fitted, fits in {mode}: "
            f"{len(times)} requests, p50 {percentile(times, 0.5):.3f} s, "
            f"p95 {percentile(times, 0.95):.3f} s"
        )


if __name__ == "__main__":
    main()
