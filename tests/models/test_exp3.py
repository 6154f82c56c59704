"""Exp3 (C1) against a hand-computed sequence, its invariants and its stored state."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from models.learners.base import Learner
from models.learners.exp3 import DEFAULT_EXP3_GAMMA, Exp3


def test_three_steps_match_hand_computation() -> None:
    # K = 3, γ = 0.5, computed by hand from p_i = (1−γ) w_i/Σw + γ/K and w_a ← w_a·exp(γ x̂/K):
    # 1) a=0, r=1: x̂ = 1/(1/3) = 3, w_0 ×= e^0.5
    #    → p = (0.5 e^.5/(e^.5+2) + 1/6, 0.5/(e^.5+2) + 1/6, …)
    # 2) a=1, r=0: factor e^0 = 1, nothing moves.
    # 3) a=2, r=0.5: x̂ = 0.5/0.30370…, w_2 ×= exp(0.5·x̂/3).
    learner = Exp3(3, gamma=0.5)
    np.testing.assert_allclose(learner.probabilities(), [1 / 3] * 3, rtol=0, atol=1e-15)
    learner.update(0, 1.0)
    after_one = [0.3925980476054697, 0.3037009761972651, 0.3037009761972651]
    np.testing.assert_allclose(learner.probabilities(), after_one, rtol=1e-13)
    learner.update(1, 0.0)
    np.testing.assert_allclose(learner.probabilities(), after_one, rtol=1e-13)
    learner.update(2, 0.5)
    after_three = [0.37460473630099234, 0.29278748122134574, 0.3326077824776619]
    np.testing.assert_allclose(learner.probabilities(), after_three, rtol=1e-13)
    assert learner.updates == 3


def test_rewards_are_clipped_into_unit_interval() -> None:
    high, one = Exp3(4), Exp3(4)
    high.update(1, 7.5)
    one.update(1, 1.0)
    assert high.probabilities().tolist() == one.probabilities().tolist()
    low, zero = Exp3(4), Exp3(4)
    low.update(1, -3.0)
    zero.update(1, 0.0)
    assert low.probabilities().tolist() == zero.probabilities().tolist()


@pytest.mark.parametrize("gamma", [0.05, 0.1, 0.5, 1.0])
def test_probabilities_sum_to_one_and_respect_floor(gamma: float) -> None:
    rng = np.random.default_rng(1)
    learner = Exp3(5, gamma=gamma)
    for _ in range(300):
        p = learner.probabilities()
        assert p.dtype == np.float64
        assert math.isclose(p.sum(), 1.0, abs_tol=1e-12)
        assert np.all(p >= gamma / 5 - 1e-15)
        learner.update(learner.select(rng), float(rng.random()))


def test_learns_the_rewarded_arm() -> None:
    rng = np.random.default_rng(2)
    learner = Exp3(4, gamma=0.2)
    for _ in range(200):
        a = learner.select(rng)
        learner.update(a, 1.0 if a == 2 else 0.0)
    assert int(np.argmax(learner.probabilities())) == 2


def test_state_round_trip_is_bitwise_through_json() -> None:
    rng = np.random.default_rng(3)
    learner = Exp3(4, gamma=DEFAULT_EXP3_GAMMA)
    for _ in range(7):
        learner.update(learner.select(rng), float(rng.random()))
    copy = Exp3(4, gamma=DEFAULT_EXP3_GAMMA)
    copy.load_state_dict(json.loads(json.dumps(learner.state_dict())))
    for _ in range(5):
        a = int(rng.integers(4))
        r = float(rng.random())
        learner.update(a, r)
        copy.update(a, r)
        assert learner.probabilities().tobytes() == copy.probabilities().tobytes()
    assert isinstance(learner, Learner)


@pytest.mark.parametrize("reward", [math.nan, math.inf, -math.inf, "yes", None])
def test_bad_reward_is_refused(reward: object) -> None:
    with pytest.raises(ValueError, match="reward"):
        Exp3(4).update(0, reward)  # type: ignore[arg-type]


@pytest.mark.parametrize("action", [-1, 4, 1.0, True, "0"])
def test_bad_action_is_refused(action: object) -> None:
    with pytest.raises(ValueError, match="action"):
        Exp3(4).update(action, 1.0)  # type: ignore[arg-type]


@pytest.mark.parametrize("gamma", [0.0, -0.1, 1.5, math.nan])
def test_bad_gamma_is_refused(gamma: float) -> None:
    with pytest.raises(ValueError, match="gamma"):
        Exp3(4, gamma=gamma)


def test_state_of_another_learner_is_refused() -> None:
    state = Exp3(4, gamma=0.5).state_dict()
    with pytest.raises(ValueError, match="gamma"):
        Exp3(4, gamma=0.1).load_state_dict(state)
    with pytest.raises(ValueError, match="n_arms"):
        Exp3(5, gamma=0.5).load_state_dict(state)
    with pytest.raises(ValueError, match="weights"):
        Exp3(4, gamma=0.5).load_state_dict({**state, "weights": [1.0, math.nan, 1.0, 1.0]})
