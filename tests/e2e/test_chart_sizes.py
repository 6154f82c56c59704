"""Dashboard charts fit their cards (issue 21, defect 2): on load, after the window is resized and
when measures are toggled, at a laptop's and a tablet's width, on an empty dashboard too."""

from __future__ import annotations

from pathlib import Path

import pytest
from playwright.sync_api import Browser, Page, expect

from app.db import Database
from app.tables import Role
from bench.seed import seed_study
from tests.conftest import make_user
from tests.e2e.conftest import sign_in_page
from tests.servers import ServerProcess


def _overflows(page: Page) -> list[str]:
    """Each chart whose drawn plot reaches past its card (more than a pixel)."""
    return page.evaluate(
        """() => Array.from(document.querySelectorAll('.card .js-plotly-plot')).flatMap((plot) => {
             const card = plot.closest('.card').getBoundingClientRect();
             const svg = plot.querySelector('.main-svg').getBoundingClientRect();
             return svg.right > card.right + 1 || svg.left < card.left - 1
               ? [`${plot.parentElement.dataset.testid || plot.id}: ${svg.width} in ${card.width}`]
               : [];
           })"""
    )


def _settled(page: Page, charts: int) -> None:
    expect(page.locator(".card .js-plotly-plot")).to_have_count(charts)
    # The page resizes plots on the next frames (ResizeObserver): wait for two of them, then for
    # every resize it started to finish (data-resizing back to 0). Events, not a time.
    page.evaluate("() => new Promise((r) => requestAnimationFrame(() => requestAnimationFrame(r)))")
    expect(
        page.locator("#dashboard:not([data-resizing]), #dashboard[data-resizing='0']")
    ).to_have_count(1)


@pytest.mark.e2e
@pytest.mark.parametrize(("width", "height"), [(1366, 900), (768, 1024)])
def test_charts_fit_their_cards(
    browser: Browser,
    live_server: ServerProcess,
    database: Database,
    exp3_study: str,
    artifacts: Path,
    width: int,
    height: int,
) -> None:
    make_user(database, "operator", Role.ANALYST)
    context = browser.new_context(viewport={"width": width, "height": height})
    page = context.new_page()
    sign_in_page(page, live_server, f"/studies/{exp3_study}/dashboard")
    expect(page.locator("#dashboard-status")).to_contain_text("answers learned")
    _settled(page, 3)  # two measures and the adaptation curves
    assert _overflows(page) == []
    page.screenshot(path=str(artifacts / f"dashboard-{width}.png"), full_page=True)
    page.get_by_label("The robot anticipates my needs.").check()
    _settled(page, 4)
    assert _overflows(page) == []
    page.get_by_label("I perceive the robot as trustworthy.").uncheck()
    page.get_by_label("The robot anticipates my needs.").uncheck()
    _settled(page, 2)
    assert _overflows(page) == []
    page.set_viewport_size({"width": width // 2 + 200, "height": height})
    _settled(page, 2)
    assert _overflows(page) == []
    page.set_viewport_size({"width": width, "height": height})
    _settled(page, 2)
    assert _overflows(page) == []
    page.screenshot(path=str(artifacts / f"dashboard-toggled-{width}.png"), full_page=True)
    context.close()


def _legends_on_axis_titles(page: Page) -> list[str]:
    """Each chart whose legend is not wholly below its x-axis titles: beside a title it runs
    into it as soon as the labels are longer (a blinded study's "Group A", "Group B")."""
    return page.evaluate(
        """() => Array.from(document.querySelectorAll('.card .js-plotly-plot')).flatMap((plot) => {
             const legend = plot.querySelector('.legend');
             if (!legend) return [];
             const l = legend.getBoundingClientRect();
             return Array.from(plot.querySelectorAll('.xtitle')).flatMap((title) => {
               const t = title.getBoundingClientRect();
               return l.top >= t.bottom ? [] : [`${plot.parentElement.dataset.testid || plot.id}`];
             });
           })"""
    )


@pytest.mark.e2e
def test_legends_stay_clear_of_the_axis_titles(
    browser: Browser, live_server: ServerProcess, database: Database, artifacts: Path
) -> None:
    """Issue 35 review: the legend, placed as a fraction of the plot area, ran into the x-axis
    title ("Group BSession") on the dashboard's short charts."""
    seed_study(database, name="legends", participants=6, seed=2)
    make_user(database, "operator", Role.ANALYST)
    context = browser.new_context(viewport={"width": 1280, "height": 900})
    page = context.new_page()
    sign_in_page(page, live_server, "/studies/legends/dashboard")
    expect(page.locator("#dashboard-status")).to_contain_text("answers learned")
    _settled(page, 3)
    expect(page.locator(".card .js-plotly-plot .legend")).to_have_count(3)
    page.screenshot(path=str(artifacts / "dashboard-legends.png"), full_page=True)
    assert _legends_on_axis_titles(page) == []
    context.close()
