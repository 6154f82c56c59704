"""bench/robust.py runs end to end on a few participants and reports means over seeds."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_the_robust_benchmark_reports_means_spreads_and_ratio_targets() -> None:
    command = [sys.executable, "bench/robust.py", "--participants", "150", "--seeds", "3"]
    command += ["--category", "conation", "--scenario", "10 % slips"]
    done = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    out = done.stdout
    assert "150 participants × 3 seeds (2026–2028)" in out
    meta = next(line for line in out.splitlines() if line.strip().startswith("meta "))
    assert meta.count("±") == 4 and meta.count("[") == 4  # each figure: mean ± sd [range]
    for target in ("wrong_95 ≤ 1.25 × reference (model)", "iterations_to_95 ≤ 1.1 × reference"):
        assert target in out, target
    assert out.rstrip().endswith("of 4 target(s) missed")
