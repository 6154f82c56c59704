"""Adaptation curves from the step log."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from analysis.adaptation import (
    CURVE_COLUMNS,
    adaptation_curves,
    curves_from_trajectories,
    preferred_probability,
    validate_steps,
)
from analysis.errors import DuplicateObservationError, InvalidInputError

PREFERRED = {"conation": 1, "cognition": 2}


def _step(participant: str, condition: str, category: str, iteration: int, pref: int,
          before: float, after: float) -> dict:  # type: ignore[type-arg]  # fmt: skip
    def probs(p: float) -> list[float]:
        rest = (1 - p) / 3
        return [p if i == pref else rest for i in range(4)]

    return {
        "participant": participant,
        "condition": condition,
        "category": category,
        "session": 1 + (iteration - 1) // 3,
        "run": 1 + (iteration - 1) % 3,
        "iteration": iteration,
        "action": pref,
        "probs_before": probs(before),
        "probs_after": probs(after),
        "answer": True,
        "reward": 1.0,
    }


@pytest.fixture
def steps() -> pd.DataFrame:
    rows = []
    # P1 and P2 in C1 (conation, preferred arm 1): 0.25 → 0.40 → 0.60 and 0.25 → 0.30 → 0.50.
    for pid, path in (("P1", [0.25, 0.40, 0.60]), ("P2", [0.25, 0.30, 0.50])):
        for it in (1, 2):
            rows.append(_step(pid, "C1", "conation", it, 1, path[it - 1], path[it]))
    # P3 in C2 answered one conation step (0.25 → 0.7) and one cognition step.
    rows.append(_step("P3", "C2", "conation", 1, 1, 0.25, 0.70))
    rows.append(_step("P3", "C2", "cognition", 1, 2, 0.25, 0.55))
    return pd.DataFrame(rows)


def test_trajectory_has_n_plus_one_points(steps: pd.DataFrame) -> None:
    traj = preferred_probability(steps, PREFERRED)
    p1 = traj[(traj.participant == "P1") & (traj.category == "conation")]
    assert p1["iteration"].tolist() == [0, 1, 2]
    np.testing.assert_allclose(p1["p_preferred"], [0.25, 0.40, 0.60])


def test_curves_by_hand(steps: pd.DataFrame) -> None:
    # C1 conation, iteration 2: values .60 and .50 → M = .55, SD = .0707107, SE = .05,
    # t(.975, 1) = 12.7062047 → CI = .55 ± .6353102.
    curves = adaptation_curves(steps, PREFERRED)
    assert tuple(curves.columns) == CURVE_COLUMNS
    c1 = curves[(curves.condition == "C1") & (curves.category == "conation")].set_index("iteration")
    assert c1["n"].tolist() == [2, 2, 2]
    np.testing.assert_allclose(c1["mean"], [0.25, 0.35, 0.55])
    assert c1.loc[2, "se"] == pytest.approx(0.05)
    assert c1.loc[2, "ci_low"] == pytest.approx(0.55 - 0.6353102, abs=1e-7)
    assert c1.loc[0, "sd"] == 0
    c2 = curves[curves.condition == "C2"]
    # Categories follow the protocol's order (conation before cognition), single participant:
    assert c2["category"].tolist() == ["conation", "conation", "cognition", "cognition"]
    assert c2["n"].tolist() == [1, 1, 1, 1]
    assert c2["ci_low"].isna().all()


def test_unfinished_participants_count_where_they_reached(steps: pd.DataFrame) -> None:
    more = steps.copy()
    more = pd.concat([more, pd.DataFrame([_step("P1", "C1", "conation", 3, 1, 0.6, 0.8)])])
    curves = adaptation_curves(more, PREFERRED)
    c1 = curves[(curves.condition == "C1") & (curves.category == "conation")]
    assert c1["n"].tolist() == [2, 2, 2, 1]


@pytest.mark.parametrize(
    ("mutate", "error", "message"),
    [
        (lambda d: d[d.index != 0], InvalidInputError, "without gaps"),
        (lambda d: pd.concat([d, d.iloc[[0]]]), DuplicateObservationError, "'P1', 'conation', 1"),
        (lambda d: d.assign(category="affection"), InvalidInputError, "without a preferred arm"),
        (lambda d: d.drop(columns="probs_after"), InvalidInputError, "no column 'probs_after'"),
        (
            lambda d: d.assign(condition=["C1", "C2", "C1", "C1", "C2", "C2"]),
            InvalidInputError,
            "more than one condition",
        ),
        (
            lambda d: d.assign(probs_after=[[0.5, 0.5], *list(d["probs_after"][1:])]),
            InvalidInputError,
            "same length",
        ),
        (
            lambda d: d.assign(probs_after=[[1.5, 0, 0, 0]] * len(d)),
            InvalidInputError,
            r"outside \[0, 1\]",
        ),
    ],
)
def test_bad_step_logs_are_refused(steps: pd.DataFrame, mutate, error, message: str) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(error, match=message):
        adaptation_curves(mutate(steps), PREFERRED)


def test_preferred_arm_must_exist(steps: pd.DataFrame) -> None:
    with pytest.raises(InvalidInputError, match="preferred arm 7"):
        adaptation_curves(steps, {"conation": 7, "cognition": 2})


def test_curves_from_trajectories_equal_direct_curves(steps: pd.DataFrame) -> None:
    direct = adaptation_curves(steps, PREFERRED)
    via = curves_from_trajectories(preferred_probability(steps, PREFERRED), list(PREFERRED))
    pd.testing.assert_frame_equal(direct, via)
    with pytest.raises(InvalidInputError, match="missing from the order"):
        curves_from_trajectories(preferred_probability(steps, PREFERRED), ["conation"])


def test_validate_steps_sorts(steps: pd.DataFrame) -> None:
    shuffled = steps.iloc[::-1].reset_index(drop=True)
    ordered = validate_steps(shuffled, PREFERRED)
    assert ordered["participant"].tolist() == ["P1", "P1", "P2", "P2", "P3", "P3"]
    assert ordered["iteration"].tolist()[:2] == [1, 2]
