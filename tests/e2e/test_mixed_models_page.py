"""The analysis page's Mixed models section in Chromium: it loads by itself after the page,
draws its figure, and fits another measure when the PI picks one (issue 23)."""

from __future__ import annotations

from pathlib import Path

import pytest
from playwright.sync_api import Browser, expect

from app.db import Database
from app.tables import Role
from bench.seed import seed_study
from tests.conftest import make_user
from tests.e2e.conftest import sign_in_page
from tests.servers import ServerProcess


@pytest.mark.e2e
def test_the_section_loads_draws_and_switches_measure(
    browser: Browser, live_server: ServerProcess, database: Database, artifacts: Path
) -> None:
    seed_study(database, name="mixedpage", participants=24, seed=3)
    make_user(database, "pi", Role.ANALYST)
    context = browser.new_context(viewport={"width": 1366, "height": 900})
    page = context.new_page()
    sign_in_page(page, live_server, "/studies/mixedpage/analysis", username="pi")
    section = page.locator("#mixed-models")
    expect(section.get_by_role("heading", name="Linear mixed model")).to_be_visible()
    expect(section.locator("h2")).to_contain_text("(trust_1)")
    expect(section.locator(".js-plotly-plot .main-svg").first).to_be_visible()
    expect(section).to_contain_text("Satterthwaite df")
    page.screenshot(path=str(artifacts / "mixed-models.png"), full_page=True)

    section.get_by_label("Measure").select_option("trust_3")
    expect(page.locator("#mixed-models h2")).to_contain_text("(trust_3)")
    expect(page.locator("#mixed-models .js-plotly-plot .main-svg").first).to_be_visible()
    slope = page.locator("#mixed-models").get_by_label(
        "also fit a random slope for session and compare"
    )
    # The box sits on its words' line, left of them, not above them (issue 35).
    box, words = slope.evaluate(
        """(box) => {
             const range = document.createRange();
             range.selectNodeContents(box.closest("label"));
             range.setStartAfter(box);
             return [box.getBoundingClientRect(), range.getBoundingClientRect()].map(
               (r) => ({left: r.left, right: r.right, top: r.top, bottom: r.bottom}));
           }"""
    )
    page.locator("#mixed-models form").screenshot(path=str(artifacts / "mixed-choice.png"))
    assert box["right"] <= words["left"], (box, words)
    assert box["top"] < words["bottom"] and words["top"] < box["bottom"], (box, words)
    slope.check()
    expect(page.locator("#mixed-models")).to_contain_text(
        "Letting the session slope vary by participant"
    )
    expect(page.locator("#mixed-models h2")).to_contain_text("(trust_3)")
    context.close()
