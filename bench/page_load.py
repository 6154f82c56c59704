"""How long the live dashboard takes to become usable in a real browser, cold and warm.

A trustlab server (a subprocess, as in production) serves a study of ``--participants`` completed
participants (bench/seed.py) on SQLite; Debian's headless Chromium, driven by Playwright, signs in
and opens the study's dashboard ``--cold`` times with an empty cache (a new browser context each),
then ``--warm`` times more in the last context (an experimenter's second visit). "Usable" is the
``trustlab:dashboard-drawn`` performance mark that static/js/dashboard.js sets when every chart
of its first draw is drawn: navigation start → charts on screen, including fetching and running
Plotly and fetching dashboard.json. Also reported: the static bytes the warm loads fetched over
the network and how many requests for static files reached the server (``transferSize`` is 0
for a file the browser's cache served without asking, and above 0 for a fetch or a revalidation).

Target (issue 21): warm p95 ≤ 1 s on this machine.

    .venv/bin/python bench/page_load.py
    .venv/bin/python bench/page_load.py --participants 1000 --warm 20
    .venv/bin/python bench/page_load.py --source ../before   # another checkout (git worktree)
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from playwright.sync_api import Page, sync_playwright  # noqa: E402

from app import schema  # noqa: E402
from app.db import Database  # noqa: E402
from app.services.staff import users  # noqa: E402
from app.tables import Role  # noqa: E402
from bench.seed import SYSTEM, seed_study  # noqa: E402
from tests.servers import ServerProcess  # noqa: E402

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking"]
PASSWORD = "benchmark password"
STUDY = "pageload"

TIMINGS = """() => {
  const navigation = performance.getEntriesByType("navigation")[0];
  const drawn = performance.getEntriesByName("trustlab:dashboard-drawn")[0];
  const statics = performance.getEntriesByType("resource")
    .filter((entry) => new URL(entry.name).pathname.startsWith("/static/"));
  return {
    drawn_ms: drawn ? drawn.startTime : null,
    dom_content_loaded_ms: navigation.domContentLoadedEventEnd,
    static_files: statics.length,
    static_bytes_fetched: statics.reduce((sum, entry) => sum + entry.transferSize, 0),
    static_requests: statics.filter((entry) => entry.transferSize > 0).length,
    page_bytes: navigation.transferSize,
  };
}"""


def percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, max(0, round(q * len(ordered)) - 1))]


def load_once(page: Page, url: str) -> dict[str, Any]:
    """Open the dashboard and wait for its first complete draw."""
    page.goto(url)
    page.wait_for_selector("#dashboard[data-drawn]", state="attached", timeout=30_000)
    figures: dict[str, Any] = page.evaluate(TIMINGS)
    if figures["drawn_ms"] is None:
        raise RuntimeError("the dashboard drew but set no performance mark")
    return figures


def measure(
    base_url: str, cold: int, warm: int
) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """``cold`` first loads, each in a new browser context (an empty cache), then ``warm`` loads
    in the last one's context."""
    with sync_playwright() as driver:
        browser = driver.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        url = f"{base_url}/studies/{STUDY}/dashboard"
        first: list[dict[str, Any]] = []
        for _ in range(cold):
            context = browser.new_context(viewport={"width": 1366, "height": 900})
            signed = context.request.post(
                f"{base_url}/api/v1/session", data={"username": "bench", "password": PASSWORD}
            )
            if signed.status != 200:
                raise RuntimeError(f"sign-in failed: {signed.status} {signed.text()}")
            page = context.new_page()
            first.append(load_once(page, url))
        again = [load_once(page, url) for _ in range(warm)]
        browser.close()
    return first, again


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--participants", type=int, default=24)
    parser.add_argument("--cold", type=int, default=5, help="loads with an empty cache")
    parser.add_argument("--warm", type=int, default=30, help="loads with a warm cache")
    parser.add_argument(
        "--source", type=Path, help="serve the trustlab checkout in this directory (a before/after)"
    )
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    if args.cold < 1 or args.warm < 1:
        parser.error("--cold and --warm must each be at least 1")
    if not Path(CHROMIUM).exists():
        sys.exit(f"{CHROMIUM} is missing: apt-get install chromium")
    load_before = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        url = f"sqlite:///{tmp}/pageload.sqlite3"
        database = Database(url)
        schema.upgrade(database)
        with database.writing() as db:
            users.create_user(
                db, username="bench", role=Role.EXPERIMENTER, password=PASSWORD, actor=SYSTEM
            )
        seed_study(database, name=STUDY, participants=args.participants, seed=1)
        database.dispose()
        server = ServerProcess(url, Path(tmp) / "var", source=args.source)
        server.start()
        try:
            cold, warm = measure(server.url, args.cold, args.warm)
        finally:
            server.stop()
    drawn = [r["drawn_ms"] for r in warm]
    first = [r["drawn_ms"] for r in cold]
    summary = {
        "participants": args.participants,
        "cores": os.cpu_count(),
        "load": {"before": round(load_before, 2), "after": round(os.getloadavg()[0], 2)},
        "cold": {
            "loads": len(cold),
            "drawn_p50_ms": round(percentile(first, 0.5), 1),
            "drawn_max_ms": round(max(first), 1),
            "static_files": cold[0]["static_files"],
            "static_bytes_fetched": cold[0]["static_bytes_fetched"],
        },
        "warm": {
            "loads": len(warm),
            "drawn_p50_ms": round(percentile(drawn, 0.5), 1),
            "drawn_p95_ms": round(percentile(drawn, 0.95), 1),
            "dom_content_loaded_p50_ms": round(
                percentile([r["dom_content_loaded_ms"] for r in warm], 0.5), 1
            ),
            "static_bytes_fetched_max": max(r["static_bytes_fetched"] for r in warm),
            "static_requests_max": max(r["static_requests"] for r in warm),
        },
    }
    if args.json:
        print(json.dumps(summary))
        return
    w, c = summary["warm"], summary["cold"]
    print(
        f"{args.participants} participants, {os.cpu_count()} cores, load average "
        f"{summary['load']['before']} before, {summary['load']['after']} after"
    )
    print(
        f"cold ({c['loads']} loads): drawn p50 {c['drawn_p50_ms']} ms, max {c['drawn_max_ms']} ms; "
        f"{c['static_files']} static files, {c['static_bytes_fetched']:,} bytes fetched"
    )
    print(
        f"warm ({w['loads']} loads): drawn p50 {w['drawn_p50_ms']} ms, p95 {w['drawn_p95_ms']} ms; "
        f"DOMContentLoaded p50 {w['dom_content_loaded_p50_ms']} ms; static bytes fetched "
        f"≤ {w['static_bytes_fetched_max']:,}, requests sent ≤ {w['static_requests_max']}"
    )


if __name__ == "__main__":
    main()
