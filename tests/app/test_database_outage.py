"""PostgreSQL restarted under load: while the server is down, requests fail with a clear 503 (and a
Retry-After) instead of a 500 or a hang; once it is back they succeed again, and the whole study
that a robot drove through the outages has every acknowledged answer exactly once.

Restarting the cluster needs the machine's own PostgreSQL (``pg_ctlcluster``, as in CI); the
test restarts it and always leaves it running.
"""

from __future__ import annotations

import random
import shutil
import subprocess
import threading
import time
from collections import Counter
from pathlib import Path

import httpx
import pytest

from app.db import Database
from tests.app.session_driver import Driver, assert_exactly_once, seat_participant
from tests.conftest import POSTGRES_SKIP_REASON, POSTGRES_URL
from tests.servers import ServerProcess


@pytest.fixture(params=[pytest.param("postgresql", marks=pytest.mark.postgres)])
def engine_name(request: pytest.FixtureRequest) -> str:
    """Only PostgreSQL has a server to restart."""
    if not POSTGRES_URL:
        pytest.skip(POSTGRES_SKIP_REASON)
    if shutil.which("pg_ctlcluster") is None:
        pytest.fail("TRUSTLAB_TEST_POSTGRES_URL is set but pg_ctlcluster is missing")
    return str(request.param)


def cluster_version() -> str:
    return sorted(p.name for p in Path("/etc/postgresql").iterdir())[-1]


def restart_postgres() -> None:
    """Stop the cluster (fast: open connections are cut), then start it again."""
    command = ["pg_ctlcluster", "--skip-systemctl-redirect", cluster_version(), "main"]
    subprocess.run([*command, "stop", "-m", "fast"], check=True, capture_output=True)
    time.sleep(0.5)  # an outage long enough for requests to hit it
    subprocess.run([*command, "start"], check=True, capture_output=True)


def ensure_postgres_running() -> None:
    command = ["pg_ctlcluster", "--skip-systemctl-redirect", cluster_version(), "main", "start"]
    subprocess.run(command, capture_output=True)  # "already running" is fine
    for _ in range(60):
        if subprocess.run(["pg_isready", "-q", "-h", "127.0.0.1"]).returncode == 0:
            return
        time.sleep(0.5)
    raise RuntimeError("PostgreSQL did not come back")


@pytest.mark.slow
@pytest.mark.exclusive  # restarts the PostgreSQL every other test shares: never beside them
def test_requests_get_503_during_a_restart_and_nothing_is_lost(
    database: Database, database_url: str, exp3_study: str, tmp_path: Path
) -> None:
    rng = random.Random(5432)
    seated = seat_participant(database, exp3_study)
    server = ServerProcess(database_url, tmp_path / "var")
    server.start()
    driver = Driver(server, seated.device_key, seated.station, seated.tablet_token)
    driver.sign_in("operator")
    restarts = 0
    outage_answers: list[httpx.Response] = []
    dropped: list[str] = []
    finished = threading.Event()

    def restarter() -> None:
        nonlocal restarts
        while not finished.is_set() and restarts < 3:
            time.sleep(rng.uniform(0.3, 0.9))
            if finished.is_set():
                return
            restart_postgres()
            restarts += 1

    def prober() -> None:
        """A second client that keeps asking while the first one works: records what it sees."""
        with httpx.Client(headers={"Authorization": f"Bearer {seated.device_key}"}) as robot:
            while not finished.is_set():
                try:
                    outage_answers.append(robot.get(f"{server.url}/api/v1/station", timeout=10))
                except httpx.TransportError as error:
                    dropped.append(repr(error))
                time.sleep(0.02)

    chaos = threading.Thread(target=restarter, daemon=True)
    probe = threading.Thread(target=prober, daemon=True)
    chaos.start()
    probe.start()
    try:
        driver.run(rng)
    finally:
        finished.set()
        chaos.join(timeout=60)
        probe.join(timeout=30)
        ensure_postgres_running()
        server.stop()

    assert restarts >= 1, "the study finished before PostgreSQL was restarted"
    seen = driver.statuses + Counter(r.status_code for r in outage_answers)
    assert seen[503] >= 1, f"no request saw the outage: {dict(seen)}"
    assert not {status for status in seen if status >= 500} - {503}, dict(seen)
    assert dropped == [], "the server dropped connections instead of answering 503"
    for unavailable in (r for r in outage_answers if r.status_code == 503):
        assert unavailable.headers["Retry-After"]
        assert "database is unavailable" in unavailable.json()["detail"]
    assert outage_answers[-1].status_code == 200, "requests did not succeed again afterwards"
    assert_exactly_once(database, exp3_study, driver)
