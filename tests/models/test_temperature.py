"""A checkpoint's temperature (issue 36): a calibration of C2's output chosen after training,
hashed with the weights, honoured by the learner, the batch learner and a restored state, and
refused when it is not a sensible number."""

from __future__ import annotations

import dataclasses
import hashlib
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from models.checkpoints import (
    HASH_FILE,
    PRETRAINED_DIR,
    RETIRED_DIR,
    WEIGHTS_FILE,
    Checkpoint,
    find_by_sha256,
    load_checkpoint,
    rewrite_checkpoint,
    shipped_checkpoint,
    with_temperature,
)
from models.learners.meta_policy import MetaPolicyLearner
from models.learners.mlp_policy import hidden_and_logits, softmax
from models.seed_selection import filter_validation, temperature_candidates
from models.simulate import BatchMetaPolicy
from tests.models.conftest import make_checkpoint

ANSWERS = [(0, 1.0), (1, 0.0), (2, 0.0), (3, 1.0), (3, 1.0), (0, 0.0), (3, 1.0)]
"""Two noes, a yes, a confirmation, a contradiction: every gate of the shipped checkpoint moves."""


def _trained() -> Checkpoint:
    """The shipped cognition checkpoint as trained (temperature 1), in memory."""
    shipped = load_checkpoint(shipped_checkpoint(4, "cognition", directory=PRETRAINED_DIR), 4)
    return dataclasses.replace(shipped, temperature=1.0)


def _feed(learner: MetaPolicyLearner) -> MetaPolicyLearner:
    for action, reward in ANSWERS:
        learner.update(action, reward)
    return learner


def _weights(learner: MetaPolicyLearner) -> dict[str, Any]:
    return learner.state_dict()["params"]


def _rewrite(checkpoint: Checkpoint, directory: Path, **extra: Any) -> Checkpoint:
    return rewrite_checkpoint(checkpoint, directory, metrics={}, **extra)


def test_a_checkpoint_without_a_temperature_writes_no_field_and_keeps_its_hash(
    tmp_path: Path,
) -> None:
    trained = _trained()
    plain = _rewrite(trained, tmp_path / "a")
    again = _rewrite(trained, tmp_path / "b")
    assert "temperature" not in json.loads((plain.path / WEIGHTS_FILE).read_text())
    assert plain.temperature == 1.0 and plain.sha256 == again.sha256
    tempered = with_temperature(plain, 1.02, tmp_path / "c", note={"why": "test"})
    assert json.loads((tempered.path / WEIGHTS_FILE).read_text())["temperature"] == 1.02
    assert tempered.temperature == 1.02 and tempered.sha256 != plain.sha256
    assert tempered.metrics["temperature"] == {
        "why": "test",
        "value": 1.02,
        "calibrates": plain.sha256,
    }
    for name, array in plain.params.items():
        assert tempered.params[name].tobytes() == array.tobytes()
    with pytest.raises(ValueError, match="calibrated already"):
        with_temperature(tempered, 1.05, tmp_path / "d", note={})


def test_a_tempered_learner_asks_with_the_tempered_policy_and_learns_as_trained() -> None:
    """It reports ``softmax(logits / T)``; its weights after the same answers are the trained
    learner's bit for bit (the update and the surprise gates see the untempered policy)."""
    trained = _trained()
    assert trained.gates is not None  # the gates read the asked question's probability
    tempered = dataclasses.replace(trained, temperature=1.3)
    plain, warm = _feed(MetaPolicyLearner(trained)), _feed(MetaPolicyLearner(tempered))
    assert _weights(warm) == _weights(plain)
    logits = hidden_and_logits(warm._params, tempered.observation, warm._offset)[1]
    # A uniform prior: the departure from it over T is the logits over T, up to a constant.
    np.testing.assert_allclose(warm.probabilities(), softmax(logits / 1.3), rtol=0, atol=1e-15)
    np.testing.assert_array_equal(plain.probabilities(), softmax(logits))
    np.testing.assert_array_equal(warm.policy(), plain.probabilities())
    assert warm.probabilities().max() < plain.probabilities().max()


def test_a_temperature_scales_what_was_learned_and_the_start_stays_the_prior(
    tmp_path: Path,
) -> None:
    """With a prior of its own (a population's) a tempered learner still asks the first
    question with the prior exactly; after answers its logits' departure from the prior is
    the trained policy's over T."""
    prior = (0.4, 0.3, 0.2, 0.1)
    trained = make_checkpoint(tmp_path / "pop", rule="natural_expected", prior=prior)
    hot = dataclasses.replace(trained, temperature=1.5)
    learner = MetaPolicyLearner(hot)
    np.testing.assert_allclose(learner.probabilities(), prior, rtol=0, atol=1e-15)
    for action, reward in ANSWERS:
        learner.update(action, reward)
    policy, tempered = np.log(learner.policy()), np.log(learner.probabilities())
    departure = (policy - np.log(prior)) / 1.5 + np.log(prior)
    np.testing.assert_allclose(
        tempered - tempered.mean(), departure - departure.mean(), rtol=0, atol=1e-12
    )
    batch = BatchMetaPolicy(hot)
    np.testing.assert_allclose(batch.probabilities()[0], prior, rtol=0, atol=1e-15)


def test_a_temperature_of_one_is_the_trained_policy_bit_for_bit() -> None:
    trained = _trained()
    one = dataclasses.replace(trained, temperature=1.0)
    a, b = MetaPolicyLearner(trained), MetaPolicyLearner(one)
    for action, reward in ANSWERS:
        a.update(action, reward)
        b.update(action, reward)
        assert a.probabilities().tobytes() == b.probabilities().tobytes()


def test_the_batch_learner_is_tempered_as_the_learner_is() -> None:
    tempered = dataclasses.replace(_trained(), temperature=1.02)
    batch = BatchMetaPolicy(tempered)
    singles = [MetaPolicyLearner(tempered) for _ in range(3)]
    rng = np.random.default_rng(5)
    for _ in range(8):
        probs = np.broadcast_to(batch.probabilities(), (3, 4))
        for row, learner in zip(probs, singles, strict=True):
            np.testing.assert_allclose(row, learner.probabilities(), rtol=0, atol=1e-12)
        actions = rng.integers(0, 4, size=3)
        rewards = rng.integers(0, 2, size=3).astype(float)
        batch.update(actions, rewards)
        for learner, action, reward in zip(singles, actions, rewards, strict=True):
            learner.update(int(action), float(reward))


def test_a_tempered_learners_state_restores_to_the_same_probabilities(tmp_path: Path) -> None:
    trained = _rewrite(_trained(), tmp_path / "trained")
    tempered = with_temperature(trained, 1.02, tmp_path / "tempered", note={})
    learner = _feed(MetaPolicyLearner(load_checkpoint(tempered.path)))
    state = json.loads(json.dumps(learner.state_dict()))
    restored = MetaPolicyLearner(load_checkpoint(tempered.path))
    restored.load_state_dict(state)
    assert restored.probabilities().tobytes() == learner.probabilities().tobytes()
    assert restored.state_dict() == learner.state_dict()
    # The trained checkpoint's learner cannot take it over: another hash, another policy.
    with pytest.raises(ValueError, match="belongs to checkpoint"):
        MetaPolicyLearner(trained).load_state_dict(state)


@pytest.mark.parametrize(
    "value", [0, 0.0, -1.02, 0.49, 2.01, 1e308, True, "1.02", None, [1.02], float("nan")]
)
def test_a_checkpoint_with_a_bad_temperature_is_refused(tmp_path: Path, value: object) -> None:
    trained = _rewrite(_trained(), tmp_path / "trained")
    weights = json.loads((trained.path / WEIGHTS_FILE).read_text())
    weights["temperature"] = value
    data = json.dumps(weights).encode()  # NaN as the literal json reads back
    (trained.path / WEIGHTS_FILE).write_bytes(data)
    (trained.path / HASH_FILE).write_text(f"{hashlib.sha256(data).hexdigest()}  {WEIGHTS_FILE}\n")
    with pytest.raises(ValueError, match=r"'temperature' must be a number from 0\.5 to 2"):
        load_checkpoint(trained.path)
    if isinstance(value, int | float):
        with pytest.raises(ValueError, match="'temperature'"):
            _rewrite(_trained(), tmp_path / "written", temperature=value)


def test_temperature_candidates_score_the_tempered_policy() -> None:
    """A temperature of 1 is the checkpoint as trained; another changes what is measured."""
    trained = _trained()
    found = temperature_candidates(
        trained, (1.0, 1.5), participants=300, score_participants=300, seed=11
    )
    assert [t for t, _ in found] == [1.0, 1.5]
    assert found[0][1].filter_score == filter_validation(trained, 300, 11).filter_score
    assert found[1][1].filter_score != found[0][1].filter_score
    assert found[1][1].figures != found[0][1].figures
    with pytest.raises(ValueError, match="calibrated already"):
        temperature_candidates(dataclasses.replace(trained, temperature=1.1), (1.0,))


def test_the_shipped_cognition_checkpoint_calibrates_the_retired_one() -> None:
    """What ships is the trained weights, bit for bit, plus the temperature the selection chose;
    the checkpoint it calibrates stays restorable among the retired ones."""
    shipped = load_checkpoint(shipped_checkpoint(4, "cognition", directory=PRETRAINED_DIR), 4)
    note = shipped.metrics["temperature"]
    assert shipped.temperature == note["value"] != 1.0
    source = find_by_sha256(note["calibrates"], [RETIRED_DIR])
    assert source is not None
    trained = load_checkpoint(source)
    assert trained.temperature == 1.0 and trained.config == shipped.config
    for name, array in trained.params.items():
        assert shipped.params[name].tobytes() == array.tobytes()
    weights = json.loads((shipped.path / WEIGHTS_FILE).read_text())
    del weights["temperature"]
    assert weights == json.loads((trained.path / WEIGHTS_FILE).read_text())
