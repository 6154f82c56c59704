"""Benchmark: fitting a population from step logs (issue 20's target: 10,000 participants ≤ 10 s).

Run from the repository root::

    .venv/bin/python bench/population_fit.py                  # 10,000 participants, seed 2026
    .venv/bin/python bench/population_fit.py --participants 48 --replicates 200

Simulates participants of a known population (three categories, K = 4, 12 answers each, prior
.7/.1/.1/.1, slip .06, hazard .02) answering questions asked at random, writes them as a steps
table, and times ``app.services.sessions.population_fit.fit_population``: the point fit of every
category (the target) and, separately, the bootstrap. Prints the figures and how far the fit is from
the truth. Never a test assertion.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

_ROOT = Path(__file__).resolve().parents[1]
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _ROOT / "bench"]
sys.path.insert(0, str(_ROOT))

import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from app.services.sessions.population_fit import fit_population, sequences_from_steps  # noqa: E402
from bench.analysis import cpu_model  # noqa: E402
from models.feedback import FeedbackModel  # noqa: E402
from models.population import fit_category  # noqa: E402

PRIOR = (0.7, 0.1, 0.1, 0.1)
SLIP, HAZARD = 0.06, 0.02
CATEGORIES = ("conation", "affection", "cognition")


def simulated_steps(
    participants: int,
    seed: int,
    prior: tuple[float, ...] = PRIOR,
    model: FeedbackModel | None = None,
    categories: tuple[str, ...] = CATEGORIES,
) -> pd.DataFrame:
    """A steps table of ``participants`` of a known population, 12 answers per category to
    questions asked at random: preferred question by ``prior``, each participant's slip rate
    drawn from ``model``'s slip prior, preferences changed by its hazard (default: slip .06,
    hazard .02)."""
    rng = np.random.default_rng(seed)
    model = model or FeedbackModel(slips=(SLIP,), hazard=HAZARD)
    k = len(prior)
    frames = []
    for category in categories:
        preferred = rng.choice(k, size=participants, p=prior)
        # One slip rate: no draw, so the figures recorded before slip priors came stay the same.
        slips = (
            model.sample_slips(rng, participants)
            if len(model.slips) > 1
            else np.full(participants, model.slips[0])
        )
        actions = rng.integers(0, k, size=(participants, 12))
        answers = np.zeros((participants, 12), dtype=int)
        for t in range(12):
            answers[:, t] = (actions[:, t] == preferred) != (rng.random(participants) < slips)
            preferred = model.change_preference(rng, preferred, np.asarray(prior))
        frames.append(
            pd.DataFrame(
                {
                    "participant": np.repeat(np.arange(participants), 12),
                    "category": category,
                    "session": np.tile(np.repeat(np.arange(4), 3), participants),
                    "run": np.tile(np.tile(np.arange(1, 4), 4), participants),
                    "iteration": np.tile(np.arange(12), participants),
                    "action": actions.ravel(),
                    "answer": answers.ravel(),
                }
            )
        )
    return pd.concat(frames, ignore_index=True)


def main() -> None:
    """Time the point fit and the bootstrap; print the error against the true population."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--participants", type=int, default=10_000)
    parser.add_argument("--replicates", type=int, default=20)
    parser.add_argument("--seed", type=int, default=2026)
    args = parser.parse_args()
    print(
        f"# {platform.python_implementation()} {platform.python_version()}, "
        f"nproc={os.cpu_count()}, CPU: {cpu_model()}; {args.participants} participants × 3 "
        f"categories × 12 answers, seed {args.seed}"
    )
    steps = simulated_steps(args.participants, args.seed)
    arms = dict.fromkeys(CATEGORIES, 4)
    start = time.perf_counter()
    sequences = sequences_from_steps(steps, arms)
    fits = {name: fit_category(seq) for name, seq in sequences.items()}
    point = time.perf_counter() - start
    print(
        f"point fit (steps → sequences → EM, 3 categories): {point:.2f} s (target ≤ 10 s: "
        f"{'met' if point <= 10 else 'MISSED'})"
    )
    for name, fit in fits.items():
        error = np.abs(fit.prior - np.asarray(PRIOR)).max()
        print(
            f"  {name}: prior {np.round(fit.prior, 3).tolist()} (max error {error:.3f}), slip "
            f"{fit.slip:.4f} (true {SLIP}), hazard {fit.hazard:.4f} (true {HAZARD}), "
            f"{fit.iterations} EM iterations"
        )
    start = time.perf_counter()
    fit_population(steps, {"steps": "simulated"}, arms=arms, replicates=args.replicates)
    whole = time.perf_counter() - start
    per = (whole - point) / (args.replicates * len(CATEGORIES))
    print(
        f"with {args.replicates} bootstrap resamples per category: {whole:.2f} s "
        f"(≈ {per * 1000:.0f} ms per resample and category)"
    )


if __name__ == "__main__":
    main()
