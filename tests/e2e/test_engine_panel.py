"""The dashboard's engine panel in real Chromium: a study whose C2 was trained for a pilot's
population shows where the meta-policy starts, at a laptop's and a tablet's width."""

from __future__ import annotations

from pathlib import Path

import pytest
from playwright.sync_api import Browser, expect

from app.db import Database
from app.tables import Role
from tests.app.test_population_use import QUESTIONS, _checkpoints, _create, _population, _protocol
from tests.conftest import PASSWORD, make_user
from tests.servers import ServerProcess


@pytest.mark.e2e
def test_the_engine_panel_shows_the_pilots_prior(
    browser: Browser,
    live_server: ServerProcess,
    database: Database,
    tmp_path: Path,
    artifacts: Path,
) -> None:
    file = tmp_path / "pilot.population.json"
    population = _population(file)
    _create(database, "main", _protocol(file, _checkpoints(tmp_path / "set", population)))
    make_user(database, "pi", Role.ADMIN)
    for width, height in ((1366, 900), (768, 1024)):
        context = browser.new_context(viewport={"width": width, "height": height})
        page = context.new_page()
        page.goto(f"{live_server.url}/login?next=/studies/main/dashboard")
        page.get_by_label("Username").fill("pi")
        page.get_by_label("Password").fill(PASSWORD)
        page.get_by_role("button", name="Sign in").click()
        panel = page.locator("#engine")
        expect(panel).to_contain_text("Meta-trained on the prior of pilot")
        expect(panel).to_contain_text(QUESTIONS["cognition"][3])
        expect(panel).to_contain_text(f"population {population.sha256[:12]}")
        box = panel.bounding_box()
        assert box is not None and box["x"] + box["width"] <= width  # nothing cut at the edge
        panel.scroll_into_view_if_needed()
        page.screenshot(path=str(artifacts / f"engine-panel-{width}.png"), full_page=True)
        context.close()
