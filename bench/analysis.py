"""Benchmark: full analysis + HTML report for 24 and 10,000 synthetic participants.

Run from the repository root::

    .venv/bin/python bench/analysis.py            # both sizes, 5 repeats (24) / 3 (10,000)
    .venv/bin/python bench/analysis.py --sizes 24 --repeats 10

Targets (issue 7): 24 participants ≤ 0.5 s, 10,000 participants ≤ 5 s, for
``analyse_study`` (scoring, five mixed ANOVAs with descriptives, marginal means and post-hoc
tests, questionnaire scores, adaptation curves) plus ``build_report`` (the self-contained HTML
with every figure). Data generation is seeded and not timed. Prints one line per size and
phase; results go to docs/performance.md ("## Analysis"). Never used as a test assertion.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time
from pathlib import Path

# Run as a script, this file's folder is first on sys.path and "analysis" would resolve to this
# very file instead of the package: put the repository root first instead.
_ROOT = Path(__file__).resolve().parents[1]
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _ROOT / "bench"]
sys.path.insert(0, str(_ROOT))

from analysis.report import build_report  # noqa: E402
from analysis.study import analyse_study  # noqa: E402
from analysis.synthetic import synthetic_study  # noqa: E402

TARGETS = {24: 0.5, 10_000: 5.0}
"""Seconds allowed for analysis + report, by number of participants."""


def cpu_model() -> str:
    """The CPU model name from /proc/cpuinfo (or platform's guess elsewhere)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def bench(n: int, repeats: int, seed: int) -> dict[str, float]:
    """Median and best seconds of analysis, report and both, over ``repeats`` runs."""
    dataset = synthetic_study(n, seed=seed, dropout_rate=0.1)
    build_report(analyse_study(dataset))  # warm-up: imports, plotly.js read, caches
    analysis_times, report_times, totals = [], [], []
    size = 0
    for _ in range(repeats):
        start = time.perf_counter()
        result = analyse_study(dataset)
        middle = time.perf_counter()
        html = build_report(result)
        end = time.perf_counter()
        analysis_times.append(middle - start)
        report_times.append(end - middle)
        totals.append(end - start)
        size = len(html.encode("utf-8"))
    return {
        "analysis_median": statistics.median(analysis_times),
        "report_median": statistics.median(report_times),
        "total_median": statistics.median(totals),
        "total_best": min(totals),
        "total_worst": max(totals),
        "responses": float(len(dataset.responses)),
        "steps": float(len(dataset.steps)),
        "report_mb": size / 1e6,
    }


def main() -> None:
    """Parse arguments, run the sizes, print one line each."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=sorted(TARGETS))
    parser.add_argument("--repeats", type=int, default=0, help="default 5 (≤ 1,000) or 3")
    parser.add_argument("--seed", type=int, default=20261122)
    args = parser.parse_args()
    print(
        f"# {platform.python_implementation()} {platform.python_version()}, "
        f"nproc={os.cpu_count()}, CPU: {cpu_model()}"
    )
    for n in args.sizes:
        repeats = args.repeats or (5 if n <= 1000 else 3)
        r = bench(n, repeats, args.seed)
        target = TARGETS.get(n)
        verdict = ""
        if target is not None:
            verdict = f"target ≤ {target:g} s: {'met' if r['total_worst'] <= target else 'MISSED'}"
        print(
            f"n={n:>6}  responses={int(r['responses']):>7}  steps={int(r['steps']):>7}  "
            f"analysis {r['analysis_median']:.3f} s + report {r['report_median']:.3f} s = "
            f"{r['total_median']:.3f} s median (best {r['total_best']:.3f}, worst "
            f"{r['total_worst']:.3f}, {repeats} runs)  report {r['report_mb']:.1f} MB  {verdict}"
        )


if __name__ == "__main__":
    main()
