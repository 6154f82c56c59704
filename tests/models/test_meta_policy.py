"""The meta-policy learner (C2): probabilities, the natural-gradient step, state and bad input."""

from __future__ import annotations

import base64
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from models.checkpoints import Checkpoint
from models.learners.base import Learner
from models.learners.meta_policy import MetaPolicyLearner, plain_state
from models.learners.mlp_policy import (
    hidden_and_logits,
    logit_gram,
    probabilities,
    update_params,
)
from tests.models.conftest import make_checkpoint


def _jacobian(params: dict[str, np.ndarray], obs: np.ndarray) -> np.ndarray:
    """∂logits/∂θ by central finite differences, θ flattened in PARAM_NAMES order."""
    names = ("W1", "b1", "W2", "b2")
    columns = []
    for name in names:
        flat = params[name].ravel()
        for i in range(flat.size):
            shifted = []
            for sign in (1.0, -1.0):
                copy = {k: v.copy() for k, v in params.items()}
                copy[name].ravel()[i] += sign * 1e-6
                shifted.append(hidden_and_logits(copy, obs)[1])
            columns.append((shifted[0] - shifted[1]) / 2e-6)
    return np.stack(columns, axis=1)


def _flat_step(params: dict[str, np.ndarray], obs: np.ndarray, rule: str, **update: Any) -> Any:
    """The change of every network parameter, flattened, after one ``update_params``."""
    new = update_params(params, obs, rule=rule, **update)  # type: ignore[arg-type]
    return np.concatenate([(new[n] - params[n]).ravel() for n in ("W1", "b1", "W2", "b2")])


def _natural_dense(jacobian: Any, pi: Any, s: Any, alpha: float, damping: float) -> Any:
    """``α (F + λI)⁻¹ Jᵀ s`` with the softmax policy's Fisher ``F``, solved densely."""
    fisher = jacobian.T @ (np.diag(pi) - np.outer(pi, pi)) @ jacobian
    eye = np.eye(jacobian.shape[1])
    return alpha * np.linalg.solve(fisher + damping * eye, jacobian.T @ s)


def test_natural_step_matches_the_dense_formula() -> None:
    rng = np.random.default_rng(0)
    obs = rng.standard_normal(3)
    from models.learners.mlp_policy import init_params

    params = init_params(rng, 3, 5, 4)
    J = _jacobian(params, obs)
    h, _ = hidden_and_logits(params, obs)
    np.testing.assert_allclose(logit_gram(params, obs, h), J @ J.T, rtol=1e-6, atol=1e-8)
    pi = probabilities(params, obs)
    s = (np.eye(4)[2] - pi) * (0.9 - 0.3)
    update = {
        "action": np.asarray(2),
        "reward": np.asarray(0.9),
        "step_size": 0.7,
        "baseline": 0.3,
        "damping": 0.1,
    }
    np.testing.assert_allclose(
        _flat_step(params, obs, "natural", **update),
        _natural_dense(J, pi, s, 0.7, 0.1),
        rtol=1e-5,
        atol=1e-9,
    )
    np.testing.assert_allclose(
        _flat_step(params, obs, "gradient", **update), 0.7 * J.T @ s, rtol=1e-5, atol=1e-9
    )


def test_expected_natural_step_matches_the_dense_formula() -> None:
    """``natural_expected``: the natural step on the expected gradient ``π_a (e_a − π)(r − b)``."""
    rng = np.random.default_rng(4)
    obs = rng.standard_normal(3)
    from models.learners.mlp_policy import init_params

    params = init_params(rng, 3, 5, 4)
    J = _jacobian(params, obs)
    pi = probabilities(params, obs)
    s = pi[1] * (np.eye(4)[1] - pi) * (0.2 - 0.5)
    step = _flat_step(
        params,
        obs,
        "natural_expected",
        action=np.asarray(1),
        reward=np.asarray(0.2),
        step_size=3.0,
        baseline=0.5,
        damping=0.05,
    )
    np.testing.assert_allclose(step, _natural_dense(J, pi, s, 3.0, 0.05), rtol=1e-5, atol=1e-9)


@pytest.mark.parametrize(("scale", "tolerance"), [(1e-4, 1e-5), (1.0, 0.1)])
def test_expected_natural_step_is_the_bayes_update_in_logit_space(
    tmp_path: Path, scale: float, tolerance: float
) -> None:
    """With step (μ₁ − μ₀)/σ², baseline (μ₁ + μ₀)/2 and vanishing damping, each answer changes
    the log-probabilities as the Bayes posterior over the preferred question changes: exactly to
    first order (a tiny step, rescaled), and within a tenth of the Bayes step for the full step
    (the tanh layer bends a long step)."""
    from models.learners.bayes import BayesLearner
    from models.tasks import TaskDistribution

    tasks = TaskDistribution(4, variance=0.1)
    checkpoint = make_checkpoint(tmp_path / "bayes-like", rule="natural_expected")
    checkpoint = Checkpoint(
        **{
            **checkpoint.__dict__,
            "step_sizes": np.full(6, scale / tasks.variance),
            "baselines": np.full(6, 0.5),
            "damping": 1e-12,
        }
    )
    learner, bayes = MetaPolicyLearner(checkpoint), BayesLearner(tasks)
    for action, reward in [(2, 0.93), (0, -0.2), (2, 1.31), (3, 0.55), (1, 0.08), (2, 0.7)]:
        before, prior = np.log(learner.probabilities()), np.log(bayes.probabilities())
        learner.update(action, reward)
        bayes.update(action, reward)
        change = (np.log(learner.probabilities()) - before) / scale
        expected = np.log(bayes.probabilities()) - prior
        bayes_step = np.abs(expected - expected[0]).max()
        np.testing.assert_allclose(
            change - change[0], expected - expected[0], atol=tolerance * bayes_step
        )
    # The score-function rule divides by π_a instead: not the Bayes update.
    other = MetaPolicyLearner(Checkpoint(**{**checkpoint.__dict__, "rule": "natural"}))
    before = np.log(other.probabilities())
    other.update(2, 0.93)
    change = np.log(other.probabilities()) - before
    assert abs((change[2] - change[0]) - 10 * (0.93 - 0.5)) > 1.0


def test_batched_update_equals_one_at_a_time(checkpoint: Checkpoint) -> None:
    rng = np.random.default_rng(1)
    batch = {
        k: np.stack([v] * 3) + rng.normal(0, 0.1, (3, *v.shape))
        for k, v in checkpoint.params.items()
    }
    actions, rewards = np.array([0, 3, 1]), np.array([1.1, -0.2, 0.4])
    together = update_params(
        batch,
        checkpoint.observation,
        actions,
        rewards,
        step_size=np.array([1.0, 0.5, 0.2]),
        baseline=0.25,
        damping=0.05,
        rule="natural",
    )
    for i in range(3):
        alone = update_params(
            {k: v[i] for k, v in batch.items()},
            checkpoint.observation,
            actions[i],
            rewards[i],
            step_size=[1.0, 0.5, 0.2][i],
            baseline=0.25,
            damping=0.05,
            rule="natural",
        )
        for name in alone:
            np.testing.assert_allclose(together[name][i], alone[name], rtol=1e-12, atol=1e-14)


def test_rewarded_question_gains_probability(checkpoint: Checkpoint) -> None:
    learner = MetaPolicyLearner.from_checkpoint(checkpoint, expected_arms=4)
    before = learner.probabilities()
    learner.update(2, 1.0)
    after = learner.probabilities()
    assert after[2] > before[2]
    assert math.isclose(after.sum(), 1.0, abs_tol=1e-12)
    learner.update(1, 0.0)
    assert learner.probabilities()[1] < after[1]
    assert isinstance(learner, Learner)


def test_step_sizes_and_baselines_follow_the_answer_index(checkpoint: Checkpoint) -> None:
    learner = MetaPolicyLearner(checkpoint)
    assert [learner.step_size(i) for i in range(5)] == [1.0, 0.8, 0.6, 0.6, 0.6]
    assert [learner.baseline(i) for i in range(4)] == [0.25, 0.3, 0.35, 0.35]
    assert MetaPolicyLearner(checkpoint, learning_rate=0.3).step_size(1) == 0.3


def test_state_round_trip_is_bitwise_and_reset_restarts(checkpoint: Checkpoint) -> None:
    rng = np.random.default_rng(2)
    learner = MetaPolicyLearner.from_checkpoint(checkpoint.path)
    start = learner.probabilities()
    for _ in range(4):
        learner.update(learner.select(rng), float(rng.normal(0.5, 0.3)))
    copy = MetaPolicyLearner.from_checkpoint(checkpoint)
    copy.load_state_dict(json.loads(json.dumps(learner.state_dict())))
    for _ in range(6):
        a, r = int(rng.integers(4)), float(rng.normal())
        learner.update(a, r)
        copy.update(a, r)
        assert learner.probabilities().tobytes() == copy.probabilities().tobytes()
    assert copy.answers == 10
    copy.reset()
    assert copy.answers == 0
    assert copy.probabilities().tobytes() == start.tobytes()


def test_state_of_another_checkpoint_is_refused(checkpoint: Checkpoint, tmp_path: Path) -> None:
    other = make_checkpoint(tmp_path / "other", seed=5)
    state = MetaPolicyLearner(checkpoint).state_dict()
    with pytest.raises(ValueError, match="checkpoint sha256"):
        MetaPolicyLearner(other).load_state_dict(state)
    with pytest.raises(ValueError, match="learning_rate"):
        MetaPolicyLearner(checkpoint, learning_rate=0.1).load_state_dict(state)
    with pytest.raises(ValueError, match="W1"):
        MetaPolicyLearner(checkpoint).load_state_dict(
            {**state, "params": {**state["params"], "W1": [[1.0]]}}
        )
    with pytest.raises(ValueError, match="W1 holds 1 numbers"):
        MetaPolicyLearner(checkpoint).load_state_dict(
            {**state, "params": {**state["params"], "W1": "AAAAAAAA8D8="}}
        )
    with pytest.raises(ValueError, match="malformed"):
        MetaPolicyLearner(checkpoint).load_state_dict(
            {**state, "params": {**state["params"], "W1": "not base64!"}}
        )


def test_states_of_format_version_1_still_restore(checkpoint: Checkpoint) -> None:
    """Version 1 (weights as JSON numbers) was written until 2026-12; those rows must restore
    to the same bits, and compare equal to their version 2 rewrite."""
    learner = MetaPolicyLearner(checkpoint)
    for action, reward in ((0, 1.0), (2, 0.0), (0, 1.0)):
        learner.update(action, reward)
    current = learner.state_dict()
    assert current["version"] == 2
    assert all(isinstance(v, str) for v in current["params"].values())
    old = {**current, "version": 1}
    old["params"] = {
        name: np.frombuffer(base64.b64decode(text), dtype="<f8")
        .reshape(checkpoint.params[name].shape)
        .tolist()
        for name, text in current["params"].items()
    }
    restored = MetaPolicyLearner(checkpoint)
    restored.load_state_dict(json.loads(json.dumps(old)))
    assert restored.probabilities().tobytes() == learner.probabilities().tobytes()
    assert restored.state_dict() == current
    assert plain_state(old) == plain_state(current)
    assert (
        plain_state(old)["params"]
        != plain_state(MetaPolicyLearner(checkpoint).state_dict())["params"]
    )
    with pytest.raises(ValueError, match="version"):
        restored.load_state_dict({**current, "version": 3})


def test_random_init_differs_but_uses_the_same_rule(checkpoint: Checkpoint) -> None:
    a = MetaPolicyLearner.random_init(checkpoint, np.random.default_rng(7))
    b = MetaPolicyLearner.random_init(checkpoint, np.random.default_rng(7))
    assert a.probabilities().tobytes() == b.probabilities().tobytes()
    assert a.probabilities().tobytes() != MetaPolicyLearner(checkpoint).probabilities().tobytes()
    a.update(0, 1.0)
    assert a.probabilities()[0] > b.probabilities()[0]
    assert a.state_dict()["init"] == "random"


def test_bad_input_is_refused(checkpoint: Checkpoint, tmp_path: Path) -> None:
    learner = MetaPolicyLearner(checkpoint)
    for reward in (math.nan, math.inf):
        with pytest.raises(ValueError, match="reward"):
            learner.update(0, reward)
    with pytest.raises(ValueError, match="action"):
        learner.update(4, 1.0)
    assert learner.answers == 0
    with pytest.raises(ValueError, match="4 questions"):
        MetaPolicyLearner.from_checkpoint(checkpoint, expected_arms=5)
    with pytest.raises(ValueError, match="4 questions"):
        MetaPolicyLearner.from_checkpoint(checkpoint.path, expected_arms=3)
    with pytest.raises(ValueError, match="learning_rate"):
        MetaPolicyLearner(checkpoint, learning_rate=-1.0)


def test_learners_do_not_import_torch() -> None:
    import subprocess
    import sys

    code = (
        "import sys, models.learners.meta_policy, models.checkpoints, models.learners.exp3, "
        "models.learners.bayes, models.replies; assert 'torch' not in sys.modules"
    )
    subprocess.run([sys.executable, "-c", code], check=True)
