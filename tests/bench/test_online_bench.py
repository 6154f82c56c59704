"""bench/online.py runs end to end on a small scale and reports what issue 51 asks of it."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.slow
def test_the_online_benchmark_reports_latency_losses_and_memory() -> None:
    command = [sys.executable, "-m", "bench.online", "--levels", "2", "--json"]
    command += ["--think", "0", "--per-item", "0", "--walk", "0", "--arrivals", "0"]
    command += ["--sessions", "1"]
    done = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    found = json.loads(done.stdout)
    assert found["engine"] == "sqlite" and found["pace_s"] == {
        "action": 0.0,
        "per_item": 0.0,
        "walk": 0.0,
    }
    (level,) = found["levels"]
    assert level["participants"] == level["completed"] == 2 and level["errors"] == 0
    assert 1 <= level["most_at_once"] <= 2
    # a practice run and one session of three questions each, for both participants
    assert level["answers_told"] == level["answers_stored"] == 2 * 2 * 3
    assert level["answers_lost"] == level["answers_doubled"] == 0 and level["verify_ok"]
    for kind in ("all_pages", "join", "online", "page", "form", "start", "answer"):
        figures = level[kind]
        assert figures["count"] > 0 and 0 < figures["p50_ms"] <= figures["p95_ms"], kind
    assert level["memory_peak_mb"] >= level["memory_idle_mb"] > 0


def test_the_online_benchmark_refuses_a_negative_pause_in_one_line() -> None:
    command = [sys.executable, "-m", "bench.online", "--walk", "-1"]
    done = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert done.returncode != 0
    assert done.stderr.strip().splitlines()[-1] == "error: a pace's pauses are seconds ≥ 0"
