"""Fitting a population from a step log (issue 20): the answers the analysis package reads from
the steps table, fitted with the adaptation engine's population model (models/population.py), as
the analysis package's verified population file.

Here in the app because it joins the two: analysis knows only pandas and statistics, models only
numpy and torch (docs: DESIGN, "Layout").
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import pandas as pd

from analysis.population import Population, answers_from_steps, steps_sha256
from models.population import AnswerSequences, bootstrap, fit_category


def sequences_from_steps(
    steps: pd.DataFrame, arms: dict[str, int] | None = None
) -> dict[str, AnswerSequences]:
    """Each category's answer sequences, as :func:`analysis.population.answers_from_steps`
    reads them (which see, also for the errors), for the engine's model."""
    return {
        name: AnswerSequences(answers.n_arms, answers.actions, answers.answers)
        for name, answers in answers_from_steps(steps, arms).items()
    }


def fit_population(
    steps: pd.DataFrame,
    source: dict[str, Any],
    *,
    arms: dict[str, int] | None = None,
    replicates: int = 200,
    seed: int = 0,
    progress: Callable[[], None] | None = None,
) -> Population:
    """Fit every category of ``steps`` with bootstrap intervals over participants."""
    rng = np.random.default_rng(seed)
    categories: dict[str, Any] = {}
    for name, seq in sequences_from_steps(steps, arms).items():
        try:
            fit = fit_category(seq)
        except ValueError as exc:
            raise ValueError(f"category {name!r}: {exc}") from None
        intervals = bootstrap(seq, fit, rng, replicates=replicates, progress=progress)
        categories[name] = {
            "arms": seq.n_arms,
            "participants": seq.participants,
            "answers": int(seq.observed.sum()),
            "prior": fit.prior.tolist(),
            "prior_ci": intervals.prior.tolist(),
            "slip": fit.slip,
            "slip_ci": list(intervals.slip),
            "hazard": fit.hazard,
            "hazard_ci": list(intervals.hazard),
            "log_likelihood": fit.log_likelihood,
            "iterations": fit.iterations,
            "converged": fit.converged,
        }
    if not categories:
        raise ValueError("the steps table has no answers to fit")
    content = {
        "source": {**source, "steps_sha256": steps_sha256(steps)},
        "categories": categories,
        "bootstrap": {"replicates": replicates, "level": 0.95, "seed": seed},
    }
    return Population.of(content)
