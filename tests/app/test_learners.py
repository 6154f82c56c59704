"""Restoring C2 learners from the exact checkpoint they were created with, across upgrades."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from app.errors import Conflict
from app.protocol import Protocol, default_protocol, parse_protocol
from app.services.sessions.learners import (
    LearnerSpec,
    build,
    feedback_model,
    learner_spec,
    recorded_checkpoint,
)
from models.checkpoints import (
    HASH_FILE,
    PRETRAINED_DIR,
    REPLICATION_DIR,
    RETIRED_DIR,
    load_checkpoint,
    shipped_checkpoint,
    trained_feedback,
)
from tests.models.conftest import make_checkpoint


def _spec(path: Path, sha256: str) -> LearnerSpec:
    return LearnerSpec("meta", 4, {"checkpoint": str(path)}, sha256)


def test_a_replaced_checkpoint_is_found_by_its_hash_beside_the_recorded_path(
    tmp_path: Path,
) -> None:
    path = tmp_path / "set" / "generic-k4"
    original = make_checkpoint(path, seed=1)
    spec = _spec(path, original.sha256)
    before = build(spec).probabilities()

    shutil.copytree(path, tmp_path / "set" / "old" / "generic-k4")
    shutil.rmtree(path)
    replacement = make_checkpoint(path, seed=2)
    assert replacement.sha256 != original.sha256

    found = recorded_checkpoint(spec)
    assert found.sha256 == original.sha256
    assert found.path == tmp_path / "set" / "old" / "generic-k4"
    np.testing.assert_array_equal(build(spec).probabilities(), before)


def test_a_labs_own_retired_set_is_searched(tmp_path: Path) -> None:
    """A lab retires its own set as docs/engine.md says: ``<set>/retired/<name>/...``."""
    path = tmp_path / "lab-set" / "online" / "generic-k4"
    original = make_checkpoint(path, seed=1)
    retired = tmp_path / "lab-set" / "retired" / "first" / "generic-k4"
    shutil.copytree(path, retired)
    shutil.rmtree(path)
    make_checkpoint(path, seed=2)
    assert recorded_checkpoint(_spec(path, original.sha256)).path == retired


def test_without_the_original_anywhere_the_error_says_what_changed(tmp_path: Path) -> None:
    path = tmp_path / "set" / "generic-k4"
    original = make_checkpoint(path, seed=1)
    shutil.rmtree(path)
    make_checkpoint(path, seed=2)
    with pytest.raises(ValueError, match="has changed since the learner was created"):
        recorded_checkpoint(_spec(path, original.sha256))
    shutil.rmtree(path)
    with pytest.raises(ValueError, match="does not exist"):
        recorded_checkpoint(_spec(path, original.sha256))


def test_an_edited_original_is_still_refused(tmp_path: Path) -> None:
    """The hash file alone only finds a candidate; its weights are verified before use."""
    path = tmp_path / "set" / "generic-k4"
    original = make_checkpoint(path, seed=1)
    copy = tmp_path / "set" / "old" / "generic-k4"
    shutil.copytree(path, copy)
    shutil.rmtree(path)
    make_checkpoint(path, seed=2)
    weights = copy / "weights.json"
    weights.write_bytes(weights.read_bytes().replace(b"0.", b"1.", 1))
    with pytest.raises(ValueError, match="does not match its hash"):
        recorded_checkpoint(_spec(path, original.sha256))


def test_learners_enrolled_with_a_retired_shipped_checkpoint_still_restore() -> None:
    """A study enrolled before the online checkpoints were replaced keeps its learners."""
    retired = sorted(RETIRED_DIR.glob(f"*/*/{HASH_FILE}"))
    assert retired, "the retired checkpoint set is missing"
    for hash_file in retired:
        old = load_checkpoint(hash_file.parent)
        current = shipped_checkpoint(old.n_arms, category=old.category)
        assert load_checkpoint(current).sha256 != old.sha256
        spec = LearnerSpec("meta", old.n_arms, {"checkpoint": str(current)}, old.sha256)
        assert recorded_checkpoint(spec).sha256 == old.sha256


OTHER = '[learners.feedback]\nkind = "binary"\nslip_values = [0.0, 0.1]\nslip_weights = [0.5, 0.5]'
"""A feedback model neither shipped set was trained for (the default set's hazard is .02)."""
PAPER = '[learners.feedback]\nkind = "gaussian"\nvariance = 0.1'


def _protocol(feedback: str) -> Protocol:
    """The shipped protocol with its ``[learners.feedback]`` table replaced by ``feedback``."""
    text = default_protocol().source_text
    start = text.index("[learners.feedback]")
    end = text.index("[[categories]]")
    return parse_protocol(text[:start] + feedback + "\n\n" + text[end:]).protocol


def test_each_feedback_model_gets_the_set_trained_for_it() -> None:
    shipped = default_protocol().protocol
    category = shipped.categories[0]
    robust = learner_spec(shipped, "C2", category, None)
    assert "trained_for_other_feedback" not in robust.config
    assert Path(robust.config["checkpoint"]).parent == PRETRAINED_DIR / "online"
    paper = learner_spec(_protocol(PAPER), "C2", category, None)
    assert "trained_for_other_feedback" not in paper.config
    assert Path(paper.config["checkpoint"]).parent == REPLICATION_DIR / "online"
    assert robust.checkpoint_sha256 != paper.checkpoint_sha256


def test_a_checkpoint_trained_for_other_participants_is_refused_unless_accepted() -> None:
    category = default_protocol().protocol.categories[0]
    with pytest.raises(Conflict) as refused:
        learner_spec(_protocol(OTHER), "C2", category, None)
    message = refused.value.message
    assert (
        "was meta-trained for binary answers, slips 0/0.025/0.05/0.075/0.1 equally likely, "
        "hazard 0.02" in message
    )
    assert "declares binary answers, slips 0/0.1 equally likely, hazard 0" in message
    assert "learners.feedback.accept_other_checkpoint = true" in message
    accepted = learner_spec(
        _protocol(OTHER + "\naccept_other_checkpoint = true"), "C2", category, None
    )
    assert accepted.config["trained_for_other_feedback"]["hazard"] == 0.02  # recorded
    assert build(accepted).probabilities().shape == (len(category.questions),)
    exp3 = learner_spec(_protocol(OTHER), "C1", category, None)  # Exp3 is not trained
    assert exp3.kind == "exp3"


def test_learners_enrolled_before_the_robust_set_shipped_still_restore() -> None:
    """Until issue 19 the paper's-model set lived where the robust set is now: a learner that
    recorded that path and an old hash is restored from the replication set, by its hash."""
    for old_path in sorted((REPLICATION_DIR / "online").iterdir()):
        old = load_checkpoint(old_path)
        recorded = PRETRAINED_DIR / "online" / old_path.name
        assert load_checkpoint(recorded).sha256 != old.sha256
        spec = LearnerSpec("meta", old.n_arms, {"checkpoint": str(recorded)}, old.sha256)
        assert recorded_checkpoint(spec).path == old_path


def test_the_protocols_feedback_model_carries_its_reward_map() -> None:
    protocol = _protocol(OTHER)
    model = feedback_model(protocol)
    assert (model.kind, model.slips, model.slip_weights) == ("binary", (0.0, 0.1), (0.5, 0.5))
    assert (model.yes, model.no) == (protocol.reward.yes, protocol.reward.no)
    assert trained_feedback(load_checkpoint(shipped_checkpoint(4, category="conation"))).same_as(
        feedback_model(default_protocol().protocol)
    )
