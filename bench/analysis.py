"""Benchmark: full analysis + HTML report for 24 and 10,000 synthetic participants.

Run from the repository root::

    .venv/bin/python bench/analysis.py            # both sizes, 5 repeats (24) / 3 (10,000)
    .venv/bin/python bench/analysis.py --sizes 24 --repeats 10
    .venv/bin/python bench/analysis.py --mixed     # the mixed models: 24 and 1,000
    .venv/bin/python bench/analysis.py --vs-r      # linear mixed models against lme4/lmerTest

Targets (issue 7): 24 participants ≤ 0.5 s, 10,000 participants ≤ 5 s, for
``analyse_study`` (scoring, five mixed ANOVAs with descriptives, marginal means and post-hoc
tests, questionnaire scores, adaptation curves) plus ``build_report`` (the self-contained HTML
with every figure). Data generation is seeded and not timed. Prints one line per size and
phase; results go to docs/performance.md ("## Analysis"). Never used as a test assertion.

With ``--mixed`` (issue 23): the mixed models (:func:`analysis.mixed_models.analyse_mixed_models`)
of 24 and 1,000 participants: per trust measure (the linear mixed models with the random slope
and their comparison, the proportional-odds model with its check, the four adaptation-and-trust
models) against the targets 2 s and 20 s, and for all five measures of the study.

With ``--vs-r`` (issue 49): the linear mixed models of 24, 100, 1,000 and 10,000 participants
(the trust score, the mean of two trust items, of a synthetic 2 × 4 study with 10 % dropout)
against lme4/lmerTest on the same data written to CSV: in-process (``linear_mixed_models``
against ``lmer`` + ``anova(type = 3)`` + ``summary`` timed with ``system.time`` by
bench/lmer.R), and from the command line (``trustlab mixed --json`` against ``Rscript
bench/lmer.R``, start-up included). "slope" fits both models on both sides, as ``trustlab mixed
--random-slope`` does. Medians over repeats, the ratio from the same run, the largest relative
difference of the numbers (estimates, SEs, df, F, p), and the peak memory (RSS) of both
processes at the largest N. Without ``Rscript`` and lmerTest the R columns are skipped.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

# Run as a script, this file's folder is first on sys.path and "analysis" would resolve to this
# very file instead of the package: put the repository root first instead.
_ROOT = Path(__file__).resolve().parents[1]
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _ROOT / "bench"]
sys.path.insert(0, str(_ROOT))

from analysis.lmm import LinearMixedModels, linear_mixed_models  # noqa: E402
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


VS_R_SIZES = (24, 100, 1000, 10_000)
"""Participants of the lme4 comparison (issue 49)."""
_LMER_R = _ROOT / "bench" / "lmer.R"


def vs_r_data(n: int, seed: int) -> pd.DataFrame:
    """participant, condition, session, trust: the mean of the first two trust items of a
    synthetic study (10 % dropout), so the CLI fits no ordinal model (not one item)."""
    outcomes = analyse_study(synthetic_study(n, seed=seed, dropout_rate=0.1)).outcomes[:2]
    keys = ["participant", "condition", "session"]
    first, second = (o.data.set_index(keys)["value"] for o in outcomes)
    trust = pd.concat([first, second], axis=1).mean(axis=1).rename("trust")
    return trust.reset_index()


def r_available() -> str:
    """Empty when ``Rscript`` with lmerTest and jsonlite runs, else why not."""
    if shutil.which("Rscript") is None:
        return "no Rscript on PATH"
    check = subprocess.run(
        ["Rscript", "-e", "library(lmerTest); library(jsonlite)"], capture_output=True, text=True
    )
    return "" if check.returncode == 0 else "Rscript cannot load lmerTest and jsonlite"


def _fit(data: pd.DataFrame, model: str) -> LinearMixedModels:
    return linear_mixed_models(
        data,
        dv="trust",
        within="session",
        between="condition",
        subject="participant",
        random_slope=model == "slope",
    )


def _trustlab_seconds(data: pd.DataFrame, model: str, repeats: int) -> tuple[float, Any]:
    result = _fit(data, model)  # warm-up: patsy's first formula
    seconds = []
    for _ in range(repeats):
        start = time.perf_counter()
        result = _fit(data, model)
        seconds.append(time.perf_counter() - start)
    return statistics.median(seconds), result


def _differences(result: LinearMixedModels, r_values: dict[str, Any]) -> float:
    """Largest relative difference of trustlab's numbers from lmerTest's (estimates, SEs, df,
    F, denominator df and p; p values below 1e-10 are left out: at p = 1e-277 a difference of
    3e-8 in F is 2e-5 in p)."""
    worst = 0.0
    for fit in result.models:
        theirs = r_values["intercept" if fit.name == "random intercept" else "slope"]
        pairs = [(fit.fixed[c], theirs[c]) for c in ("estimate", "se", "df")] + [
            (fit.tests[c], theirs[c]) for c in ("F", "df2", "p")
        ]
        for ours, reference in pairs:
            a, b = np.asarray(ours, float), np.atleast_1d(np.asarray(reference, float))
            # A p below 1e-10 amplifies the rounding of F (1e-8) a thousandfold: left out.
            shown = np.abs(b) >= 1e-10
            gaps = np.abs(a - b)[shown] / np.abs(b)[shown]
            worst = max(worst, float(gaps.max(initial=0.0)))
    return worst


def _wall(command: list[str], repeats: int, **kwargs: Any) -> float:
    seconds = []
    for _ in range(repeats):
        start = time.perf_counter()
        subprocess.run(command, check=True, capture_output=True, **kwargs)
        seconds.append(time.perf_counter() - start)
    return statistics.median(seconds)


def _trustlab_command(csv: Path, model: str) -> list[str]:
    args = ["--dv", "trust", "--within", "session", "--between", "condition"]
    args += ["--subject", "participant", "--json"]
    slope = ["--random-slope"] if model == "slope" else []
    return [
        sys.executable,
        "-c",
        "from app.cli import main; main()",
        "mixed",
        str(csv),
        *args,
        *slope,
    ]


_PEAK_RSS = """
import resource, subprocess, sys
subprocess.run(sys.argv[1:], check=True, capture_output=True)
print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024)
"""
_FIT_RSS = """
import sys, pandas as pd
from analysis.lmm import linear_mixed_models

def peak():  # VmHWM: this process's own peak (ru_maxrss can carry the parent's over exec)
    for line in open("/proc/self/status"):
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024

data = pd.read_csv(sys.argv[1])
before = peak()
linear_mixed_models(data, dv="trust", within="session", between="condition",
                    subject="participant", random_slope=True)
print(before, peak())
"""


def _peak_mb(command: list[str]) -> float:
    """Peak RSS (MB) of ``command`` run as the only child of a fresh interpreter."""
    done = subprocess.run(
        [sys.executable, "-c", _PEAK_RSS, *command], check=True, capture_output=True, text=True
    )
    return float(done.stdout.strip())


def bench_vs_r(sizes: list[int], repeats: int, cli_repeats: int, seed: int) -> None:
    """Print the trustlab vs lme4/lmerTest table (issue 49)."""
    missing = r_available()
    if missing:
        print(f"# R part skipped: {missing}")
    env = {**os.environ, "PYTHONPATH": str(_ROOT)}
    print(
        f"{'N':>6} {'model':>9} {'ratings':>7} | {'trustlab':>8} {'lme4':>7} {'ratio':>5} | "
        f"{'CLI':>6} {'Rscript':>7} {'ratio':>5} | max rel diff"
    )
    with tempfile.TemporaryDirectory() as folder:
        csv = Path(folder) / "trust.csv"
        for n in sizes:
            data = vs_r_data(n, seed)
            data.to_csv(csv, index=False)
            runs = repeats or (5 if n <= 1000 else 3)
            for model in ("intercept", "slope"):
                ours, result = _trustlab_seconds(data, model, runs)
                cli = _wall(_trustlab_command(csv, model), cli_repeats, cwd=_ROOT, env=env)
                cells = f"{ours:8.3f} {'':>7} {'':>5} | {cli:6.2f} {'':>7} {'':>5} |"
                if not missing:
                    done = subprocess.run(
                        ["Rscript", str(_LMER_R), str(csv), model, str(runs)],
                        check=True,
                        capture_output=True,
                        text=True,
                    )
                    r = json.loads(done.stdout)
                    theirs = statistics.median(np.atleast_1d(r["seconds"]).tolist())
                    rscript = _wall(["Rscript", str(_LMER_R), str(csv), model, "0"], cli_repeats)
                    cells = (
                        f"{ours:8.3f} {theirs:7.3f} {ours / theirs:5.2f} | {cli:6.2f} "
                        f"{rscript:7.2f} {cli / rscript:5.2f} | "
                        f"{_differences(result, r['values']):.1e}"
                    )
                print(f"{n:>6} {model:>9} {len(data.dropna()):>7} | {cells}", flush=True)
        start_up = _wall([sys.executable, "-c", "import app.cli"], cli_repeats, cwd=_ROOT, env=env)
        print(f"of which trustlab's start-up (python -c 'import app.cli'): {start_up:.2f} s")
        n = max(sizes)
        data = vs_r_data(n, seed)
        data.to_csv(csv, index=False)
        fit = subprocess.run(
            [sys.executable, "-c", _FIT_RSS, str(csv)],
            check=True,
            capture_output=True,
            text=True,
            cwd=_ROOT,
            env=env,
        )
        before, after = (float(v) for v in fit.stdout.split())
        line = (
            f"peak RSS at N={n:,} (both models): trustlab in-process {after:.0f} MB "
            f"({before:.0f} MB before the fit), trustlab mixed "
            f"{_peak_mb(_trustlab_command(csv, 'slope')):.0f} MB"
        )
        if not missing:
            line += (
                f", Rscript {_peak_mb(['Rscript', str(_LMER_R), str(csv), 'slope', '1']):.0f} MB"
            )
        print(line)


def main() -> None:
    """Parse arguments, run the sizes, print one line each."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--sizes", type=int, nargs="+", help="default 24 and 10,000 (with --mixed: 24 and 1,000)"
    )
    parser.add_argument("--repeats", type=int, default=0, help="default 5 (≤ 1,000) or 3")
    parser.add_argument("--seed", type=int, default=20261122)
    parser.add_argument("--mixed", action="store_true", help="benchmark the mixed models")
    parser.add_argument(
        "--vs-r", action="store_true", help="linear mixed models against lme4/lmerTest"
    )
    parser.add_argument("--cli-repeats", type=int, default=3, help="command-line runs (--vs-r)")
    args = parser.parse_args()
    print(
        f"# {platform.python_implementation()} {platform.python_version()}, "
        f"nproc={os.cpu_count()}, CPU: {cpu_model()}"
    )
    if args.vs_r:
        bench_vs_r(args.sizes or list(VS_R_SIZES), args.repeats, args.cli_repeats, args.seed)
        return
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
