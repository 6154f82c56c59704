"""Issue 21, defect 10: a second visit to the dashboard draws its charts without asking the
server for a single static file (versioned URLs, immutable; app/web/assets.py). The figures for
how long that takes are bench/page_load.py's; this pins the behaviour they rest on."""

from __future__ import annotations

import pytest
from playwright.sync_api import Browser, Page

from app.db import Database
from app.tables import Role
from tests.conftest import make_user
from tests.e2e.conftest import sign_in_page
from tests.servers import ServerProcess

STATIC_ENTRIES = """() => performance.getEntriesByType("resource")
  .filter((entry) => new URL(entry.name).pathname.startsWith("/static/"))
  .map((entry) => ({ path: new URL(entry.name).pathname, transferred: entry.transferSize }))"""


def _open_dashboard(page: Page, server: ServerProcess, study: str) -> list[dict[str, object]]:
    page.goto(f"{server.url}/studies/{study}/dashboard")
    page.wait_for_selector("#dashboard[data-drawn]", state="attached")
    drawn = page.evaluate("() => performance.getEntriesByName('trustlab:dashboard-drawn').length")
    assert drawn == 1, "the first draw sets one performance mark"
    entries: list[dict[str, object]] = page.evaluate(STATIC_ENTRIES)
    return entries


@pytest.mark.e2e
def test_a_second_visit_fetches_no_static_file(
    browser: Browser, live_server: ServerProcess, database: Database, exp3_study: str
) -> None:
    make_user(database, "operator", Role.ADMIN)
    context = browser.new_context(viewport={"width": 1366, "height": 900})
    page = context.new_page()
    sign_in_page(page, live_server, f"/studies/{exp3_study}")

    first = _open_dashboard(page, live_server, exp3_study)
    paths = {str(entry["path"]) for entry in first}
    assert "/static/vendor/plotly-cartesian.min.js" in paths
    assert any(int(str(entry["transferred"])) > 0 for entry in first), "the first visit fetches"

    again = _open_dashboard(page, live_server, exp3_study)
    assert {str(entry["path"]) for entry in again} == paths
    fetched = [entry for entry in again if int(str(entry["transferred"])) > 0]
    assert fetched == [], f"served again by the server instead of the cache: {fetched}"
    context.close()
