"""Benchmark: analytic power questions and simulation-based power of the mixed and ordinal models.

Run from the repository root::

    OMP_NUM_THREADS=1 nice -n 10 .venv/bin/python bench/power.py
    .venv/bin/python bench/power.py --datasets 200 --repeats 50 --ordinal-datasets 100

Targets: simulation-based power for the random-intercept model with 1,000 simulated datasets at
N = 24 × 4 sessions ≤ 60 s on the 2-core machine; analytic power ≤ 50 ms per question (power
for N, N for a target power, detectable effect; the median and the worst of ``--repeats``).
The ordinal model (no target: recorded) is timed with ``--ordinal-datasets`` (default 200) at
the same N, five categories with equally spaced thresholds, the interaction with latent f = .2.
Prints one line per figure; results go to docs/performance.md ("## Power"). Never used as a
test assertion.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time
from pathlib import Path

_ROOT = Path(__file__).resolve().parents[1]
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _ROOT / "bench"]
sys.path.insert(0, str(_ROOT))

from analysis.power import (  # noqa: E402
    PowerDesign,
    detectable_effect,
    n_for_power,
    power_for_n,
)
from analysis.power_ordinal import latent_model, simulate_ordinal_power  # noqa: E402
from analysis.power_simulation import effect_pattern, simulate_power  # noqa: E402

ANALYTIC_TARGET = 0.050
SIMULATION_TARGET = 60.0


def _analytic(repeats: int) -> dict[str, list[float]]:
    questions = {
        "power for N": lambda d: power_for_n(d, f=0.25, n_total=24),
        "N for power .80": lambda d: n_for_power(d, f=0.1, target=0.8),
        "detectable f": lambda d: detectable_effect(d, n_total=24, target=0.8),
    }
    times: dict[str, list[float]] = {name: [] for name in questions}
    for _ in range(repeats):
        for effect in ("between", "within", "interaction"):
            design = PowerDesign(effect, 2, 4, 0.5, epsilon=0.8 if effect != "between" else 1)
            for name, ask in questions.items():
                start = time.perf_counter()
                ask(design)
                times[name].append(time.perf_counter() - start)
    return times


def main() -> None:
    """Time the analytic questions and the simulation; print the figures."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--datasets", type=int, default=1000)
    parser.add_argument("--ordinal-datasets", type=int, default=200)
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument("--seed", type=int, default=2026)
    args = parser.parse_args()
    print(
        f"python {platform.python_version()}, nproc {os.cpu_count()}, "
        f"OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', 'unset')}"
    )
    for name, times in _analytic(args.repeats).items():
        median, worst = statistics.median(times), max(times)
        verdict = "met" if worst <= ANALYTIC_TARGET else "MISSED"
        print(
            f"analytic {name:<16} median {median * 1000:.2f} ms, worst {worst * 1000:.2f} ms "
            f"({len(times)} questions) — target ≤ {ANALYTIC_TARGET * 1000:.0f} ms: {verdict}"
        )
    start = time.perf_counter()
    result = simulate_power(
        "interaction",
        means=effect_pattern("interaction", 0.2, 2, 4),
        sd=1.0,
        rho=0.5,
        n_total=24,
        replicates=args.datasets,
        seed=args.seed,
    )
    elapsed = time.perf_counter() - start
    analytic = PowerDesign("interaction", 2, 4, 0.5).power(0.2, 24)
    verdict = "met" if elapsed <= SIMULATION_TARGET else "MISSED"
    print(
        f"simulation {args.datasets} datasets, N = 24 × 4: {elapsed:.1f} s "
        f"({elapsed / args.datasets * 1000:.1f} ms each) — target ≤ {SIMULATION_TARGET:.0f} s: "
        f"{verdict}; power {result.power:.3f} [{result.ci_low:.3f}, {result.ci_high:.3f}], "
        f"analytic {analytic:.3f}, failures {result.failures}"
    )
    if args.ordinal_datasets:
        population = latent_model(effect_pattern("interaction", 0.2, 2, 4), rho=0.5)
        start = time.perf_counter()
        ordinal = simulate_ordinal_power(
            "interaction",
            population=population,
            n_total=24,
            replicates=args.ordinal_datasets,
            seed=args.seed,
        )
        elapsed = time.perf_counter() - start
        print(
            f"ordinal simulation {args.ordinal_datasets} datasets, N = 24 × 4, 5 categories: "
            f"{elapsed:.1f} s ({elapsed / args.ordinal_datasets * 1000:.0f} ms each); power "
            f"{ordinal.power:.3f} [{ordinal.ci_low:.3f}, {ordinal.ci_high:.3f}], "
            f"failures {ordinal.failures}"
        )


if __name__ == "__main__":
    main()
