"""The exact learner as a third condition (issue 36 item 3): a study with exp3, meta and bayes
conditions enrols, answers, replays in ``trustlab verify`` (and a tampered bayes learner is
reported), keeps three neutral labels when blinded, and a bayes condition the filter cannot run
is refused at study creation with the key path."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient
from sqlalchemy import select, update

from analysis.figures import PALETTE
from analysis.population import Population
from analysis.report import build_report
from analysis.study import analyse_study
from app.db import Database
from app.protocol import ProtocolError, parse_protocol
from app.services import studies
from app.services.analysis_views.study_data import load_dataset
from app.services.audit import Actor
from app.services.participants.enrolment import enroll_participant
from app.services.privacy.sites import Scope
from app.services.sessions import learner_cache, learners, populations, verify
from app.tables import Answer, LearnerState, Participant, Prompt, Role
from models.feedback import FeedbackModel
from models.learners.bayes import BayesLearner
from models.learners.belief import BeliefLearner
from models.replies import heard_probability
from tests.app.test_cli import run
from tests.app.test_condition_colours import _colours_of
from tests.conftest import Lab, UserClientFactory, protocol_text

THIRD = (
    '[[conditions]]\nid = "C3"\nlabel = "Exact filter"\nlearner = "bayes"\n'
    'neutral_label = "Group C"\n'
)
THREE = {
    'neutral_label = "Group B"\n': f'neutral_label = "Group B"\n\n{THIRD}',
    "block_sizes = [2, 4]": "block_sizes = [3, 6]",
}
"""The shipped protocol with a third condition, C3, that runs the exact filter."""

SQLITE = pytest.mark.parametrize("engine_name", ["sqlite"], indirect=True)
SHIPPED_FEEDBACK = (
    'kind = "binary"\nslip_values = [0.0, 0.025, 0.05, 0.075, 0.1]\n'
    "slip_weights = [0.2, 0.2, 0.2, 0.2, 0.2]\nhazard = 0.02\n"
)


def _bits(value: Any) -> Any:
    """A JSON value with every float as its exact bits."""
    if isinstance(value, dict):
        return {key: _bits(item) for key, item in value.items()}
    if isinstance(value, list):
        return [_bits(item) for item in value]
    return value.hex() if isinstance(value, float) else value


@pytest.fixture
def three(app: FastAPI, database: Database, user_client: UserClientFactory) -> Iterator[Lab]:
    """Study 'three' (C1 exp3, C2 meta, C3 bayes) and station 'lab-3'."""
    with database.writing() as db:
        loaded = parse_protocol(protocol_text(**THREE))
        studies.create_study(db, name="three", loaded=loaded, actor=Actor.system())
    admin = user_client(Role.ADMIN)
    assert admin.post("/api/v1/stations", json={"name": "lab-3"}).status_code == 201
    key = admin.post("/api/v1/stations/lab-3/devices", json={"label": "pepper"}).json()["key"]
    with TestClient(app, headers={"Authorization": f"Bearer {key}"}) as robot:
        yield Lab(app, database, "three", "lab-3", key, user_client(Role.EXPERIMENTER), robot, {})


def _one_per_condition(lab: Lab) -> dict[str, str]:
    """Enrol until every condition has a participant (blocks of 3 or 6: at most 5 needed)."""
    first: dict[str, str] = {}
    while len(first) < 3:
        code = lab.enrol_and_assign()
        listed = lab.experimenter.get(f"/api/v1/studies/{lab.study}/participants").json()
        condition = next(p["condition"] for p in listed if p["code"] == code)
        first.setdefault(condition, code)
    return first


def _findings(lab: Lab) -> list[tuple[str, str]]:
    with lab.database.read_session() as db:
        report = verify.verify_study(db, study_name=lab.study)
    return [(f.check, f.detail) for f in report.findings]


@SQLITE
def test_exp3_meta_and_bayes_enrol_answer_and_replay_in_verify(three: Lab) -> None:
    lab = three
    codes = _one_per_condition(lab)
    for code in codes.values():
        lab.experimenter.put(
            f"/api/v1/stations/{lab.station}/participant", json={"study": lab.study, "code": code}
        )
        for _ in ("familiarisation", "session 1"):
            lab.start_session()
            lab.run_session(preferred=1)
        lab.fill_pending_questionnaires()
    assert _findings(lab) == []
    # The dashboard draws a curve per condition, the third in the palette's third colour.
    data = lab.experimenter.get(f"/studies/{lab.study}/dashboard.json").json()
    for index, condition in enumerate(("C1", "C2", "C3")):
        assert _colours_of(data["adaptation"]["data"], condition) == {PALETTE[index]}
        assert _colours_of(data["measures"][0]["payload"]["data"], condition) == {PALETTE[index]}
    # So do the analysis and the report (the ANOVA itself: tests/analysis, with 2 or 3 groups).
    with lab.database.read_session() as db:
        result = analyse_study(
            load_dataset(db, scope=Scope.every_site(), study=studies.get_study(db, lab.study))
        )
    assert result.colors == {"C1": PALETTE[0], "C2": PALETTE[1], "C3": PALETTE[2]}
    assert "C3 (Exact filter)" in build_report(result)

    with lab.database.read_session() as db:
        bayes = db.scalars(select(Participant).where(Participant.code == codes["C3"])).one()
        rows = list(db.scalars(select(LearnerState).where(LearnerState.participant_id == bayes.id)))
        assert {row.kind for row in rows} == {"bayes"}
        assert rows[0].config["feedback"]["hazard"] == 0.02  # the protocol's model, recorded
        cognition = next(row for row in rows if row.category == "cognition")
        steps = db.execute(
            select(Prompt, Answer)
            .join(Answer, Answer.prompt_id == Prompt.id)
            .where(Prompt.participant_id == bayes.id, Prompt.category == "cognition")
            .where(Prompt.adapts)
            .order_by(Answer.learner_version)
        ).all()
        # Replayed here from the initial state, the stored state is the same bits, and so is
        # the live learner the server keeps between answers.
        replayed = learners.restore(cognition, initial=True)
        assert isinstance(replayed, BeliefLearner)
        for prompt, answer in steps:
            replayed.update(prompt.action, answer.reward)
        assert _bits(replayed.state_dict()) == _bits(cognition.state)
        believed = replayed.probabilities()
        assert believed[1] == believed.max() > 0.25  # three answers, all for the second key
        # "heard": the reply's probability is the filter's posterior of the asked question,
        # as the probability of the answer heard under the declared mean slip rate.
        prompt, answer = steps[-1]
        declared = FeedbackModel.from_json(cognition.config["feedback"])
        assert answer.probability == heard_probability(
            prompt.probabilities[prompt.action], said_yes=answer.answer, slip=declared.mean_slip
        )
    app_database: Database = lab.app.state.database
    with app_database.read_session() as db:
        cache = learner_cache.of(db)
        cached = cache.take(cognition.id, cognition.version, lambda: pytest.fail("not cached"))
    assert _bits(cached.state_dict()) == _bits(cognition.state)

    log_alpha = [list(row) for row in cognition.state["log_alpha"]]
    log_alpha[2][1] += 1e-6
    with lab.database.writing() as db:
        db.execute(
            update(LearnerState)
            .where(LearnerState.id == cognition.id)
            .values(state={**cognition.state, "log_alpha": log_alpha})
        )
        db.commit()
    differs = ("replay", "cognition learner: stored state differs from the replayed one")
    assert _findings(lab) == [differs]
    with lab.database.writing() as db:  # a learner config edited to another model replays wrong
        config = {**cognition.config, "feedback": {**cognition.config["feedback"], "hazard": 0.1}}
        db.execute(
            update(LearnerState).where(LearnerState.id == cognition.id).values(config=config)
        )
        db.commit()
    [(check, detail)] = _findings(lab)
    assert check == "replay" and detail.endswith("probabilities differ")


@pytest.mark.parametrize("engine_name", ["sqlite", "postgresql"], indirect=True)
def test_the_database_gives_a_bayes_state_back_bit_for_bit(database: Database) -> None:
    """JSON on SQLite, JSONB (numeric) on PostgreSQL: both store the shortest decimal that
    round-trips, so the filter's floats come back as the same bits."""
    with database.writing() as db:
        loaded = parse_protocol(protocol_text(**THREE))
        study = studies.create_study(db, name="three", loaded=loaded, actor=Actor.system())
        protocol = studies.protocol_of(study)
    learner = learners.build(learners.learner_spec(protocol, "C3", protocol.categories[2], None))
    for action, reward in [(1, 1.0), (0, 0.0), (1, 0.0), (3, 1.0), (1, 1.0), (2, 0.0)]:
        learner.update(action, reward)
    state = learner.state_dict()
    with database.writing() as db:
        enroll_participant(db, study_name="three", actor=Actor.system(), code="P1")
    with database.writing() as db:
        db.execute(update(LearnerState).values(state=state))
        db.commit()
    with database.read_session() as db:
        stored = db.scalars(select(LearnerState.state)).first()
    assert _bits(stored) == _bits(state)


@SQLITE
def test_a_blinded_study_of_three_gives_three_neutral_labels(
    database: Database, user_client: UserClientFactory
) -> None:
    with database.writing() as db:
        loaded = parse_protocol(protocol_text(**THREE, **{"blinded = false": "blinded = true"}))
        study = studies.create_study(db, name="blind3", loaded=loaded, actor=Actor.system())
        assert sorted((study.neutral_labels or {}).values()) == ["Group A", "Group B", "Group C"]
        protocol = studies.protocol_of(study)
    experimenter = user_client(Role.EXPERIMENTER)
    seen = {
        experimenter.post("/api/v1/studies/blind3/participants", json={}).json()["condition"]
        for _ in range(6)
    }
    assert seen == {"Group A", "Group B", "Group C"}  # one block of 6, or two of 3
    shown = experimenter.get("/api/v1/studies/blind3/protocol").json()
    assert [c["id"] for c in shown["conditions"]] == ["Group A", "Group B", "Group C"]
    assert shown["learners"] == {}
    # Nor would the robot's first words tell: the filter starts at the prior, as Exp3 does.
    category = protocol.categories[0]
    start = {
        condition: learners.probabilities_list(
            learners.build(learners.learner_spec(protocol, condition, category, None))
        )
        for condition in ("C1", "C3")
    }
    assert start["C1"] == start["C3"] == [0.25] * 4


def _problems(text: str) -> list[str]:
    with pytest.raises(ProtocolError) as raised:
        parse_protocol(text, source="lab.toml")
    return str(raised.value).splitlines()


BAYES = 'conditions[2].learner = "bayes"'


@pytest.mark.parametrize(
    ("replacements", "expected"),
    [
        (
            {SHIPPED_FEEDBACK: 'kind = "binary"\n'},
            f"lab.toml: learners.feedback: {BAYES}: with yes/no answers that never slip and a "
            "preference that never changes, the exact filter is certain after one yes and would "
            "have to ignore any answer that contradicts it: declare a slip rate (slip or "
            "slip_values) or a hazard",
        ),
        (
            {"yes = 1.0\nno = 0.0": "yes = 1.0\nno = 1.0"},
            f"lab.toml: reward: {BAYES}: the exact filter tells a yes from a no by its reward, "
            "but yes and no both give 1",
        ),
        (
            {SHIPPED_FEEDBACK: 'kind = "gaussian"\nvariance = 1e-310\n'},
            f"lab.toml: learners.feedback.variance: {BAYES}: σ² 1e-310 is too small for rewards "
            "1 and 0: every answer's log-likelihood overflows, so one answer would rule out "
            "every other question for good",
        ),
    ],
    ids=["yes/no without slips or hazard", "yes and no alike", "σ² underflows"],
)
def test_a_bayes_condition_the_filter_cannot_run_is_refused(
    replacements: dict[str, str], expected: str
) -> None:
    assert _problems(protocol_text(**THREE, **replacements)) == [expected]


def test_the_paper_model_and_a_hazard_alone_are_accepted() -> None:
    paper = parse_protocol(protocol_text(**THREE, **{SHIPPED_FEEDBACK: ""})).protocol
    spec = learners.learner_spec(paper, "C3", paper.categories[0], None)
    assert isinstance(learners.build(spec), BayesLearner)
    hazard = protocol_text(**THREE, **{SHIPPED_FEEDBACK: 'kind = "binary"\nhazard = 0.02\n'})
    protocol = parse_protocol(hazard).protocol
    spec = learners.learner_spec(protocol, "C3", protocol.categories[0], None)
    assert isinstance(learners.build(spec), BeliefLearner)


@SQLITE
def test_refused_on_the_api_and_in_one_line_on_the_command_line(
    database_url: str, user_client: UserClientFactory, tmp_path: Path
) -> None:
    bad = protocol_text(**THREE, **{SHIPPED_FEEDBACK: 'kind = "binary"\n'})
    admin = user_client(Role.ADMIN)
    response = admin.post("/api/v1/studies", json={"name": "x", "protocol_toml": bad})
    assert response.status_code == 422
    assert response.json()["detail"].startswith(
        f"protocol_toml: learners.feedback: {BAYES}: with yes/no"
    )
    path = tmp_path / "lab.toml"
    path.write_text(bad)
    code, _, err = run(database_url, "study", "create", "--protocol", str(path), "--name", "x")
    assert code == 2
    assert err.startswith(f"error: {path}: learners.feedback: {BAYES}: with yes/no")
    assert len(err.strip().splitlines()) == 1
    assert admin.get("/api/v1/studies/x").status_code == 404  # nothing half-written


def test_with_a_population_the_filter_starts_at_its_training_prior(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """C2 is meta-trained on the population's training prior; the exact filter for the same
    participants starts there too, and records it (replay needs no file)."""
    protocol = parse_protocol(protocol_text(**THREE)).protocol
    category = protocol.categories[0]
    content = {
        "source": {"steps": "pilot.csv"},
        "categories": {
            category.name: {"arms": 4, "prior": [0.7, 0.1, 0.1, 0.1], "participants": 6}
        },
    }
    population = Population.of(content)
    monkeypatch.setattr(populations, "population_of", lambda _protocol: population)
    spec = learners.learner_spec(protocol, "C3", category, None)
    prior = population.training_prior(category.name, 4, list(category.questions))
    assert spec.config["prior"] == list(prior)
    assert spec.config["population_sha256"] == population.sha256
    assert learners.build(spec).probabilities() == pytest.approx(prior, rel=1e-12)
