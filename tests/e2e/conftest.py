"""Browser tests: Debian's Chromium driven by Playwright against a real trustlab server.

They run on SQLite only (the database layer is covered on both engines elsewhere) and save a
screenshot of every page they visit under test-artifacts/ for people to look at.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from playwright.sync_api import Browser, Page, Playwright, expect, sync_playwright

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
ARTIFACTS = REPO_ROOT / "test-artifacts"
SECRET = b"subprocess-test-secret-0123456789abcdef"

# Assertions wait for what the page shows, never for a time; the ceiling only decides how long a
# broken page takes to fail. Playwright's 5 s default was too short for server work such as a mixed
# model fit while the parallel suite shares two cores (the mixed-models page failed at load 7-9).
expect.set_options(timeout=30_000)


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
    chromium = playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
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


def sign_in_page(
    page: Page, server: ServerProcess, next_url: str, username: str = "operator"
) -> None:
    """Sign ``username`` in through the real form and wait until ``next_url`` is shown."""
    page.goto(f"{server.url}/login?next={next_url}")
    page.get_by_label("Username").fill(username)
    page.get_by_label("Password").fill(PASSWORD)
    page.get_by_role("button", name="Sign in").click()
    expect(page).to_have_url(f"{server.url}{next_url}")
