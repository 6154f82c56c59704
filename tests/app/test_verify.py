"""``trustlab verify``: findings name sessions as people do; replays tolerate rounding only."""

from __future__ import annotations

import hashlib
import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from sqlalchemy import select, update

from app.protocol import parse_protocol
from app.services import studies
from app.services.audit import Actor
from app.services.sessions import learners, replies, verify
from app.tables import Answer, LearnerState, Prompt, Run, RunStatus, StudySession
from models.checkpoints import (
    HASH_FILE,
    PRETRAINED_DIR,
    REPLICATION_DIR,
    TRACE_GATES,
    WEIGHTS_FILE,
    load_checkpoint,
    with_temperature,
)
from models.learners.meta_policy import MetaPolicyLearner
from models.learners.mlp_policy import softmax
from tests.conftest import Lab, protocol_text


def _findings(lab: Lab) -> list[tuple[str, str]]:
    with lab.database.read_session() as db:
        report = verify.verify_study(db, study_name=lab.study)
    return [(f.check, f.detail) for f in report.findings]


def test_findings_name_the_familiarisation_run_not_session_0(lab: Lab) -> None:
    lab.enrol_and_assign()
    lab.start_session()
    lab.run_session()
    lab.start_session()
    lab.run_session()
    assert _findings(lab) == []
    with lab.database.writing() as db:
        sessions = {s.number: s for s in db.scalars(select(StudySession))}
        db.execute(update(StudySession).where(StudySession.number == 0).values(ended_at=None))
        for number in (0, 1):
            last = db.scalars(
                select(Run).where(Run.session_id == sessions[number].id).order_by(Run.number.desc())
            ).first()
            assert last is not None
            db.execute(update(Run).where(Run.id == last.id).values(status=RunStatus.RUNNING))
        db.commit()
    findings = _findings(lab)
    assert findings == [
        ("timeline", "the familiarisation run: status and end time disagree"),
        ("timeline", "the familiarisation run is running out of turn"),
        ("timeline", "session 1 run 3 is running out of turn"),
    ]
    assert not any("session 0" in detail for _, detail in findings)


def test_a_reply_probability_off_the_protocols_basis_is_found(
    lab: Lab, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The shipped basis is "heard": replies a faulty server chose by the asked question's
    probability (the "chosen" rule) are found, even where their level happens to agree."""
    lab.enrol_and_assign()
    lab.start_session()
    with monkeypatch.context() as patched:
        patched.setattr(replies, "reply_probability", lambda basis, **given: given["asked"])
        lab.run_session()
    with lab.database.read_session() as db:
        steps = sorted(db.scalars(select(Prompt.id)))
    assert _findings(lab) == [
        ("step", f"step {step}: reply probability does not follow replies.basis 'heard'")
        for step in steps
    ]


def _shift(values: list[float], by: float) -> list[float]:
    return [values[0] + by, values[1] - by, *values[2:]]


def test_rounding_differences_pass_and_real_differences_are_found(
    lab: Lab, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A server on another CPU kernel differs from the replay in the last bits (1e-16): clean.
    A change a fault would cause (1e-6 and up) is still a finding."""
    lab.enrol_and_assign()
    for _ in ("familiarisation", "session 1"):
        lab.start_session()
        lab.run_session()
    assert _findings(lab) == []

    exact = learners.probabilities_list
    for by, found in ((3e-16, False), (1e-6, True)):
        monkeypatch.setattr(
            learners, "probabilities_list", lambda learner, by=by: _shift(exact(learner), by)
        )
        findings = _findings(lab)
        assert bool(findings) is found
        assert all(check == "replay" and "probabilities differ" in d for check, d in findings)
    monkeypatch.setattr(learners, "probabilities_list", exact)

    with lab.database.writing() as db:
        row = db.scalars(select(LearnerState).where(LearnerState.category == "cognition")).one()
        state = dict(row.state)

    def store(learner_state: dict[str, object]) -> list[tuple[str, str]]:
        with lab.database.writing() as db:
            db.execute(
                update(LearnerState).where(LearnerState.id == row.id).values(state=learner_state)
            )
            db.commit()
        return _findings(lab)

    weights = state["weights"]
    assert isinstance(weights, list)
    assert store({**state, "weights": _shift(weights, 1e-15 * abs(weights[0]))}) == []
    differs = [("replay", "cognition learner: stored state differs from the replayed one")]
    assert store({**state, "weights": _shift(weights, 1e-6 * (1.0 + abs(weights[0])))}) == differs
    assert store({**state, "updates": True}) == differs


def test_close_compares_structure_exactly_and_numbers_within_the_tolerance() -> None:
    assert verify._close({"a": [1.0, 2.0]}, {"a": [1.0 + 1e-15, 2.0]})
    assert not verify._close({"a": [1.0, 2.0]}, {"a": [1.0, 2.0, 3.0]})
    assert not verify._close({"a": 1.0}, {"b": 1.0})
    assert not verify._close([0.5], [0.5 + 1e-7])
    assert not verify._close("exp3", "meta")
    assert not verify._close(True, 1)
    assert verify._close(1e6, 1e6 * (1 + 1e-12))
    assert not verify._close(5, 5.000000001)  # an integer is compared exactly
    assert verify._close(3, 3) and verify._close(float("inf"), float("inf"))
    assert not verify._close(2**62, 2**62 + 10**8)


ROBUST_TABLE = (
    'kind = "binary"\nslip_values = [0.0, 0.025, 0.05, 0.075, 0.1]\n'
    "slip_weights = [0.2, 0.2, 0.2, 0.2, 0.2]\nhazard = 0.02"
)


@pytest.mark.parametrize("participants", ["robust", "paper"])
def test_verify_replays_learners_of_the_default_and_the_replication_set(
    lab: Lab, participants: str
) -> None:
    """Both C2 sets replay: the default set (the shipped protocol's model) and the replication
    set (the paper's model), also for a learner enrolled before issue 19, whose recorded path is
    where the replication set used to be."""
    changes = {'learner = "exp3"': 'learner = "meta"'}
    if participants == "paper":
        changes[ROBUST_TABLE] = 'kind = "gaussian"'
    with lab.database.writing() as db:
        studies.create_study(
            db, name="c2", loaded=parse_protocol(protocol_text(**changes)), actor=Actor.system()
        )
    c2 = replace(lab, study="c2")
    c2.enrol_and_assign()
    for _ in ("familiarisation", "session 1"):
        c2.start_session()
        c2.run_session(preferred=1)
    expected = PRETRAINED_DIR if participants == "robust" else REPLICATION_DIR
    with lab.database.writing() as db:
        states = list(db.scalars(select(LearnerState)))
        assert states and {s.kind for s in states} == {"meta"}
        for state in states:
            assert Path(state.config["checkpoint"]).parent == expected / "online"
            if participants == "paper":  # as a study enrolled before the robust set shipped
                old_place = PRETRAINED_DIR / "online" / Path(state.config["checkpoint"]).name
                db.execute(
                    update(LearnerState)
                    .where(LearnerState.id == state.id)
                    .values(config={**state.config, "checkpoint": str(old_place)})
                )
        db.commit()
    assert _findings(c2) == []
    with lab.database.writing() as db:  # and a real difference is still found
        first = db.scalars(select(LearnerState)).first()
        assert first is not None
        other = REPLICATION_DIR if participants == "robust" else PRETRAINED_DIR
        name = Path(first.config["checkpoint"]).name
        db.execute(
            update(LearnerState)
            .where(LearnerState.id == first.id)
            .values(checkpoint_sha256=load_checkpoint(other / "online" / name).sha256)
        )
        db.commit()
    assert _findings(c2)


def test_verify_replays_a_learner_that_keeps_a_per_question_surprise_trace(
    lab: Lab, tmp_path: Path
) -> None:
    """A checkpoint whose gates trace the surprises per question (issue 36): the trace is in
    every stored state, verify replays it, and a trace edited in the database is found."""
    source = PRETRAINED_DIR / "online" / "cognition-k4"
    weights = json.loads((source / WEIGHTS_FILE).read_text())
    horizon = len(weights["step_sizes"])
    weights["surprise"]["trace"] = {
        name: np.linspace(-1.0 + 0.5 * i, 1.0, horizon).tolist()
        for i, name in enumerate(TRACE_GATES)
    }
    traced = tmp_path / "cognition-k4"
    traced.mkdir()
    data = json.dumps(weights).encode()
    (traced / WEIGHTS_FILE).write_bytes(data)
    (traced / HASH_FILE).write_text(f"{hashlib.sha256(data).hexdigest()}  {WEIGHTS_FILE}\n")
    for name in ("config.json", "metrics.json"):
        (traced / name).write_text((source / name).read_text())
    assert load_checkpoint(traced).traces
    changes = {
        'learner = "exp3"': 'learner = "meta"',
        'checkpoint = "shipped"': f'checkpoint = "{traced}"',
    }
    with lab.database.writing() as db:
        studies.create_study(
            db, name="tr", loaded=parse_protocol(protocol_text(**changes)), actor=Actor.system()
        )
    c2 = replace(lab, study="tr")
    c2.enrol_and_assign()
    for _ in ("familiarisation", "session 1"):
        c2.start_session()
        c2.run_session(preferred=1)
    with lab.database.read_session() as db:
        states = [row.state for row in db.scalars(select(LearnerState))]
    assert states and all(len(s["surprise_trace"]) == 4 for s in states)
    assert any(max(s["surprise_trace"]) > 0 for s in states)
    assert _findings(c2) == []
    with lab.database.writing() as db:
        first = db.scalars(select(LearnerState)).first()
        assert first is not None
        trace = list(first.state["surprise_trace"])
        trace[0] += 0.1
        db.execute(
            update(LearnerState)
            .where(LearnerState.id == first.id)
            .values(state={**first.state, "surprise_trace": trace})
        )
        db.commit()
    assert any("stored state differs" in detail for _, detail in _findings(c2))


def test_verify_replays_a_learner_on_a_calibrated_checkpoint(lab: Lab, tmp_path: Path) -> None:
    """A checkpoint with a temperature (issue 36): every learner asks with and stores the
    tempered probabilities (not the trained policy's), and verify replays them from the recorded
    checkpoint."""
    shipped = load_checkpoint(PRETRAINED_DIR / "online" / "cognition-k4")
    hot = with_temperature(
        replace(shipped, temperature=1.0), 1.3, tmp_path / "hot" / "cognition-k4", note={}
    )
    changes = {
        'learner = "exp3"': 'learner = "meta"',
        'checkpoint = "shipped"': f'checkpoint = "{hot.path}"',
    }
    with lab.database.writing() as db:
        studies.create_study(
            db, name="hot", loaded=parse_protocol(protocol_text(**changes)), actor=Actor.system()
        )
    c2 = replace(lab, study="hot")
    c2.enrol_and_assign()
    for _ in ("familiarisation", "session 1"):
        c2.start_session()
        c2.run_session(preferred=1)
    assert _findings(c2) == []
    with lab.database.read_session() as db:
        rows = [(r.checkpoint_sha256, r.state) for r in db.scalars(select(LearnerState))]
        after = [a.probabilities_after for a in db.scalars(select(Answer))]
        prompts = list(db.scalars(select(Prompt)))
    assert rows and all(sha256 == hot.sha256 for sha256, _ in rows)
    for _, state in rows:  # the last answer stored what the tempered learner reports
        learner = MetaPolicyLearner(hot)
        learner.load_state_dict(state)
        logits = np.log(learner.policy())
        tempered, trained = softmax(logits / 1.3), softmax(logits)
        assert any(np.allclose(p, tempered, rtol=0, atol=1e-12) for p in after)
        assert not any(np.allclose(p, trained, rtol=0, atol=1e-6) for p in after)
    assert any(not np.allclose(p.probabilities, 0.25) for p in prompts)  # it did adapt
