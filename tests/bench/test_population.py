"""bench/population.py runs end to end (tiny trainings) and prints its rows and targets."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_the_population_benchmark_runs_and_reports_each_target(tmp_path: Path) -> None:
    command = [sys.executable, "bench/population.py", "--participants", "200"]
    command += ["--meta-batches", "1", "--tasks-per-batch", "4", "--workers", "1"]
    command += ["--checkpoints", str(tmp_path)]
    for case in ("skewed N=24", "uniform N=24", "wrong pilot N=24"):
        command += ["--case", case]
    first = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert first.returncode == 0, first.stderr
    out = first.stdout
    assert "# 3 trainings" in out and "(0 reused" in out
    for row in ("skewed N=24", "uniform N=24", "wrong pilot N=24"):
        assert any(line.startswith(row) for line in out.splitlines()), row
    assert "harm of a wrong pilot: fitted − uniform =" in out
    for target in (
        "fitted ≤ 0.8 × uniform",
        "fitted ≤ 1.1 × reference",
        "meta ahead of random init by ≥ 0.5",
        "uniform N=24: fitted − uniform ≤ 0.05",
    ):
        assert target in out, target
    again = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert again.returncode == 0 and "# 0 trainings" in again.stdout and "(3 reused" in again.stdout
    rows = [line for line in out.splitlines() if line.startswith("skewed N=24")]
    assert rows == [line for line in again.stdout.splitlines() if line.startswith("skewed N=24")]


def test_the_held_out_check_prints_each_draw_and_what_the_fitted_one_overstates(
    tmp_path: Path,
) -> None:
    command = [sys.executable, "bench/population.py", "--held-out", "2", "--participants", "200"]
    command += ["--meta-batches", "1", "--tasks-per-batch", "4", "--workers", "1"]
    command += ["--checkpoints", str(tmp_path)]
    done = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert "# held-out check: 2 trainings" in done.stdout
    assert sum(line.startswith(("0 ", "1 ")) for line in lines) == 2  # one row per pilot
    (header,) = [line for line in lines if line.startswith("mean ± SD over 2 pilots")]
    for column in ("C2 answers", "gain over C1", "gain over uniform C2", "gain overstated"):
        assert column in header, column
    for draw in ("fitted (--population alone)", "held-out (--true-population)", "truth"):
        (row,) = [line for line in lines if line.startswith(draw)]
        assert row.count("±") == 5, row
    assert "not the held-out one, overstates C2's gain over C1 by" in done.stdout
    assert (tmp_path / "held-out" / "pilot1.held-out.json").is_file()
