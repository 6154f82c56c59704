"""Two versions of trustlab under the same robot load, in alternating phases, for a fair A/B.

This machine's speed drifts by tens of percent within minutes (docs/performance.md), more than
most changes to the robot's path are worth, so comparing two runs of bench/api.py made one after
the other mostly compares two moments. Here both versions serve at once, each from its own
source tree with its own fresh database, and closed-loop robots (as in bench/api.py) load them in
turn for a few seconds each: a drift weighs on both alike. Prints, per version, the robot
requests per second (prompts and answers; the server is saturated, so this is one over its time
per request) and the answer p99 of every phase with their medians, then the pairwise ratios.

    git worktree add /tmp/before HEAD~1
    .venv/bin/python bench/api_ab.py --before /tmp/before
    .venv/bin/python bench/api_ab.py --before /tmp/before --clients 100 --pairs 6 --seconds 5
    .venv/bin/python bench/api_ab.py --before /tmp/before \
        --postgres postgresql+psycopg://postgres@127.0.0.1:5432/test --workers 2

The databases are prepared with this checkout's code (bench.api.prepare), so both versions must
share the schema.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import uvloop

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from bench.api import (  # noqa: E402
    Samples,
    bench_database,
    percentile,
    prepare,
    robot_loop,
    sign_in,
)
from bench.rawhttp import RawHttp  # noqa: E402
from tests.servers import ServerProcess  # noqa: E402


async def phase(base: str, keys: list[str], seconds: float) -> dict[str, Any]:
    """One closed-loop phase with one robot per key: throughput, answer p99, errors."""
    credentials = await sign_in(base)
    experimenters = [RawHttp(base, credentials) for _ in keys]
    samples = Samples()
    started = time.perf_counter()
    deadline = started + seconds
    await asyncio.gather(
        *(
            robot_loop(base, key, f"bench-{i}", experimenters[i], deadline, samples)
            for i, key in enumerate(keys)
        )
    )
    elapsed = time.perf_counter() - started
    for experimenter in experimenters:
        await experimenter.close()
    return {
        "requests_per_s": (len(samples.prompt) + len(samples.answer)) / elapsed,
        "answer_p99_ms": percentile(samples.answer, 0.99),
        "errors": len(samples.errors),
        "first_error": samples.errors[0] if samples.errors else "",
    }


def schedule(pairs: int) -> list[str]:
    """Which version each phase loads: before, after, after, before, before, after…, so that
    neither always comes first after a switch (nor always second)."""
    return [("before", "after")[(number + number // 2) % 2] for number in range(2 * pairs)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--before", type=Path, required=True, help="the other source tree")
    parser.add_argument("--clients", type=int, default=10, help="robots loading a server")
    parser.add_argument("--pairs", type=int, default=8, help="phases per version")
    parser.add_argument("--seconds", type=float, default=4.0, help="length of a phase")
    parser.add_argument(
        "--warmup", type=float, default=2.0, help="uncounted load on each server first (s)"
    )
    parser.add_argument("--exp3-only", action="store_true", help="both conditions Exp3")
    parser.add_argument("--postgres", help="maintenance URL; compares on PostgreSQL instead")
    parser.add_argument("--workers", type=int, default=1, help="uvicorn workers per server")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    args = parser.parse_args()
    versions = {"before": args.before.resolve(), "after": ROOT}
    results: dict[str, list[dict[str, Any]]] = {name: [] for name in versions}
    with tempfile.TemporaryDirectory() as tmp, contextlib.ExitStack() as databases:
        servers: dict[str, ServerProcess] = {}
        keys: dict[str, list[str]] = {}
        try:
            for name, source in versions.items():
                url = databases.enter_context(bench_database(args.postgres, tmp, name))
                keys[name] = prepare(url, args.clients, args.exp3_only)
                servers[name] = ServerProcess(
                    url, Path(tmp) / f"var-{name}", workers=args.workers, source=source
                )
                servers[name].start()
            for name in versions:  # warm-up, not counted
                uvloop.run(phase(servers[name].url, keys[name], args.warmup))
            for name in schedule(args.pairs):
                results[name].append(uvloop.run(phase(servers[name].url, keys[name], args.seconds)))
        finally:
            for server in servers.values():
                server.stop()
    engine = "postgresql" if args.postgres else "sqlite"
    if args.json:
        settings = {"engine": engine, "clients": args.clients, "exp3_only": args.exp3_only}
        print(json.dumps({**settings, **results}))
        return
    print(
        f"engine={engine} workers={args.workers} clients={args.clients} pairs={args.pairs} "
        f"seconds={args.seconds} exp3_only={args.exp3_only}"
    )
    for name, phases in results.items():
        rates = [p["requests_per_s"] for p in phases]
        p99s = [p["answer_p99_ms"] for p in phases]
        print(
            f"{name:>6}: requests/s {' '.join(f'{r:.0f}' for r in rates)} "
            f"(median {statistics.median(rates):.0f}); answer p99 ms "
            f"{' '.join(f'{p:.1f}' for p in p99s)} (median {statistics.median(p99s):.1f}); "
            f"errors {sum(int(p['errors']) for p in phases)}"
        )
        for error in {p["first_error"] for p in phases if p["first_error"]}:
            print(f"        first error of a phase: {error}")
    ratios = [
        a["requests_per_s"] / b["requests_per_s"]
        for a, b in zip(results["after"], results["before"], strict=True)
    ]
    print(
        f"after/before requests/s by pair: {' '.join(f'{r:.2f}' for r in ratios)} "
        f"(median {statistics.median(ratios):.2f})"
    )


if __name__ == "__main__":
    main()
