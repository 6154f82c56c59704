"""The browser tests' CPU-throttle switch (``TRUSTLAB_E2E_CPU_THROTTLE``) reaches every page.

What it does to a page (Chromium runs the page's scripts N times slower) is Chromium's; what is
ours is that every page of every browser the tests launch gets it before its first navigation,
whichever way the page was opened.
"""

from __future__ import annotations

import pytest
from playwright.sync_api import Page, Playwright

from tests.e2e import conftest


@pytest.fixture
def throttled(monkeypatch: pytest.MonkeyPatch) -> list[tuple[str, float]]:
    """The (page's URL when throttled, rate) of every page the switch throttles."""
    seen: list[tuple[str, float]] = []
    monkeypatch.setenv(conftest.THROTTLE_VARIABLE, "4")
    monkeypatch.setattr(conftest, "_throttle", lambda page, rate: seen.append((page.url, rate)))
    return seen


@pytest.mark.e2e
def test_every_page_is_throttled_before_it_loads(
    playwright: Playwright, throttled: list[tuple[str, float]]
) -> None:
    chromium = conftest.launch_chromium(playwright)
    try:
        context = chromium.new_context()
        page = context.new_page()
        assert throttled == [("about:blank", 4.0)]
        with context.expect_page() as popup:
            page.evaluate("() => { window.open('about:blank'); }")
        popup.value.wait_for_load_state()
        assert len(throttled) == 2  # the popup, once
        alone = chromium.new_page()  # a page in a context of its own
        assert len(throttled) == 3
        assert alone.url == "about:blank"
        context.close()
        alone.context.close()
    finally:
        chromium.close()


@pytest.mark.e2e
def test_without_the_switch_no_page_is_throttled(
    playwright: Playwright, monkeypatch: pytest.MonkeyPatch
) -> None:
    seen: list[Page] = []
    monkeypatch.delenv(conftest.THROTTLE_VARIABLE, raising=False)
    monkeypatch.setattr(conftest, "_throttle", lambda page, rate: seen.append(page))
    chromium = conftest.launch_chromium(playwright)
    try:
        chromium.new_context().new_page()
        chromium.new_page()
        assert seen == []
    finally:
        chromium.close()


@pytest.mark.parametrize("given", ["fast", "0.5", "0"])
def test_a_malformed_switch_is_refused(monkeypatch: pytest.MonkeyPatch, given: str) -> None:
    monkeypatch.setenv(conftest.THROTTLE_VARIABLE, given)
    with pytest.raises(pytest.UsageError, match="must be a number of at least 1"):
        conftest.cpu_throttle()
