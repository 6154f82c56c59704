"""C2's per-question surprise trace (issue 36): gates that see which question each surprise was
on, kept in the learner's state, off for every checkpoint that does not record it, and no effect
at all while its coefficients are zero (where training starts)."""

from __future__ import annotations

import dataclasses
import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

from models.checkpoints import (
    HASH_FILE,
    PRETRAINED_DIR,
    TRACE_GATES,
    WEIGHTS_FILE,
    Checkpoint,
    load_checkpoint,
    shipped_checkpoint,
    write_checkpoint,
)
from models.learners.meta_policy import MetaPolicyLearner
from models.learners.mlp_policy import surprise
from models.seed_selection import best_by_validation, filter_validation
from models.simulate import BatchMetaPolicy

ANSWERS = [(0, 1.0), (0, 0.0), (0, 0.0), (1, 1.0), (2, 0.0), (1, 1.0), (0, 1.0)]
"""A history with a repeated contradiction of question 0 and scattered surprises."""


def _shipped() -> Checkpoint:
    return load_checkpoint(shipped_checkpoint(4, "cognition", directory=PRETRAINED_DIR), 4)


def _tracing(checkpoint: Checkpoint, kind: str = "surprise", scale: float = 1.0) -> Checkpoint:
    """``checkpoint`` with a per-question trace; coefficients ``scale`` × a spread of values
    (0: the trace's starting point, no effect)."""
    assert checkpoint.gates is not None
    horizon = checkpoint.horizon
    trace = {
        name: scale * np.linspace(-1.0 + 0.5 * i, 1.0, horizon)
        for i, name in enumerate(TRACE_GATES)
    }
    gates = dataclasses.replace(checkpoint.gates, trace=trace, trace_kind=kind)
    return dataclasses.replace(checkpoint, gates=gates)


def _run(learner: MetaPolicyLearner, answers: list[tuple[int, float]]) -> list[bytes]:
    seen = [learner.probabilities().tobytes()]
    for action, reward in answers:
        learner.update(action, reward)
        seen.append(learner.probabilities().tobytes())
    return seen


@pytest.mark.parametrize("kind", ["surprise", "contradiction"])
def test_a_zero_trace_reproduces_the_gates_without_it_bit_for_bit(kind: str) -> None:
    """Training starts at zero coefficients: from there it must be today's learner exactly."""
    shipped = _shipped()
    zero = _tracing(shipped, kind, scale=0.0)
    assert zero.traces and not shipped.traces
    assert _run(MetaPolicyLearner(zero), ANSWERS) == _run(MetaPolicyLearner(shipped), ANSWERS)
    traced = MetaPolicyLearner(zero)
    _run(traced, ANSWERS)
    assert np.any(traced.surprise_trace > 0)  # kept, though it changes nothing yet


def test_the_surprise_trace_adds_each_surprise_to_its_question_and_forgets_it() -> None:
    checkpoint = _tracing(_shipped())
    learner = MetaPolicyLearner(checkpoint)
    expected = np.zeros(4)
    for action, reward in ANSWERS:
        p_asked = learner.policy()[action]
        u = float(surprise(p_asked, reward, 1.0, 0.0))
        others = expected.sum() - expected[action]
        rho = float(
            checkpoint.step_and_retention(
                learner.answers, p_asked, reward, 0.0, (expected[action], others)
            )[1]
        )
        expected = rho * (expected + u * (np.arange(4) == action))
        learner.update(action, reward)
    np.testing.assert_allclose(learner.surprise_trace, expected, rtol=1e-14)
    assert learner.surprise_trace[3] == 0.0 and learner.surprise_trace[0] > 0.5


def test_a_contradiction_trace_counts_noes_net_of_yeses() -> None:
    checkpoint = _tracing(_shipped(), "contradiction")
    learner = MetaPolicyLearner(checkpoint)
    learner.update(0, 1.0)  # a yes finds the favourite: no contradiction
    assert np.all(learner.surprise_trace == 0.0)
    p_asked = learner.policy()[0]
    learner.update(0, 0.0)  # a no to it: contradicted by its probability
    assert learner.surprise_trace[0] == pytest.approx(p_asked * _retention(learner), rel=0.5)
    assert learner.surprise_trace[0] > 0 and np.all(learner.surprise_trace[1:] == 0.0)
    before = learner.surprise_trace[0]
    learner.update(0, 1.0)  # a yes to it again takes part of the no back
    assert 0 <= learner.surprise_trace[0] < before


def _retention(learner: MetaPolicyLearner) -> float:
    return learner.checkpoint.retention_after(learner.answers - 1)


def test_the_trace_gates_change_later_steps_by_which_question_was_contradicted() -> None:
    checkpoint = _tracing(_shipped(), "contradiction")
    repeated, scattered = MetaPolicyLearner(checkpoint), MetaPolicyLearner(checkpoint)
    for _ in range(4):
        repeated.update(0, 1.0)
        scattered.update(0, 1.0)
    repeated.update(0, 0.0)
    scattered.update(1, 1.0)  # the same number of surprises, on another question
    # Their next "no" to question 0 reads differently: one is the second contradiction of it.
    repeated.update(0, 0.0)
    scattered.update(0, 0.0)
    assert not np.allclose(repeated.probabilities(), scattered.probabilities())


@pytest.mark.parametrize("kind", ["surprise", "contradiction"])
def test_the_trace_is_kept_in_the_state_and_round_trips_bitwise(kind: str) -> None:
    checkpoint = _tracing(_shipped(), kind)
    learner = MetaPolicyLearner(checkpoint)
    _run(learner, ANSWERS)
    state = learner.state_dict()
    assert state["surprise_trace"] == learner.surprise_trace.tolist()
    assert "surprise_memory" not in state
    restored = MetaPolicyLearner(checkpoint)
    restored.load_state_dict(json.loads(json.dumps(state)))
    assert restored.state_dict() == state
    assert restored.surprise_trace.tobytes() == learner.surprise_trace.tobytes()
    assert _run(restored, ANSWERS) == _run(learner, ANSWERS)
    zeroed = MetaPolicyLearner(checkpoint)  # the same weights with the trace dropped
    zeroed.load_state_dict({**state, "surprise_trace": [0.0] * 4})
    zeroed.update(0, 0.0)
    twin = MetaPolicyLearner(checkpoint)
    twin.load_state_dict(state)
    twin.update(0, 0.0)
    assert not np.allclose(zeroed.probabilities(), twin.probabilities())
    learner.reset()
    assert np.all(learner.surprise_trace == 0.0)


def test_old_checkpoints_keep_their_states_exactly() -> None:
    """A checkpoint without a trace writes no trace in its state, and refuses one."""
    shipped = _shipped()
    learner = MetaPolicyLearner(shipped)
    _run(learner, ANSWERS)
    state = learner.state_dict()
    assert "surprise_trace" not in state
    with pytest.raises(ValueError, match="does not keep"):
        MetaPolicyLearner(shipped).load_state_dict({**state, "surprise_trace": [0.0] * 4})


@pytest.mark.parametrize(
    ("trace", "message"),
    [
        (None, "must record its surprise trace"),
        ([0.0] * 3, "must record its surprise trace"),
        (0.0, "must record its surprise trace"),
        ([0.0, -0.1, 0.0, 0.0], "finite and ≥ 0"),
        ([0.0, float("nan"), 0.0, 0.0], "finite and ≥ 0"),
        ([0.0, True, 0.0, 0.0], "must hold numbers"),
    ],
)
def test_a_state_with_a_bad_trace_is_refused(trace: object, message: str) -> None:
    checkpoint = _tracing(_shipped())
    state = MetaPolicyLearner(checkpoint).state_dict()
    if trace is None:
        del state["surprise_trace"]
    else:
        state["surprise_trace"] = trace
    with pytest.raises(ValueError, match=message):
        MetaPolicyLearner(checkpoint).load_state_dict(state)


@pytest.mark.parametrize("kind", ["surprise", "contradiction"])
def test_the_batch_learner_traces_as_one_learner_does(kind: str) -> None:
    checkpoint = _tracing(_shipped(), kind)
    rng = np.random.default_rng(5)
    actions = rng.integers(0, 4, size=(8, 3))
    rewards = rng.integers(0, 2, size=(8, 3)).astype(float)
    batch = BatchMetaPolicy(checkpoint)
    for t in range(8):
        batch.update(actions[t], rewards[t])
    for row in range(3):
        learner = MetaPolicyLearner(checkpoint)
        for t in range(8):
            learner.update(int(actions[t, row]), float(rewards[t, row]))
        np.testing.assert_allclose(batch.probabilities()[row], learner.probabilities(), rtol=1e-12)
        np.testing.assert_allclose(batch.trace[row], learner.surprise_trace, rtol=1e-12)


def _rewrite(path: Path, weights: dict[str, object]) -> None:
    data = json.dumps(weights).encode()
    (path / WEIGHTS_FILE).write_bytes(data)
    (path / HASH_FILE).write_text(f"{hashlib.sha256(data).hexdigest()}  {WEIGHTS_FILE}\n")


@pytest.mark.parametrize("kind", ["surprise", "contradiction"])
def test_a_tracing_checkpoint_writes_and_loads_its_trace(tmp_path: Path, kind: str) -> None:
    source = _tracing(_shipped(), kind)
    written = write_checkpoint(
        tmp_path / "traced",
        n_arms=4,
        category=source.category,
        mode=source.mode,
        rule=source.rule,
        observation=source.observation,
        params=source.params,
        step_sizes=source.step_sizes,
        baselines=source.baselines,
        damping=source.damping,
        config=source.config,
        metrics={},
        prior=source.prior,
        retention=source.retention,
        gates=source.gates,
        temperature=source.temperature,
    )
    assert written.gates is not None and source.gates is not None and source.gates.trace
    assert written.gates.trace_kind == kind and written.gates.trace is not None
    for name in TRACE_GATES:
        assert written.gates.trace[name].tobytes() == source.gates.trace[name].tobytes()
    weights = json.loads((written.path / WEIGHTS_FILE).read_text())
    assert ("trace_kind" in weights["surprise"]) == (kind != "surprise")  # old hashes stay
    assert _run(MetaPolicyLearner(written), ANSWERS) == _run(MetaPolicyLearner(source), ANSWERS)


def test_a_checkpoint_with_a_bad_trace_is_refused(tmp_path: Path) -> None:
    source = _shipped()
    path = tmp_path / "bad"
    path.mkdir()
    for name in ("config.json", "metrics.json"):
        (path / name).write_text((source.path / name).read_text())
    weights = json.loads((source.path / WEIGHTS_FILE).read_text())
    zeros = [0.0] * source.horizon
    weights["surprise"]["trace"] = dict.fromkeys(TRACE_GATES[:3], zeros)
    _rewrite(path, weights)
    with pytest.raises(ValueError, match=r"'surprise\.trace' must be an object"):
        load_checkpoint(path)
    weights["surprise"]["trace"] = dict.fromkeys(TRACE_GATES, zeros)
    weights["surprise"]["trace"]["step"] = zeros[:-1]
    _rewrite(path, weights)
    with pytest.raises(ValueError, match="'step' has shape"):
        load_checkpoint(path)
    weights["surprise"]["trace"]["step"] = zeros
    weights["surprise"]["trace_kind"] = "hunch"
    _rewrite(path, weights)
    with pytest.raises(ValueError, match="trace_kind"):
        load_checkpoint(path)
    del weights["surprise"]["trace_kind"]
    _rewrite(path, weights)
    assert load_checkpoint(path).traces


def test_seed_selection_scores_every_candidate_on_the_same_participants() -> None:
    """The same checkpoint scores the same twice; a trace that changes the learner scores
    differently on the same draws; the best is the highest."""
    shipped = _shipped()
    first = filter_validation(shipped, participants=300)
    again = filter_validation(shipped, participants=300)
    assert first.filter_score == again.filter_score and first.filter_score < 0
    assert first.standard_error > 0
    other = filter_validation(_tracing(shipped, scale=2.0), participants=300)
    assert other.filter_score != first.filter_score
    best = best_by_validation([first, other])
    assert best.filter_score == max(first.filter_score, other.filter_score)
    with pytest.raises(ValueError, match="no checkpoints"):
        best_by_validation([])
