"""Browser tests: Debian's Chromium driven by Playwright against a real trustlab server.

They run on SQLite only (the database layer is covered on both engines elsewhere) and save a
screenshot of every page they visit under test-artifacts/ for people to look at.

``TRUSTLAB_E2E_CPU_THROTTLE=N`` slows every page the tests open N times (Chromium's CDP
``Emulation.setCPUThrottlingRate``): a run with 4 shows the races a loaded machine would, a test
that reads what the page has not yet done (docs/development.md, "Browser tests").
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from playwright.sync_api import Browser, BrowserContext, Page, Playwright, expect, sync_playwright

from app.db import Database
from app.settings import REPO_ROOT
from tests.conftest import PASSWORD
from tests.servers import ServerProcess

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--no-first-run",
]
THROTTLE_VARIABLE = "TRUSTLAB_E2E_CPU_THROTTLE"
ARTIFACTS = REPO_ROOT / "test-artifacts"
SECRET = b"subprocess-test-secret-0123456789abcdef"

# Assertions wait for what the page shows, never for a time; the ceiling only decides how long a
# broken page takes to fail. Playwright's 5 s default was too short for server work such as a mixed
# model fit while the parallel suite shares two cores (the mixed-models page failed at load 7-9).
expect.set_options(timeout=30_000)


def cpu_throttle() -> float | None:
    """The slow-down ``TRUSTLAB_E2E_CPU_THROTTLE`` asks for (1 is none), or None when unset."""
    given = os.environ.get(THROTTLE_VARIABLE, "").strip()
    if not given:
        return None
    try:
        rate = float(given)
    except ValueError:
        rate = 0.0
    if rate < 1:
        raise pytest.UsageError(
            f"{THROTTLE_VARIABLE} must be a number of at least 1, not {given!r}"
        )
    return rate


def pytest_configure(config: pytest.Config) -> None:
    """Refuse a malformed ``TRUSTLAB_E2E_CPU_THROTTLE`` before any test runs."""
    cpu_throttle()


def launch_chromium(playwright: Playwright, *extra_args: str) -> Browser:
    """Debian's Chromium, headless, with ``extra_args``; every page it opens is CPU-throttled
    when ``TRUSTLAB_E2E_CPU_THROTTLE`` says so. Every browser of the tests starts here, so the
    switch reaches each of their pages."""
    chromium = playwright.chromium.launch(
        executable_path=CHROMIUM, args=[*CHROMIUM_ARGS, *extra_args]
    )
    rate = cpu_throttle()
    if rate is not None:
        _throttle_pages(chromium, rate)
    return chromium


def _throttle(page: Page, rate: float) -> None:
    page.context.new_cdp_session(page).send("Emulation.setCPUThrottlingRate", {"rate": rate})


def _throttle_pages(browser: Browser, rate: float) -> None:
    """Throttle every page of every context of ``browser``, from before its first navigation.

    Playwright has no browser-wide page hook, so the browser's ``new_context`` and ``new_page``
    are wrapped on this instance. A context's ``page`` event alone would not do: in the sync API
    its handler's CDP call completes only after ``new_page`` has returned, so a test's first
    ``goto`` could start unthrottled. ``new_page`` therefore throttles before it returns, and
    the event throttles the pages a page opens itself (popups).
    """
    make_context = browser.new_context
    make_page = browser.new_page

    def watched(context: BrowserContext) -> BrowserContext:
        opening = False

        def opened_by_a_page(page: Page) -> None:
            if not opening:  # new_page's own is throttled below
                _throttle(page, rate)

        context.on("page", opened_by_a_page)
        open_page = context.new_page

        def new_page() -> Page:
            nonlocal opening
            opening = True
            try:
                page = open_page()
            finally:
                opening = False
            _throttle(page, rate)
            return page

        context.new_page = new_page  # type: ignore[method-assign]
        return context

    def new_context(**options: Any) -> BrowserContext:
        return watched(make_context(**options))

    def new_page(**options: Any) -> Page:
        """``Browser.new_page``: a page in a context of its own (Playwright makes it inside)."""
        page = make_page(**options)
        _throttle(page, rate)
        return page

    browser.new_context = new_context  # type: ignore[method-assign]
    browser.new_page = new_page  # type: ignore[method-assign]


@pytest.fixture
def engine_name() -> str:
    """Browser tests use SQLite."""
    return "sqlite"


@pytest.fixture(scope="module")
def playwright() -> Iterator[Playwright]:
    """Playwright's driver, per module: while it runs, its event loop is the thread's running
    loop, so a later test's ``asyncio.run`` on the same pytest-xdist worker would fail."""
    if not Path(CHROMIUM).exists():
        pytest.fail(f"{CHROMIUM} is missing: install Debian's chromium (.ci/run does)")
    with sync_playwright() as driver:
        yield driver


@pytest.fixture(scope="module")
def browser(playwright: Playwright) -> Iterator[Browser]:
    """One headless Chromium per module."""
    chromium = launch_chromium(playwright)
    yield chromium
    chromium.close()


@pytest.fixture
def live_server(database: Database, database_url: str, tmp_path: Path) -> Iterator[ServerProcess]:
    """A trustlab server on the test's database."""
    server = ServerProcess(database_url, tmp_path / "var")
    server.start()
    yield server
    server.stop()


@pytest.fixture
def artifacts(request: pytest.FixtureRequest) -> Path:
    """Where this test's screenshots go."""
    folder = ARTIFACTS / request.node.name.replace("/", "_").replace("[", "-").rstrip("]")
    folder.mkdir(parents=True, exist_ok=True)
    return folder


SSE_OPEN = (
    "window.__sseOpen = false;"
    " document.addEventListener('htmx:sseOpen', () => { window.__sseOpen = true; });"
)
"""An init script that notes when htmx's event stream of a staff page is open: a change made
before it is open reaches the page by no event, so a test that makes one waits for this first."""


def sign_in_page(
    page: Page, server: ServerProcess, next_url: str, username: str = "operator"
) -> None:
    """Sign ``username`` in through the real form and wait until ``next_url`` is shown."""
    page.goto(f"{server.url}/login?next={next_url}")
    page.get_by_label("Username").fill(username)
    page.get_by_label("Password").fill(PASSWORD)
    page.get_by_role("button", name="Sign in").click()
    expect(page).to_have_url(f"{server.url}{next_url}")
