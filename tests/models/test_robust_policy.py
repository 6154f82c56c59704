"""C2 for real participants (issue 19): a policy anchored at the prior, a forgetting step, and the
shipped set meta-trained for yes/no answers that slip and preferences that change."""

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
    REPLICATION_DIR,
    WEIGHTS_FILE,
    Checkpoint,
    SurpriseGates,
    load_checkpoint,
    shipped_checkpoint,
    shipped_set,
    trained_feedback,
)
from models.feedback import FeedbackModel
from models.learners.meta_policy import MetaPolicyLearner
from models.learners.mlp_policy import (
    anchor_offset,
    init_params,
    probabilities,
    retain,
    surprise,
)
from models.simulate import BatchMetaPolicy
from tests.models.conftest import make_checkpoint

SHIPPED = sorted(path.parent for path in (PRETRAINED_DIR / "online").glob(f"*/{WEIGHTS_FILE}"))
REPLICATION = sorted(path.parent for path in (REPLICATION_DIR / "online").glob(f"*/{WEIGHTS_FILE}"))


def _names(paths: list[Path]) -> list[str]:
    return [path.name for path in paths]


def test_the_default_set_ships_every_k_and_category_for_the_robust_model() -> None:
    expected = [f"generic-k{k}" for k in range(2, 11)]
    expected += ["affection-k4", "cognition-k4", "conation-k4"]
    assert sorted(_names(SHIPPED)) == sorted(expected)
    assert sorted(_names(REPLICATION)) == sorted(expected)
    for path in SHIPPED:
        checkpoint = load_checkpoint(path)
        model = trained_feedback(checkpoint)
        assert model.kind == "binary" and model.hazard > 0 and max(model.slips) > 0, path
        assert checkpoint.prior is not None and checkpoint.retention is not None, path
        assert checkpoint.gates is not None and checkpoint.config["surprise_gates"], path
    for path in REPLICATION:  # the paper's model, the checkpoints as they shipped before
        checkpoint = load_checkpoint(path)
        assert trained_feedback(checkpoint).same_as(FeedbackModel.paper(0.1)), path
        assert checkpoint.prior is None and checkpoint.retention is None, path
        assert checkpoint.gates is None, path


def test_shipped_set_follows_the_feedback_model() -> None:
    assert shipped_set(FeedbackModel.paper(0.1)) == REPLICATION_DIR
    assert shipped_set(FeedbackModel(slips=(0.05,), hazard=0.02)) == PRETRAINED_DIR


@pytest.mark.parametrize("path", SHIPPED, ids=_names(SHIPPED))
def test_the_first_question_is_drawn_from_the_prior_exactly(path: Path) -> None:
    checkpoint = load_checkpoint(path)
    assert checkpoint.prior is not None
    uniform = np.full(checkpoint.n_arms, 1.0 / checkpoint.n_arms)
    np.testing.assert_allclose(checkpoint.prior, uniform, rtol=0, atol=1e-15)
    np.testing.assert_allclose(
        MetaPolicyLearner(checkpoint).probabilities(), uniform, rtol=0, atol=1e-15
    )
    random = MetaPolicyLearner.random_init(checkpoint, np.random.default_rng(4))
    np.testing.assert_allclose(random.probabilities(), uniform, rtol=0, atol=1e-15)


def test_the_anchor_holds_for_any_prior_and_any_weights() -> None:
    """By construction, not by training: random weights and a skewed prior start at the prior."""
    rng = np.random.default_rng(11)
    prior = np.array([0.55, 0.25, 0.15, 0.05])
    obs = rng.standard_normal(8)
    for _ in range(5):
        params = init_params(rng, 8, 12, 4)
        params = {k: v * rng.uniform(1, 30) for k, v in params.items()}  # far from uniform
        assert np.max(np.abs(probabilities(params, obs) - prior)) > 0.05
        offset = anchor_offset(prior, params, obs)
        np.testing.assert_allclose(probabilities(params, obs, offset), prior, rtol=0, atol=1e-14)
    with pytest.raises(ValueError, match="prior above 0"):
        anchor_offset(np.array([0.5, 0.5, 0.0, 0.0]), params, obs)


@pytest.mark.parametrize("path", SHIPPED, ids=_names(SHIPPED))
def test_a_saturated_belief_can_be_left(path: Path) -> None:
    """After five consistent yeses to one question, three noes in a row bring it below .5."""
    learner = MetaPolicyLearner(load_checkpoint(path))
    for _ in range(5):
        learner.update(0, 1.0)
    assert learner.probabilities()[0] > 0.9
    for _ in range(3):
        learner.update(0, 0.0)
    assert learner.probabilities()[0] < 0.5


def test_the_saturation_check_fails_for_the_set_trained_without_forgetting() -> None:
    """The check discriminates: the paper's-model C2 stays sure after three noes (issue 19)."""
    learner = MetaPolicyLearner(
        load_checkpoint(shipped_checkpoint(4, "conation", "online", REPLICATION_DIR))
    )
    for reward in [1.0] * 5 + [0.0] * 3:
        learner.update(0, reward)
    assert learner.probabilities()[0] > 0.99


def test_retain_moves_the_weights_toward_the_start() -> None:
    rng = np.random.default_rng(2)
    start, moved = init_params(rng, 3, 4, 2), init_params(rng, 3, 4, 2)
    half = retain(moved, start, 0.5)
    for name in start:
        np.testing.assert_allclose(half[name], (start[name] + moved[name]) / 2)
    for name in start:
        np.testing.assert_allclose(retain(moved, start, 1.0)[name], moved[name], rtol=1e-15)


@pytest.mark.parametrize("init", ["checkpoint", "random"])
def test_state_round_trips_bitwise_with_anchor_and_forgetting(init: str) -> None:
    checkpoint = load_checkpoint(SHIPPED[0])
    rng = np.random.default_rng(9)
    make = (
        (lambda: MetaPolicyLearner(checkpoint))
        if init == "checkpoint"
        else (lambda: MetaPolicyLearner.random_init(checkpoint, np.random.default_rng(5)))
    )
    learner = make()
    for _ in range(4):
        learner.update(learner.select(rng), float(rng.integers(2)))
    state = json.loads(json.dumps(learner.state_dict()))
    restored = MetaPolicyLearner(checkpoint)  # a different start: the state must carry its own
    restored.load_state_dict(state)
    assert restored.probabilities().tobytes() == learner.probabilities().tobytes()
    for action, reward in [(1, 0.0), (0, 1.0), (2, 1.0)]:
        learner.update(action, reward)
        restored.update(action, reward)
        assert restored.probabilities().tobytes() == learner.probabilities().tobytes()
    assert restored.state_dict() == learner.state_dict()


def test_the_batched_simulation_learner_matches_the_deployed_one() -> None:
    checkpoint = load_checkpoint(shipped_checkpoint(4, "cognition"))
    rng = np.random.default_rng(3)
    actions = rng.integers(0, 4, size=(6, 7))
    rewards = rng.integers(0, 2, size=(6, 7)).astype(float)
    batch = BatchMetaPolicy(checkpoint)
    singles = [MetaPolicyLearner(checkpoint) for _ in range(6)]
    for t in range(7):
        batch.update(actions[:, t], rewards[:, t])
        for row, learner in enumerate(singles):
            learner.update(int(actions[row, t]), float(rewards[row, t]))
    expected = np.stack([learner.probabilities() for learner in singles])
    np.testing.assert_allclose(batch.probabilities(), expected, rtol=1e-12, atol=1e-14)


def _rewrite(path: Path, **changes: object) -> None:
    """Edit weights.json and re-hash it, as a (mistaken) hand-made checkpoint would be."""
    weights = json.loads((path / WEIGHTS_FILE).read_text())
    weights.update(changes)
    data = (json.dumps(weights, sort_keys=True, separators=(",", ":")) + "\n").encode()
    (path / WEIGHTS_FILE).write_bytes(data)
    (path / HASH_FILE).write_text(f"{hashlib.sha256(data).hexdigest()}  {WEIGHTS_FILE}\n")


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"prior": [0.5, 0.5, 0.0, 0.0]}, "'prior' must be positive and sum to 1"),
        ({"prior": [0.3, 0.3, 0.3, 0.3]}, "'prior' must be positive and sum to 1"),
        ({"prior": [0.5, 0.5]}, "'prior' has shape"),
        ({"retention": [1.5, 1.0, 1.0]}, "'retention' must lie in (0, 1]"),
        ({"retention": [0.9]}, "'retention' has shape"),
        (
            {"surprise": {"yes": 1, "no": 0, "step": [0, 0, 0], "retention": [0, 0, 0]}},
            "with 'retention' set",
        ),
        (
            {
                "retention": [0.9] * 3,
                "surprise": {"yes": 1, "no": 1, "step": [0] * 3, "retention": [0] * 3},
            },
            "two different rewards",
        ),
        (
            {
                "retention": [0.9] * 3,
                "surprise": {"yes": 1, "no": 0, "step": [0] * 2, "retention": [0] * 3},
            },
            "'step' has shape",
        ),
    ],
)
def test_a_bad_anchor_or_retention_is_refused_on_load(
    tmp_path: Path, changes: dict[str, object], message: str
) -> None:
    path = tmp_path / "generic-k4"
    make_checkpoint(path, seed=2)  # three answers' step sizes
    _rewrite(path, **changes)
    with pytest.raises(ValueError) as refused:
        load_checkpoint(path)
    assert message in str(refused.value) and str(path) in str(refused.value)


def test_a_checkpoint_without_anchor_or_retention_is_what_it_always_was() -> None:
    old = load_checkpoint(REPLICATION[0])
    assert old.offset_for(old.params) is None and old.retention_after(3) == 1.0
    anchored = dataclasses.replace(old, prior=np.full(old.n_arms, 1.0 / old.n_arms))
    assert isinstance(anchored, Checkpoint)
    np.testing.assert_allclose(
        MetaPolicyLearner(anchored).probabilities(), anchored.prior, rtol=0, atol=1e-15
    )


def test_surprise_measures_how_unexpected_an_answer_was() -> None:
    assert surprise(0.99, 0.0, 1.0, 0.0) == pytest.approx(0.99)  # "no" to the sure question
    assert surprise(0.01, 1.0, 1.0, 0.0) == pytest.approx(0.99)  # "yes" to a written-off one
    assert surprise(0.5, 1.0, 1.0, 0.0) == pytest.approx(0.5)
    assert surprise(0.9, 5.0, 5.0, -5.0) == pytest.approx(0.1)  # any reward map
    np.testing.assert_allclose(surprise(np.array([0.2, 0.8]), np.array([0.0, 1.0]), 1, 0), 0.2)


def test_zero_gates_are_no_gates_and_surprise_forgets_more() -> None:
    checkpoint = load_checkpoint(SHIPPED[0])
    assert checkpoint.retention is not None
    zero = SurpriseGates(1.0, 0.0, np.zeros(checkpoint.horizon), np.zeros(checkpoint.horizon))
    plain = dataclasses.replace(checkpoint, gates=None)
    gated = dataclasses.replace(checkpoint, gates=zero)
    for index in (0, 5, 20):
        step, rho = plain.step_and_retention(index, 0.9, 0.0)
        g_step, g_rho = gated.step_and_retention(index, 0.9, 0.0)
        assert g_step == pytest.approx(step, rel=1e-15) and g_rho == pytest.approx(rho, rel=1e-14)
    forget = SurpriseGates(1.0, 0.0, np.zeros(checkpoint.horizon), -np.ones(checkpoint.horizon))
    keen = dataclasses.replace(checkpoint, gates=forget)
    calm = keen.step_and_retention(2, 0.9, 1.0)[1]  # the expected yes
    shock = keen.step_and_retention(2, 0.9, 0.0)[1]  # the unexpected no
    assert shock < calm < checkpoint.retention_after(2)
    _, rhos = keen.step_and_retention(2, np.array([0.9, 0.9]), np.array([1.0, 0.0]))
    assert np.shape(rhos) == (2,) and rhos[1] == pytest.approx(shock)


@pytest.mark.parametrize("path", SHIPPED, ids=_names(SHIPPED))
def test_a_yes_leaves_the_asked_question_likelier_than_a_no(path: Path) -> None:
    """Every baseline lies between the rewards of no and yes, so no answer's sign is reversed: at
    every answer, after the same history, a yes leaves the asked question likelier than a no.
    (Either may lower it from a belief above the forgetting step's cap, as the filter's hazard
    does.)"""
    checkpoint = load_checkpoint(path)
    model = trained_feedback(checkpoint)
    assert np.all(checkpoint.baselines > model.no) and np.all(checkpoint.baselines < model.yes)
    for answers_before in range(checkpoint.horizon):
        after = {}
        for reward in (model.yes, model.no):
            learner = MetaPolicyLearner(checkpoint)
            for _ in range(answers_before):
                learner.update(1, model.no)
            learner.update(0, reward)
            after[reward] = learner.probabilities()[0]
        assert after[model.yes] > after[model.no], answers_before


def test_a_state_carries_its_start_and_a_bad_one_is_refused() -> None:
    checkpoint = load_checkpoint(SHIPPED[0])
    plain = MetaPolicyLearner(checkpoint)
    plain.update(0, 1.0)
    random = MetaPolicyLearner.random_init(checkpoint, np.random.default_rng(1))
    random.load_state_dict(plain.state_dict())  # a checkpoint-start state: the anchor follows
    assert random.probabilities().tobytes() == plain.probabilities().tobytes()
    state = MetaPolicyLearner.random_init(checkpoint, np.random.default_rng(2)).state_dict()
    without = {k: v for k, v in state.items() if k != "initial"}
    with pytest.raises(ValueError, match="record its initial weights"):
        MetaPolicyLearner(checkpoint).load_state_dict(without)
    broken = MetaPolicyLearner.random_init(checkpoint, np.random.default_rng(3))
    broken._initial["b2"][0] = np.nan  # a corrupted stored start
    with pytest.raises(ValueError, match="finite numbers"):
        MetaPolicyLearner(checkpoint).load_state_dict(broken.state_dict())


def _remembering(checkpoint: Checkpoint) -> Checkpoint:
    """``checkpoint`` with gates that also see the surprises so far (issue 36), coefficients
    away from zero so that forgetting them would show."""
    assert checkpoint.gates is not None
    horizon = checkpoint.horizon
    gates = dataclasses.replace(checkpoint.gates, memory_step=np.linspace(-1.5, 0.5, horizon))
    return dataclasses.replace(checkpoint, gates=gates)


def _untraced() -> Checkpoint:
    """The first shipped checkpoint without a per-question trace (the expected memory below is
    computed without one; affection's ships with a trace since issue 36)."""
    return next(c for c in map(load_checkpoint, SHIPPED) if not c.traces)


def test_a_surprise_memory_is_kept_in_the_state_and_changes_later_steps() -> None:
    plain = _untraced()
    checkpoint = _remembering(plain)
    assert checkpoint.remembers and not plain.remembers
    learner = MetaPolicyLearner(checkpoint)
    answers = [(0, 1.0), (0, 0.0), (1, 1.0), (0, 1.0)]
    expected = 0.0
    for action, reward in answers:
        p_asked = learner.policy()[action]  # the gates see the trained policy
        rho = checkpoint.step_and_retention(learner.answers, p_asked, reward, expected)[1]
        expected = float(rho) * (expected + float(surprise(p_asked, reward, 1.0, 0.0)))
        learner.update(action, reward)
    assert learner.surprise_memory == pytest.approx(expected, rel=1e-15) and expected > 0.1
    state = learner.state_dict()
    assert state["surprise_memory"] == learner.surprise_memory
    restored = MetaPolicyLearner(checkpoint)
    restored.load_state_dict(json.loads(json.dumps(state)))
    assert restored.state_dict() == state
    for twin in (learner, restored):
        twin.update(2, 1.0)
    assert restored.probabilities().tobytes() == learner.probabilities().tobytes()
    forgetful = MetaPolicyLearner(checkpoint)  # the same answers with the memory zeroed
    forgetful.load_state_dict({**state, "surprise_memory": 0.0})
    forgetful.update(2, 1.0)
    assert not np.allclose(forgetful.probabilities(), learner.probabilities())
    learner.reset()
    assert learner.surprise_memory == 0.0


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"surprise_memory": None}, "must record its surprise memory"),
        ({"surprise_memory": -0.5}, "finite and ≥ 0"),
        ({"surprise_memory": float("inf")}, "finite and ≥ 0"),
        ({"surprise_memory": True}, "must record its surprise memory"),
        ({"surprise_memory": [0.2]}, "must record its surprise memory"),
    ],
)
def test_a_state_without_its_surprise_memory_is_refused(
    change: dict[str, object], message: str
) -> None:
    checkpoint = _remembering(load_checkpoint(SHIPPED[0]))
    state = MetaPolicyLearner(checkpoint).state_dict()
    if change["surprise_memory"] is None:
        del state["surprise_memory"]
    else:
        state.update(change)
    with pytest.raises(ValueError, match=message):
        MetaPolicyLearner(checkpoint).load_state_dict(state)
    plain = load_checkpoint(SHIPPED[0])  # a memory its checkpoint does not keep
    invented = {**MetaPolicyLearner(plain).state_dict(), "surprise_memory": 0.0}
    with pytest.raises(ValueError, match="does not keep"):
        MetaPolicyLearner(plain).load_state_dict(invented)


def test_the_batch_learner_remembers_surprises_as_one_learner_does() -> None:
    checkpoint = _remembering(load_checkpoint(SHIPPED[0]))
    rng = np.random.default_rng(5)
    actions = rng.integers(0, 4, size=(6, 3))
    rewards = rng.integers(0, 2, size=(6, 3)).astype(float)
    batch = BatchMetaPolicy(checkpoint)
    for t in range(6):
        batch.update(actions[t], rewards[t])
    for row in range(3):
        learner = MetaPolicyLearner(checkpoint)
        for t in range(6):
            learner.update(int(actions[t, row]), float(rewards[t, row]))
        np.testing.assert_allclose(batch.probabilities()[row], learner.probabilities(), rtol=1e-12)
        assert np.asarray(batch.memory)[row] == pytest.approx(learner.surprise_memory, rel=1e-12)


def test_a_checkpoint_with_a_bad_memory_is_refused(tmp_path: Path) -> None:
    source = load_checkpoint(SHIPPED[0])
    path = tmp_path / source.path.name
    path.mkdir()
    for name in ("config.json", "metrics.json"):
        (path / name).write_text((source.path / name).read_text())
    weights = json.loads((source.path / WEIGHTS_FILE).read_text())

    def write(memory: object) -> None:
        weights["surprise"]["memory_step"] = memory
        data = json.dumps(weights).encode()
        (path / WEIGHTS_FILE).write_bytes(data)
        (path / HASH_FILE).write_text(f"{hashlib.sha256(data).hexdigest()}  {WEIGHTS_FILE}\n")

    write([0.0] * (source.horizon - 1))
    with pytest.raises(ValueError, match="'memory_step' has shape"):
        load_checkpoint(path)
    write([0.0] * (source.horizon - 1) + [float("nan")])
    with pytest.raises(ValueError, match="NaN"):
        load_checkpoint(path)
    write([0.25] * source.horizon)
    assert load_checkpoint(path).remembers
