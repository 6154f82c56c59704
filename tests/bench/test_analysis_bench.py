"""bench/analysis.py --mixed runs end to end on a small study and prints its figures."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_the_mixed_models_benchmark_prints_one_measure_and_the_whole_study() -> None:
    command = [sys.executable, "bench/analysis.py", "--mixed", "--sizes", "24", "--repeats", "1"]
    done = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    line = done.stdout.strip().splitlines()[-1]
    assert re.match(
        r"n=\s*24  ratings/measure=\s*\d+  one measure \d+\.\d\d s median \(worst \d+\.\d\d\)  "
        r"all 5 measures \d+\.\d\d s  \(1 runs, all converged\)  target ≤ 2 s: (met|MISSED)$",
        line,
    ), line
