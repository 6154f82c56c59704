"""Analytic power of the mixed RM-ANOVA: published G*Power figures, independent algebra, shape."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pingouin as pg
import pytest
from scipy import stats

from analysis.anova import orthonormal_contrasts
from analysis.errors import InvalidInputError
from analysis.power import (
    PowerDesign,
    detectable_effect,
    effect_sizes_from_means,
    eta2_from_f,
    f_from_eta2,
    n_for_power,
    power_for_n,
)

# ------------------------------------------------------------------ published G*Power figures


def test_gpower_one_way_within_under_both_conventions() -> None:
    # One-way RM-ANOVA, 3 levels, partial η² = .05, α = .05, power .80. G*Power 3.1 gives
    # N = 33 with its default (ρ = .5, ε = 1) and N = 95 with the option "as in SPSS":
    # M. Gallucci, "Repeated Measures: software inconsistency", PAMLj 0.8.0 documentation,
    # https://pamlj.github.io/rosetta_factorial_n.html
    f = f_from_eta2(0.05)
    assert n_for_power(PowerDesign("within", 1, 3, 0.5), f=f, target=0.8).n_total == 33
    spss = PowerDesign("within", 1, 3, None, convention="spss")
    assert n_for_power(spss, f=f, target=0.8).n_total == 95


def test_gpower_within_with_no_correlation() -> None:
    # f = .25, α = .05, power .95, one group, 3 measurements, r = 0: G*Power total N = 84
    # (stats.stackexchange.com/q/68754, answer quoting G*Power's "ANOVA: Repeated measures,
    # within factors").
    assert n_for_power(PowerDesign("within", 1, 3, 0.0), f=0.25, target=0.95).n_total == 84


@pytest.mark.parametrize(
    ("effect", "groups", "sessions", "eta2", "n_total", "power"),
    [
        ("within", 1, 2, 0.022, 90, 0.804),
        ("between", 2, 2, 0.038, 152, 0.803),
        ("interaction", 2, 2, 0.01, 198, 0.804),
        ("within", 2, 2, 0.01, 198, 0.804),
    ],
)
def test_pwrss_examples_validated_with_gpower(
    effect: str, groups: int, sessions: int, eta2: float, n_total: int, power: float
) -> None:
    # pwrss 0.3 power.f.mixed.anova examples (ρ = .5, α = .05, power .80), whose formulas its
    # documentation says are validated with G*Power: reference/anova.mixed.md of
    # github.com/sjentsch/pwrss (the CRAN package's manual page "anova.mixed").
    design = PowerDesign(effect, groups, sessions, 0.5)  # type: ignore[arg-type]
    found = n_for_power(design, f=f_from_eta2(eta2), target=0.8)
    assert found.n_total == n_total
    assert round(found.power, 3) == power


def test_pingouin_power_rm_anova_agrees_for_one_group() -> None:
    # pingouin 0.5's power_rm_anova (tested against G*Power, its docstring says): its own
    # example η² = .1, m = 3, n = 20 gives .8913; and with ε and ρ varied it agrees everywhere.
    design = PowerDesign("within", 1, 3, 0.5)
    assert round(power_for_n(design, f=f_from_eta2(0.1), n_total=20).power, 4) == 0.8913
    for eta2, m, n, rho, eps in [
        (0.05, 4, 30, 0.3, 0.7),
        (0.02, 5, 60, 0.7, 0.4),
        (0.1, 2, 12, -0.2, 1),
    ]:
        ours = power_for_n(PowerDesign("within", 1, m, rho, eps), f=f_from_eta2(eta2), n_total=n)
        theirs = pg.power_rm_anova(eta_squared=eta2, m=m, n=n, corr=rho, epsilon=eps)
        assert ours.power == pytest.approx(theirs, abs=1e-9)


# ------------------------------------------------------------------ independent algebra


def _compound_symmetry(m: int, rho: float) -> np.ndarray:
    return (1 - rho) * np.eye(m) + rho * np.ones((m, m))


@pytest.mark.parametrize("rho", [-0.2, 0.0, 0.4, 0.8])
def test_noncentrality_equals_the_exact_one_of_a_means_table(rho: float) -> None:
    # The exact λ of each F test when every participant's measures are N(μ_g, Σ) with Σ
    # compound symmetric (σ = 1), computed from contrasts, not from the formulas under test:
    # between λ = Σ n (1'μ_g − 1'μ̄)² / 1'Σ1, within λ = N ‖C'μ̄‖² / (1 − ρ),
    # interaction λ = Σ n ‖C'(μ_g − μ̄)‖² / (1 − ρ).
    rng = np.random.default_rng(7)
    k, m, n = 3, 4, 10
    means = rng.normal(size=(k, m))
    sigma = _compound_symmetry(m, rho)
    contrasts = orthonormal_contrasts(m)
    grand = means.mean(axis=0)
    ones = np.ones(m)
    exact = {
        "between": n
        * float(np.sum((means @ ones - grand @ ones) ** 2))
        / float(ones @ sigma @ ones),
        "within": k * n * float(np.sum((contrasts.T @ grand) ** 2)) / (1 - rho),
        "interaction": n * float(np.sum(((means - grand) @ contrasts) ** 2)) / (1 - rho),
    }
    sizes = effect_sizes_from_means(means, 1.0)
    for effect, lam in exact.items():
        design = PowerDesign(effect, k, m, rho)  # type: ignore[arg-type]
        assert design.noncentrality(sizes[effect], k * n) == pytest.approx(lam, rel=1e-12)


def test_power_is_the_noncentral_f_tail() -> None:
    design = PowerDesign("interaction", 2, 4, 0.5, epsilon=0.6)
    answer = power_for_n(design, f=0.2, n_total=30)
    assert (answer.df1, answer.df2) == pytest.approx((1.8, 50.4))
    assert answer.lam == pytest.approx(0.04 * 30 * 4 * 0.6 / 0.5)
    critical = stats.f.ppf(0.95, 1.8, 50.4)
    assert answer.f_critical == pytest.approx(critical)
    assert answer.power == pytest.approx(1 - stats.ncf.cdf(critical, 1.8, 50.4, answer.lam))


def test_spss_convention_is_the_lambda_a_published_f_implies() -> None:
    # Seed paper: F(1, 22) = 4.794, η² = .179 and F(3, 66) = 5.629, η² = .204 (N = 24, 2 × 4).
    between = power_for_n(
        PowerDesign("between", 2, 4, None, convention="spss"), f=f_from_eta2(0.179), n_total=24
    )
    inter = power_for_n(
        PowerDesign("interaction", 2, 4, None, convention="spss"), f=f_from_eta2(0.204), n_total=24
    )
    assert between.lam == pytest.approx(4.794, abs=0.01)
    assert inter.lam == pytest.approx(5.629 * 3, abs=0.05)
    assert (between.df1, between.df2, inter.df1, inter.df2) == (1, 22, 3, 66)


# ------------------------------------------------------------------ shape of the answers


@pytest.mark.parametrize("effect", ["between", "within", "interaction"])
def test_power_rises_with_n_and_f(effect: str) -> None:
    design = PowerDesign(effect, 2, 4, 0.5, epsilon=0.8 if effect != "between" else 1)  # type: ignore[arg-type]
    by_n = [design.power(0.25, n) for n in range(6, 80, 2)]
    by_f = [design.power(f, 24) for f in np.linspace(0, 0.4, 21)]  # below saturation
    assert all(b > a for a, b in itertools.pairwise(by_n))
    assert all(b > a for a, b in itertools.pairwise(by_f))
    assert by_f[0] == pytest.approx(0.05)


@pytest.mark.parametrize("effect", ["within", "interaction"])
def test_within_power_rises_with_rho_and_epsilon(effect: str) -> None:
    by_rho = [PowerDesign(effect, 2, 4, r).power(0.2, 24) for r in np.linspace(-0.3, 0.9, 13)]  # type: ignore[arg-type]
    by_eps = [PowerDesign(effect, 2, 4, 0.5, e).power(0.2, 24) for e in (1 / 3, 0.5, 0.75, 1)]  # type: ignore[arg-type]
    assert all(b > a for a, b in itertools.pairwise(by_rho))
    assert all(b > a for a, b in itertools.pairwise(by_eps))


def test_between_power_falls_with_rho() -> None:
    by_rho = [PowerDesign("between", 2, 4, r).power(0.3, 24) for r in (0.0, 0.3, 0.6, 0.9)]
    assert all(b < a for a, b in itertools.pairwise(by_rho))


@pytest.mark.parametrize("groups", [2, 3])
def test_sample_size_is_the_smallest_multiple_of_k_that_reaches_the_target(groups: int) -> None:
    design = PowerDesign("interaction", groups, 4, 0.5)
    found = n_for_power(design, f=0.2, target=0.9)
    assert found.n_total % groups == 0
    assert found.power >= 0.9 > design.power(0.2, found.n_total - groups)
    assert found.question == "sample size" and found.target_power == 0.9


def test_detectable_effect_has_the_target_power() -> None:
    design = PowerDesign("between", 2, 4, 0.6)
    found = detectable_effect(design, n_total=24, target=0.8)
    assert found.power == pytest.approx(0.8, abs=1e-8)
    assert found.eta2 == pytest.approx(eta2_from_f(found.f))
    assert n_for_power(design, f=found.f * 1.001, target=0.8).n_total <= 24


def test_json_carries_outputs_and_the_design() -> None:
    answer = power_for_n(PowerDesign("within", 2, 4, 0.5, 0.9, 0.01), f=0.3, n_total=20).to_dict()
    for key in ("power", "n_total", "lambda", "df1", "df2", "f", "eta2", "design"):
        assert key in answer
    assert answer["design"] == {
        "effect": "within",
        "groups": 2,
        "sessions": 4,
        "rho": 0.5,
        "rho_used": True,
        "epsilon": 0.9,
        "epsilon_used": True,
        "alpha": 0.01,
        "convention": "gpower",
    }


def test_effect_sizes_from_a_means_table() -> None:
    sizes = effect_sizes_from_means([[1, 1], [3, 3]], [[2, 2], [2, 2]])
    assert sizes == {"between": 0.5, "within": 0.0, "interaction": 0.0, "sd": 2.0}
    crossing = effect_sizes_from_means([[0, 2], [2, 0]], 1)
    assert crossing["interaction"] == 1.0 and crossing["between"] == crossing["within"] == 0


# ------------------------------------------------------------------ bad input: one line each


@pytest.mark.parametrize(
    ("make", "words"),
    [
        (lambda: PowerDesign("within", 1, 4, 1.0), "rho"),
        (lambda: PowerDesign("within", 1, 4, -1.2), "rho"),
        (lambda: PowerDesign("between", 2, 4, -0.5), "impossible"),
        (lambda: PowerDesign("within", 2, 4, 0.5, epsilon=0.2), "epsilon"),
        (lambda: PowerDesign("within", 2, 4, 0.5, epsilon=1.1), "epsilon"),
        (lambda: PowerDesign("within", 2, 4, None), "rho"),
        (lambda: PowerDesign("between", 1, 4, 0.5), "2 or more groups"),
        (lambda: PowerDesign("interaction", 2, 1, 0.5), "2 or more sessions"),
        (lambda: PowerDesign("within", 2, 4, 0.5, alpha=1.5), "alpha"),
        (lambda: power_for_n(PowerDesign("within", 2, 4, 0.5), f=-0.1, n_total=20), "f must"),
        (lambda: power_for_n(PowerDesign("within", 2, 4, 0.5), f=0.1, n_total=2), "N = 2"),
        (lambda: n_for_power(PowerDesign("within", 2, 4, 0.5), f=0.1, target=1.0), "target"),
        (lambda: n_for_power(PowerDesign("within", 2, 4, 0.5), f=0.1, target=0), "target"),
        (lambda: n_for_power(PowerDesign("within", 2, 4, 0.5), f=0.0, target=0.8), "f = 0"),
        (lambda: f_from_eta2(1.0), "eta²"),
    ],
)
def test_bad_input_is_one_clear_line(make: object, words: str) -> None:
    with pytest.raises(InvalidInputError) as caught:
        make()  # type: ignore[operator]
    assert isinstance(caught.value, ValueError)
    message = str(caught.value)
    assert words in message and "\n" not in message


def test_analytic_answers_are_plain_numbers() -> None:
    answer = n_for_power(PowerDesign("between", 2, 4, 0.6), f=0.37, target=0.8)
    assert isinstance(answer.n_total, int) and math.isfinite(answer.power)


def test_the_pi_guides_worked_example() -> None:
    # docs/pi-guide.md, "Plan the next study": the seed paper's η² read "as in SPSS", and the
    # same answers from its means table with the ρ ≈ .60 its F values imply.
    between = PowerDesign("between", 2, 4, None, convention="spss")
    inter = PowerDesign("interaction", 2, 4, None, convention="spss")
    assert round(power_for_n(between, f=f_from_eta2(0.179), n_total=24).power, 3) == 0.553
    assert n_for_power(between, f=f_from_eta2(0.179), target=0.8).n_total == 40
    assert round(power_for_n(inter, f=f_from_eta2(0.204), n_total=24).power, 3) == 0.933
    assert n_for_power(inter, f=f_from_eta2(0.204), target=0.8).n_total == 18
    lower = PowerDesign("interaction", 2, 4, None, epsilon=0.333, convention="spss")
    assert lower.epsilon == 1 / 3
    sizes = effect_sizes_from_means(
        [[3.03, 2.42, 2.83, 2.67], [2.92, 3.17, 3.75, 3.92]],
        [[1.24, 0.996, 1.267, 0.888], [0.793, 0.835, 0.754, 0.515]],
    )
    by_means = power_for_n(PowerDesign("between", 2, 4, 0.6), f=sizes["between"], n_total=24)
    assert round(by_means.power, 3) == 0.552
