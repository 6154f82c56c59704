"""Simulated power of the ordinal model: its population, its seed, its size and power, bad input."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from analysis.errors import InvalidInputError
from analysis.power_ordinal import (
    LatentOrdinalModel,
    equally_spaced_thresholds,
    latent_model,
    observed_proportions,
    pilot_latent_model,
    simulate_ordinal_power,
)
from analysis.power_simulation import effect_pattern


def test_thresholds_reproduce_the_pilots_category_proportions() -> None:
    shares = [0.05, 0.15, 0.4, 0.3, 0.1]
    population = latent_model(np.zeros((2, 4)), rho=0.6, proportions=shares)
    assert population.category_proportions() == pytest.approx(shares, abs=1e-6)
    assert population.rho == pytest.approx(0.6)
    # The default cuts ±2 latent SD into K equal bins: symmetric, centre-heavy.
    default = latent_model(np.zeros((2, 4)), rho=0.5, categories=5).category_proportions()
    assert default == pytest.approx(default[::-1]) and default.argmax() == 2
    assert equally_spaced_thresholds(3, 0.0) == pytest.approx(
        np.array([-2, 2]) / 3 * np.pi / np.sqrt(3)
    )


def test_an_f_is_read_on_the_latent_scale() -> None:
    population = latent_model(effect_pattern("within", 0.3, 2, 4), rho=0.4)
    assert population.effect_sizes() == pytest.approx(
        {"between": 0.0, "within": 0.3, "interaction": 0.0}, abs=1e-12
    )


def test_the_same_seed_gives_the_same_figures() -> None:
    population = latent_model(effect_pattern("between", 0.5, 2, 3), rho=0.3, categories=4)
    kwargs = {"population": population, "n_total": 10, "replicates": 8}
    first = simulate_ordinal_power("between", seed=11, **kwargs)  # type: ignore[arg-type]
    again = simulate_ordinal_power("between", seed=11, **kwargs)  # type: ignore[arg-type]
    assert repr(first) == repr(again)  # equal, and mean_df2 is NaN (no df for a χ²)
    assert first.to_dict()["kind"] == "ordinal"
    assert first.to_dict()["model"].startswith("rating ~ condition * session, proportional odds")


def test_no_effect_rejects_at_about_alpha_and_a_large_effect_almost_always() -> None:
    # 32 datasets of 16 participants each: the Wilson interval of a rate near .05 is about
    # [.01, .2]. (With 400 datasets the between test's rate is .055 at N = 12, .038 at 24.)
    null = latent_model(effect_pattern("between", 0.0, 2, 4), rho=0.5)
    size = simulate_ordinal_power("between", population=null, n_total=16, replicates=32, seed=3)
    assert size.ci_low <= 0.05 <= size.ci_high
    large = latent_model(effect_pattern("between", 1.0, 2, 4), rho=0.5)
    power = simulate_ordinal_power("between", population=large, n_total=16, replicates=32, seed=3)
    assert power.power >= 0.9 and power.power > size.power + 0.5
    assert power.failures == size.failures == 0


def test_a_pilots_fitted_model_gives_back_the_population_it_came_from() -> None:
    # 3,000 participants drawn from a known latent population (between and session effects,
    # rho .5): the marginal fit, rescaled to the participant level, recovers it (within
    # sampling error and the logistic-normal approximation; checked to ±0.12 with two seeds).
    truth = LatentOrdinalModel(
        cell_means=np.array([[-0.6, -0.2, 0.2, 0.6], [0.4, 0.8, 1.2, 1.6]]),
        thresholds=np.array([-2.5, -0.8, 0.8, 2.5]),
        participant_sd=float(np.sqrt(np.pi**2 / 3)),  # rho = .5
        source="test",
    )
    rng = np.random.default_rng(41)
    n, m = 3000, 4
    group = np.repeat(np.arange(n) % 2, m)
    session = np.tile(np.arange(m), n)
    latent = (
        truth.cell_means[group, session]
        + np.repeat(rng.normal(0, truth.participant_sd, n), m)
        + rng.logistic(0, 1, n * m)
    )
    data = pd.DataFrame(
        {
            "participant": np.repeat(np.arange(n), m),
            "condition": np.where(group == 0, "C1", "C2"),
            "session": session + 1,
            "trust": np.searchsorted(truth.thresholds, latent) + 1,
        }
    )
    fitted = pilot_latent_model(
        data, dv="trust", within="session", between="condition", subject="participant", rho=0.5
    )
    assert "pilot's fitted ordinal model" in fitted.source
    # Effects are identified up to the thresholds' location: compare centred.
    centre = truth.cell_means.mean()
    assert fitted.cell_means - fitted.cell_means.mean() == pytest.approx(
        truth.cell_means - centre, abs=0.2
    )
    assert fitted.thresholds - fitted.cell_means.mean() == pytest.approx(
        truth.thresholds - centre, abs=0.2
    )


@pytest.mark.parametrize(
    ("make", "words"),
    [
        (lambda: latent_model(np.zeros((2, 4)), rho=0.5, categories=2), "3 to 11 rating"),
        (lambda: latent_model(np.zeros((2, 4)), rho=1.0), r"rho must be in \[0, 1\)"),
        (lambda: observed_proportions([1.0, 2.5, 3.0], "trust_mean"), "one rating item"),
        (lambda: observed_proportions([1, 2, 2, 1], "trust_1"), "uses 2"),
        (lambda: latent_model(np.zeros((1, 4)), rho=0.5), "2 or more groups"),
        (
            lambda: simulate_ordinal_power(
                "between",
                population=latent_model(np.zeros((2, 3)), rho=0),
                n_total=9,
                replicates=3,
            ),
            "multiple",
        ),
    ],
)
def test_bad_input_is_one_line(make: object, words: str) -> None:
    with pytest.raises(InvalidInputError, match=words) as caught:
        make()  # type: ignore[operator]
    assert "\n" not in str(caught.value)
