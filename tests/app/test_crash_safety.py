"""SIGKILL the server at random moments while a robot runs sessions: nothing acknowledged is lost,
nothing is applied twice, and ``trustlab verify`` stays clean (SQLite and PostgreSQL)."""

from __future__ import annotations

import random
import threading
import time
from pathlib import Path

import pytest

from app.db import Database
from tests.app.session_driver import Driver, assert_exactly_once, seat_participant
from tests.servers import ServerProcess

KILLS = 6
"""Kills per run: bounded for CI (each costs a server restart, about a second)."""


@pytest.mark.slow
def test_sigkill_at_random_moments_loses_nothing_and_applies_nothing_twice(
    database: Database, database_url: str, exp3_study: str, tmp_path: Path
) -> None:
    rng = random.Random(20261122)
    seated = seat_participant(database, exp3_study)
    server = ServerProcess(database_url, tmp_path / "var")
    server.start()
    driver = Driver(server, seated.device_key, seated.station, seated.tablet_token)
    driver.sign_in("operator")
    # Kill points are request numbers drawn at random over the run (about 160 requests); each
    # kill lands a random few milliseconds after that request was sent, so it may hit the server
    # before, during or after the request's transaction. One kill at a time.
    kill_points = set(rng.sample(range(3, 150), KILLS))
    kills: list[int] = []
    killing = threading.Lock()

    def kill_then_restart() -> None:
        with killing:
            time.sleep(rng.uniform(0.0, 0.015))
            server.kill()
            kills.append(driver.sent)
            server.start()

    def maybe_kill(sent: int) -> None:
        due = sent in kill_points or (len(kills) < KILLS and sent > max(kill_points))
        if due and not killing.locked():
            threading.Thread(target=kill_then_restart, daemon=True).start()

    driver.before_each_request = maybe_kill
    try:
        driver.run(rng)
    finally:
        with killing:
            server.stop()

    assert len(kills) >= KILLS, f"only {len(kills)} kills: the test did not exercise crashes"
    assert_exactly_once(database, exp3_study, driver)
