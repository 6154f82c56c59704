"""Benchmark: each ``trustlab`` command's wall time to its first output (issue 49, item 1).

Run from the repository root::

    .venv/bin/python bench/cli.py                 # every command, median of 10 runs
    .venv/bin/python bench/cli.py --repeats 3 --only study

Each run is a fresh ``python -c "from app.cli import main; main()" …`` subprocess, timed from
its start to the first byte it writes (stdout or stderr), as a person at a shell feels it. One
temporary SQLite database is migrated and given a study, a station and a participant once,
before any timing; commands that write (enrol, create) get a new name on every run. Targets:
0.3 s for ``--help`` and the commands that need no database, 0.6 s for those that open it, on
an idle machine. Prints a table with the target beside each median; results go to
docs/performance.md ("Command start-up (issue 49)"). Never used as a test assertion.
"""

from __future__ import annotations

import argparse
import itertools
import os
import platform
import select
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PROGRAM = "from app.cli import main; main()"
NO_DATABASE, DATABASE = 0.3, 0.6
"""Seconds to first output allowed: commands that need no database, and those that open it."""


@dataclass(frozen=True)
class Command:
    """One command line to time; ``words`` gets the run's number, for names that must be new."""

    label: str
    words: Callable[[int], list[str]]
    target: float
    stdin: str | None = None


_counter = itertools.count(1)


def fixed(*words: str) -> Callable[[int], list[str]]:
    """The same command line on every run."""
    return lambda _run: list(words)


def commands(tmp: Path) -> list[Command]:
    """The commands of issue 49 item 1 (and their neighbours) that build no learner."""
    out = tmp / "long.csv"
    return [
        Command("--help", fixed("--help"), NO_DATABASE),
        Command("study --help", fixed("study", "--help"), NO_DATABASE),
        Command("languages list", fixed("languages", "list"), NO_DATABASE),
        Command("languages check sv", fixed("languages", "check", "sv"), NO_DATABASE),
        Command(
            "power (analytic)",
            fixed(
                *("power", "--effect", "between", "--groups", "2", "--sessions", "4"),
                *("--f", "0.25", "--rho", "0.5", "--target-power", "0.8"),
            ),
            NO_DATABASE,
        ),
        Command("db current", fixed("db", "current"), DATABASE),
        Command("study list", fixed("study", "list"), DATABASE),
        Command(
            "participant enroll", fixed("participant", "enroll", "--study", "default"), DATABASE
        ),
        Command("station create", lambda n: ["station", "create", f"bench-{n}"], DATABASE),
        Command("station list", fixed("station", "list"), DATABASE),
        Command("device create", fixed("device", "create", "--station", "bench-0"), DATABASE),
        Command(
            "user create",
            lambda n: [
                *("user", "create", "--username", f"bench{n}", "--role", "analyst"),
                "--password-stdin",
            ],
            DATABASE,
            stdin="a long enough password\n",
        ),
        Command("user list", fixed("user", "list"), DATABASE),
        Command(
            "export long-csv",
            fixed(
                "export", "--study", "default", "--format", "long-csv", "--out", str(out), "--force"
            ),
            DATABASE,
        ),
    ]


def environment(tmp: Path) -> dict[str, str]:
    """The subprocesses' environment: the temporary database, the checkout on the path."""
    return {
        **os.environ,
        "PYTHONPATH": str(ROOT),
        "TRUSTLAB_DATABASE_URL": f"sqlite:///{tmp / 'bench.sqlite3'}",
        "TRUSTLAB_VAR_DIR": str(tmp / "var"),
        "TRUSTLAB_SECRET_KEY": "bench-secret-0123456789abcdef0123456789",
    }


def run(words: list[str], env: dict[str, str], stdin: str | None = None) -> tuple[float, int]:
    """Seconds from the start of ``trustlab WORDS`` to its first output byte, and its status."""
    started = time.perf_counter()
    process = subprocess.Popen(
        [sys.executable, "-c", PROGRAM, *words],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env=env,
        cwd=ROOT,
    )
    assert process.stdin and process.stdout and process.stderr
    if stdin is not None:
        process.stdin.write(stdin.encode())
    process.stdin.close()
    select.select([process.stdout, process.stderr], [], [])
    first = time.perf_counter() - started
    process.stdout.read()
    err = process.stderr.read()
    process.wait()
    if process.returncode != 0:
        raise SystemExit(f"trustlab {' '.join(words)} failed:\n{err.decode()}")
    return first, process.returncode


def set_up(env: dict[str, str]) -> None:
    """Migrate the database, then add what the timed commands refer to."""
    for words in (["init", "--no-demo"], ["station", "create", "bench-0"]):
        run(words, env)
    run(["participant", "enroll", "--study", "default"], env)


def main() -> None:
    """Time every command and print the table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=10, help="Runs per command (median).")
    parser.add_argument("--only", default="", help="Only commands whose label contains this.")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="trustlab-bench-cli-") as name:
        tmp = Path(name)
        env = environment(tmp)
        set_up(env)
        print(f"{platform.node()}: {os.cpu_count()} cores, load {os.getloadavg()[0]:.2f}")
        print(f"{'command':<22} {'median s':>9} {'min s':>7} {'target s':>9}  met")
        for command in commands(tmp):
            if args.only not in command.label:
                continue
            times = [
                run(command.words(next(_counter)), env, command.stdin)[0]
                for _ in range(args.repeats)
            ]
            median = statistics.median(times)
            met = "yes" if median <= command.target else "NO"
            figures = f"{median:>9.3f} {min(times):>7.3f} {command.target:>9.1f}"
            print(f"{command.label:<22} {figures}  {met}")
        print(f"load after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
