"""bench/api_ab.py compares what it says: each server runs its own source tree, the phases
alternate, and a short comparison runs end to end without errors."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import httpx

from bench.api_ab import schedule
from tests.servers import ServerProcess

ROOT = Path(__file__).resolve().parents[2]

_MARKED_APP = """
from starlette.applications import Starlette
from starlette.responses import PlainTextResponse
from starlette.routing import Route


def create_app():
    async def healthz(_request):
        return PlainTextResponse("served from the other tree")

    return Starlette(routes=[Route("/healthz", healthz)])
"""


def test_a_server_runs_the_source_tree_it_is_given(tmp_path: Path) -> None:
    tree = tmp_path / "tree"
    (tree / "app").mkdir(parents=True)
    (tree / "app" / "__init__.py").write_text("")
    (tree / "app" / "main.py").write_text(_MARKED_APP)
    server = ServerProcess("sqlite:///unused.sqlite3", tmp_path / "var", source=tree)
    server.start()
    try:
        assert httpx.get(f"{server.url}/healthz").text == "served from the other tree"
    finally:
        server.stop()


def test_neither_version_always_goes_first_after_a_switch() -> None:
    assert schedule(4) == ["before", "after", "after", "before"] * 2
    assert schedule(3).count("before") == schedule(3).count("after") == 3


def test_a_short_comparison_runs_end_to_end() -> None:
    finished = subprocess.run(
        [
            sys.executable,
            str(ROOT / "bench" / "api_ab.py"),
            "--before",
            str(ROOT),
            "--clients",
            "2",
            "--pairs",
            "1",
            "--seconds",
            "0.5",
            "--warmup",
            "0.2",
            "--exp3-only",
            "--json",
        ],
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert finished.returncode == 0, finished.stderr[-2000:]
    result = json.loads(finished.stdout)
    for version in ("before", "after"):
        (phase,) = result[version]
        assert phase["requests_per_s"] > 0 and phase["answer_p99_ms"] > 0
        assert phase["errors"] == 0, phase["first_error"]
