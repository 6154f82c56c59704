"""Simulated power of the mixed model: agrees with the analytic power where they coincide."""

from __future__ import annotations

import numpy as np
import pytest
from statsmodels.stats.proportion import proportion_confint

from analysis.errors import InvalidInputError
from analysis.power import PowerDesign, effect_sizes_from_means
from analysis.power_simulation import effect_pattern, simulate_power, wilson_interval


def test_wilson_interval_matches_statsmodels() -> None:
    for successes, trials in [(0, 20), (7, 20), (118, 200), (200, 200)]:
        expected = proportion_confint(successes, trials, alpha=0.05, method="wilson")
        assert wilson_interval(successes, trials) == pytest.approx(expected, abs=1e-12)


@pytest.mark.parametrize("effect", ["between", "within", "interaction"])
def test_patterns_have_the_asked_f_and_no_other_effect(effect: str) -> None:
    sizes = effect_sizes_from_means(effect_pattern(effect, 0.3, 3, 4), 1.0)
    for name in ("between", "within", "interaction"):
        assert sizes[name] == pytest.approx(0.3 if name == effect else 0.0, abs=1e-12)


def test_simulated_power_agrees_with_the_analytic_in_a_balanced_compound_symmetric_case() -> None:
    # Balanced, complete, compound symmetric (ρ = .5, ε = 1): the random-intercept model's F
    # and df are the RM-ANOVA's, so the analytic (G*Power) power is the simulation's truth.
    design = PowerDesign("interaction", 2, 3, 0.5)
    analytic = design.power(0.25, 16)
    simulated = simulate_power(
        "interaction",
        means=effect_pattern("interaction", 0.25, 2, 3),
        sd=1.0,
        rho=0.5,
        n_total=16,
        replicates=200,
        seed=2026,
    )
    assert simulated.ci_low <= analytic <= simulated.ci_high
    assert simulated.failures == 0
    assert simulated.mean_df2 == pytest.approx(design.degrees_of_freedom(16)[1], rel=0.02)


def test_the_same_seed_gives_the_same_figures() -> None:
    kwargs = {
        "means": effect_pattern("between", 0.4, 2, 3),
        "sd": 2.0,
        "rho": 0.3,
        "n_total": 10,
        "replicates": 15,
    }
    first = simulate_power("between", seed=5, **kwargs)  # type: ignore[arg-type]
    again = simulate_power("between", seed=5, **kwargs)  # type: ignore[arg-type]
    assert first == again
    assert first.to_dict()["model"].startswith("rating ~ condition * session")


@pytest.mark.parametrize(
    ("changes", "words"),
    [
        ({"rho": -0.1}, "rho"),
        ({"n_total": 9}, "multiple"),
        ({"replicates": 0}, "1 or more"),
        ({"sd": 0.0}, "SD"),
        ({"means": np.zeros((1, 3))}, "2 or more groups"),
    ],
)
def test_bad_simulation_input_is_one_line(changes: dict[str, object], words: str) -> None:
    kwargs: dict[str, object] = {
        "means": np.zeros((2, 3)),
        "sd": 1.0,
        "rho": 0.5,
        "n_total": 10,
        "replicates": 5,
    }
    kwargs.update(changes)
    with pytest.raises(InvalidInputError, match=words):
        simulate_power("within", **kwargs)  # type: ignore[arg-type]
