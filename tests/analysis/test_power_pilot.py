"""A pilot's ρ, ε, variance components and effects, with seeded bootstrap intervals."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from analysis.anova import mixed_anova
from analysis.errors import InvalidInputError
from analysis.power_pilot import PILOT_QUANTITIES, estimate_pilot

KW = {"dv": "y", "within": "session", "between": "condition", "subject": "participant"}


def _pilot(n_per_group: int, rho: float, seed: int = 3, sessions: int = 4) -> pd.DataFrame:
    """Compound-symmetric ratings (σ = 1) with a growing C2 − C1 difference."""
    rng = np.random.default_rng(seed)
    rows = []
    for g, condition in enumerate(("C1", "C2")):
        for i in range(n_per_group):
            u = rng.normal(0, np.sqrt(rho))
            for s in range(sessions):
                y = 3 + 0.2 * g * s + u + rng.normal(0, np.sqrt(1 - rho))
                rows.append((f"{condition}-{i}", condition, s + 1, y))
    return pd.DataFrame(rows, columns=["participant", "condition", "session", "y"])


def test_a_large_pilot_recovers_rho_epsilon_and_the_variances() -> None:
    estimate = estimate_pilot(_pilot(300, 0.6), **KW, replicates=0)
    values = estimate.estimates
    assert values["rho"] == pytest.approx(0.6, abs=0.04)
    assert values["epsilon"] > 0.95
    assert values["var_participant"] == pytest.approx(0.6, abs=0.08)
    assert values["var_residual"] == pytest.approx(0.4, abs=0.03)
    # the interaction pattern 0.2 · g · s has residual SD 0.2 · sqrt(5/16) = 0.1118
    assert values["f_interaction"] == pytest.approx(0.1118, abs=0.03)


def test_epsilon_is_the_anovas_greenhouse_geisser() -> None:
    data = _pilot(6, 0.5, seed=11)
    estimate = estimate_pilot(data, **KW, replicates=0)
    anova = mixed_anova(data, **KW)
    assert estimate.estimates["epsilon"] == pytest.approx(anova.sphericity.eps_gg, rel=1e-10)


def test_bootstrap_intervals_hold_the_estimate_and_a_seed_repeats_them() -> None:
    data = _pilot(8, 0.5)
    first = estimate_pilot(data, **KW, replicates=200, seed=42)
    again = estimate_pilot(data, **KW, replicates=200, seed=42)
    other = estimate_pilot(data, **KW, replicates=200, seed=43)
    assert first.intervals == again.intervals
    assert first.intervals != other.intervals
    for name in ("rho", "sd", "var_residual"):
        low, high = first.intervals[name]
        assert low < first.estimates[name] < high
    payload = first.to_dict()
    assert list(payload["estimates"]) == list(PILOT_QUANTITIES)
    assert payload["n_per_group"] == [8, 8] and payload["bootstrap"]["seed"] == 42


def test_too_small_a_pilot_is_refused_in_one_line() -> None:
    data = _pilot(5, 0.5)
    data = data[~data["participant"].isin(["C2-0", "C2-1"])]
    with pytest.raises(InvalidInputError, match=r"4 or more participants .* C2: 3$"):
        estimate_pilot(data, **KW)
    single = _pilot(5, 0.5, sessions=1)
    with pytest.raises(InvalidInputError, match="two or more sessions") as caught:
        estimate_pilot(single, **KW)
    assert "\n" not in str(caught.value)
