"""`trustlab serve` stops when told to, also with consoles open: their live streams (server-sent
events) never end by themselves, and a server that waited for them would never stop on its own
(a restart of the lab's server would hang until the service manager killed it)."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import threading
from pathlib import Path

import httpx

from app.db import Database
from app.services.audit import Actor
from app.services.sessions import stations
from app.tables import Role
from tests.conftest import PASSWORD, make_user
from tests.servers import TrustlabServe


def test_the_server_stops_within_its_grace_period_with_a_live_stream_open(
    sqlite_template: Path, tmp_path: Path
) -> None:
    """Engine-independent, so on SQLite only: the server's shutdown, not the database's."""
    path = tmp_path / "serve.sqlite3"
    shutil.copyfile(sqlite_template, path)
    url = f"sqlite:///{path}"
    database = Database(url)
    try:
        make_user(database, "watcher", Role.ADMIN)
        with database.writing() as db:
            stations.create_station(db, name="lab-1", actor=Actor.system())
    finally:
        database.dispose()
    server = TrustlabServe(
        url, tmp_path / "var", extra_env={"TRUSTLAB_SHUTDOWN_GRACE_SECONDS": "1"}
    )
    server.start()
    streaming = threading.Event()
    ended: list[str] = []

    def watch() -> None:
        with httpx.Client(base_url=server.url, timeout=60) as console:
            signed_in = console.post(
                "/api/v1/session", json={"username": "watcher", "password": PASSWORD}
            )
            assert signed_in.status_code == 200, signed_in.text
            with console.stream("GET", "/stations/lab-1/events") as stream:
                assert stream.status_code == 200
                streaming.set()
                try:
                    for _ in stream.iter_bytes():
                        pass
                    ended.append("closed by the server")
                except httpx.HTTPError as exc:
                    ended.append(f"cut: {type(exc).__name__}")

    watcher = threading.Thread(target=watch, daemon=True)
    watcher.start()
    try:
        assert streaming.wait(30), "the console's live stream did not open"
        assert server.process is not None
        os.killpg(server.process.pid, signal.SIGTERM)
        try:
            server.process.wait(timeout=30)  # it waits 1 s for the stream, then cuts it
        except subprocess.TimeoutExpired:
            raise AssertionError("the server did not stop with a live stream open") from None
        log = server.log_path.read_text()
        assert "Application shutdown complete" in log, log[-2000:]  # a clean stop, not a crash
        watcher.join(30)
        assert ended, "the stream was left open"
    finally:
        server.kill()
