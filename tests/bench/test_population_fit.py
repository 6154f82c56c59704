"""bench/population_fit.py runs end to end on a small population and reports the figures."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_the_fit_benchmark_runs_and_prints_its_figures() -> None:
    result = subprocess.run(
        [sys.executable, "bench/population_fit.py", "--participants", "60", "--replicates", "2"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert result.returncode == 0, result.stderr
    assert "point fit (steps → sequences → EM, 3 categories)" in result.stdout
    assert result.stdout.count("max error") == 3
    assert "bootstrap resamples per category" in result.stdout
