"""bench/speech.py runs end to end on a small set (one voice, one SNR, one seed; the default engine,
Whisper) and prints its table; without espeak-ng it says so in one line and exits 2."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.timeout(300)
@pytest.mark.skipif(shutil.which("espeak-ng") is None, reason="needs Debian's espeak-ng")
def test_the_speech_benchmark_prints_its_table_and_verdicts(tmp_path: Path) -> None:
    records = tmp_path / "records.jsonl"
    command = [sys.executable, "bench/speech.py", "--voices", "1", "--snrs", "10", "--seeds", "1"]
    command += ["--records", str(records)]
    done = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=280)
    assert done.returncode == 0, done.stderr
    lines = done.stdout.strip().splitlines()
    assert re.match(
        r"\d+ clips \(7 yes/no, \d+ other\), 1 voices \(all\), whisper tiny\.en", lines[0]
    )
    assert lines[-1].startswith("peak RSS ") and lines[-1].endswith(" MB")
    rows = [line for line in lines if line.startswith(("| clean", "| SNR 10"))]
    assert len(rows) == 2, done.stdout
    for row in rows:
        cells = [cell.strip() for cell in row.strip("|").split("|")]
        assert len(cells) == 9 and all(re.fullmatch(r"[\d.± -]+", c) for c in cells[1:]), row
    verdicts = [line for line in lines if line.startswith(("clean:", "SNR 10 dB:"))]
    assert len(verdicts) == 2 and all(re.search(r"(met|MISSED)$", v) for v in verdicts)
    again = subprocess.run(
        [sys.executable, "bench/speech.py", "--from-records", str(records)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert again.returncode == 0, again.stderr
    reported = again.stdout.strip().splitlines()
    assert "noise seeds: clean 1, SNR 10 dB 1" in reported[0]
    recounted = [line for line in reported if line.startswith(("| clean", "| SNR 10"))]
    figures = [row.split("|")[2:5] + row.split("|")[8:10] for row in (*rows, *recounted)]
    assert figures[:2] == figures[2:]  # the same rates, waits and counts from the records


def test_without_espeak_the_benchmark_says_so_and_exits_2(tmp_path: Path) -> None:
    env = {**os.environ, "PATH": str(tmp_path)}
    done = subprocess.run(
        [sys.executable, "bench/speech.py"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
        env=env,
    )
    assert done.returncode == 2
    assert (
        done.stdout.strip()
        == "error: espeak-ng is not installed (Debian: apt-get install espeak-ng)"
    )
