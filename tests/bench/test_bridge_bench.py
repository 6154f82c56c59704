"""bench/bridge.py runs end to end on a small scale: one participant's practice run and session
1 through each robot kind's stand-in, with a latency summary per kind."""

from __future__ import annotations

import json

import pytest

from bench import bridge


@pytest.mark.timeout(240)
def test_the_bridge_benchmark_reports_each_kind(capsys: pytest.CaptureFixture[str]) -> None:
    assert bridge.main(["--participants", "1", "--json"]) == 0
    found = json.loads(capsys.readouterr().out)
    assert sorted(found) == ["furhat", "naoqi", "rosbridge"]
    for summary in found.values():
        assert summary["n"] == 12  # the practice run's 3 answers and session 1's 9
        assert 0 < summary["median_ms"] <= summary["p95_ms"] <= summary["max_ms"]


def test_an_unknown_kind_is_refused_in_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_:
        bridge.main(["--kinds", "furhat,asimo"])
    assert exit_.value.code == 2
    assert "unknown kind(s) asimo; known: naoqi, furhat, rosbridge" in capsys.readouterr().err
