"""bench/bridge.py runs end to end on a small scale: one participant's practice run and session
1 through each robot kind's stand-in, with a latency summary per kind."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from bench import bridge

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.timeout(240)
def test_the_bridge_benchmark_reports_each_kind() -> None:
    """Run as a script: its standard output is the JSON alone, although the qi library logs to
    the process's standard output."""
    done = subprocess.run(
        [sys.executable, "bench/bridge.py", "--participants", "1", "--json"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=230,
    )
    assert done.returncode == 0, done.stderr
    found = json.loads(done.stdout)
    assert sorted(found) == ["furhat", "naoqi", "rosbridge"]
    for summary in found.values():
        assert summary["n"] == 12  # the practice run's 3 answers and session 1's 9
        assert 0 < summary["median_ms"] <= summary["p95_ms"] <= summary["max_ms"]


def test_an_unknown_kind_is_refused_in_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_:
        bridge.main(["--kinds", "furhat,asimo"])
    assert exit_.value.code == 2
    assert "unknown kind(s) asimo; known: naoqi, furhat, rosbridge" in capsys.readouterr().err
