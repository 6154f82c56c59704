"""``trustlab serve``'s access log keeps participant codes and tablet tokens out unless asked
(TRUSTLAB_ACCESS_LOG): a request naming a code, and the log line without it."""

from __future__ import annotations

import shutil
from pathlib import Path

import httpx
import pytest

from app.access_log import redact
from tests.servers import TrustlabServe

CODE = "SECRET-P017"
TOKEN = "tok3n-of-a-tablet"


@pytest.mark.parametrize(
    ("path", "logged"),
    [
        (f"/studies/s1/participants/{CODE}/withdraw", "/studies/s1/participants/[hidden]/withdraw"),
        (f"/api/v1/studies/s1/participants/{CODE}", "/api/v1/studies/s1/participants/[hidden]"),
        (f"/t/{TOKEN}", "/t/[hidden]"),
        (f"/k/{TOKEN}?next=1", "/k/[hidden]?next=1"),
        (f"/studies/s1/timeline?code={CODE}&x=1", "/studies/s1/timeline?code=[hidden]&x=1"),
        ("/studies/s1/participants", "/studies/s1/participants"),
    ],
)
def test_the_paths_lose_their_codes_and_tokens(path: str, logged: str) -> None:
    assert redact(path) == logged


@pytest.mark.parametrize("mode", ["default", "off", "full"])
def test_trustlab_serve_logs_requests_without_codes_unless_asked(
    sqlite_template: Path, tmp_path: Path, mode: str
) -> None:
    """Engine-independent, so on SQLite only: the server's logging, not the app's."""
    path = tmp_path / "serve.sqlite3"
    shutil.copyfile(sqlite_template, path)
    env = {} if mode == "default" else {"TRUSTLAB_ACCESS_LOG": mode}
    server = TrustlabServe(f"sqlite:///{path}", tmp_path / "var", extra_env=env)
    server.start()
    try:
        for asked in (f"/studies/s1/participants/{CODE}/withdraw", f"/t/{TOKEN}"):
            httpx.get(server.url + asked, follow_redirects=False)
    finally:
        server.stop()
    log = server.log_path.read_text()
    if mode == "full":
        assert f'"GET /studies/s1/participants/{CODE}/withdraw HTTP/1.1"' in log, log
        return
    assert CODE not in log and TOKEN not in log, log
    if mode == "default":
        assert '"GET /studies/s1/participants/[hidden]/withdraw HTTP/1.1"' in log, log
        assert '"GET /t/[hidden] HTTP/1.1"' in log, log
    else:
        assert "/studies/s1/participants/" not in log and '"GET /healthz' not in log, log
