"""bench/room.py runs end to end on a small scale and reports both of issue 22's figures."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.e2e
def test_the_room_benchmark_reports_frame_rates_and_caption_latency() -> None:
    command = [sys.executable, "bench/room.py", "--sessions", "0", "--seconds", "0.3"]
    command += ["--viewports", "480x320", "--json"]
    done = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    found = json.loads(done.stdout)
    (rate,) = found["frame_rate"]
    assert rate["viewport"] == "480x320"
    assert rate["standing_fps"] > 0 and rate["walking_fps"] > 0
    assert 0.5 <= rate["render_scale"] <= 1.5
    latency = found["zone_to_caption"]
    assert latency["n"] == 3  # the practice run's three prompts
    assert 0 < latency["median_ms"] <= latency["p95_ms"] <= latency["max_ms"]
