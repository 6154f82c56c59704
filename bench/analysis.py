"""Benchmark: full analysis + HTML report for 24 and 10,000 synthetic participants.

Run from the repository root::

    .venv/bin/python bench/analysis.py            # both sizes, 5 repeats (24) / 3 (10,000)
    .venv/bin/python bench/analysis.py --sizes 24 --repeats 10
    .venv/bin/python bench/analysis.py --mixed     # the mixed models: 24 and 1,000

Targets (issue 7): 24 participants ≤ 0.5 s, 10,000 participants ≤ 5 s, for
``analyse_study`` (scoring, five mixed ANOVAs with descriptives, marginal means and post-hoc
tests, questionnaire scores, adaptation curves) plus ``build_report`` (the self-contained HTML
with every figure). Data generation is seeded and not timed. Prints one line per size and
phase; results go to docs/performance.md ("## Analysis"). Never used as a test assertion.

With ``--mixed`` (issue 23): the mixed models (:func:`analysis.mixed_models.analyse_mixed_models`)
of 24 and 1,000 participants: per trust measure (the linear mixed models with the random slope
and their comparison, the proportional-odds model with its check, the four adaptation-and-trust
models) against the targets 2 s and 20 s, and for all five measures of the study.
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

from analysis.mixed_models import analyse_mixed_models  # noqa: E402
from analysis.report import build_report  # noqa: E402
from analysis.study import analyse_study  # noqa: E402
from analysis.synthetic import synthetic_study  # noqa: E402

TARGETS = {24: 0.5, 10_000: 5.0}
"""Seconds allowed for analysis + report, by number of participants."""

MIXED_TARGETS = {24: 2.0, 1000: 20.0}
"""Seconds allowed for every mixed model of one trust measure, by number of participants."""


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


def bench_mixed(n: int, repeats: int, seed: int) -> dict[str, float]:
    """Median and worst seconds of the mixed models of one measure and of all measures."""
    result = analyse_study(synthetic_study(n, seed=seed, dropout_rate=0.1))
    first = result.outcomes[0].key
    analyse_mixed_models(result, keys=[first])  # warm-up: statsmodels and patsy imports
    one, everything = [], []
    statuses: list[str] = []
    for _ in range(repeats):
        start = time.perf_counter()
        models = analyse_mixed_models(result, keys=[first])
        one.append(time.perf_counter() - start)
        start = time.perf_counter()
        analyse_mixed_models(result)
        everything.append(time.perf_counter() - start)
        lmm = models.outcomes[0].lmm
        statuses = [m.status for m in lmm.models] if lmm else [models.outcomes[0].lmm_problem]
    return {
        "one_median": statistics.median(one),
        "one_worst": max(one),
        "all_median": statistics.median(everything),
        "measures": float(len(result.outcomes)),
        "ratings": float(len(result.outcomes[0].data)),
        "converged": float(all(s == "converged" or "boundary" in s for s in statuses)),
    }


def main() -> None:
    """Parse arguments, run the sizes, print one line each."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--sizes", type=int, nargs="+", help="default 24 and 10,000 (with --mixed: 24 and 1,000)"
    )
    parser.add_argument("--repeats", type=int, default=0, help="default 5 (≤ 1,000) or 3")
    parser.add_argument("--seed", type=int, default=20261122)
    parser.add_argument("--mixed", action="store_true", help="benchmark the mixed models")
    args = parser.parse_args()
    print(
        f"# {platform.python_implementation()} {platform.python_version()}, "
        f"nproc={os.cpu_count()}, CPU: {cpu_model()}"
    )
    if args.mixed:
        for n in args.sizes or sorted(MIXED_TARGETS):
            repeats = args.repeats or (3 if n <= 100 else 1)
            r = bench_mixed(n, repeats, args.seed)
            target = MIXED_TARGETS.get(n)
            verdict = ""
            if target is not None:
                verdict = (
                    f"target ≤ {target:g} s: {'met' if r['one_worst'] <= target else 'MISSED'}"
                )
            print(
                f"n={n:>5}  ratings/measure={int(r['ratings']):>5}  one measure "
                f"{r['one_median']:.2f} s median (worst {r['one_worst']:.2f})  all "
                f"{int(r['measures'])} measures {r['all_median']:.2f} s  ({repeats} runs, "
                f"{'all converged' if r['converged'] else 'NOT ALL CONVERGED'})  {verdict}"
            )
        return
    for n in args.sizes or sorted(TARGETS):
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
