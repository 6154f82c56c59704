"""A protocol naming a population for its C2 learners (issue 20): every pairing that can be wrong
is refused at study creation, and C2 learners record the population and start at its prior."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from analysis.methods import design_paragraph
from analysis.population import Population, write_population
from app.db import Database
from app.errors import Conflict, InvalidInput
from app.protocol import default_protocol, parse_protocol
from app.services import studies
from app.services.analysis_views.study_data import load_dataset
from app.services.audit import Actor
from app.services.participants.enrolment import enroll_participant
from app.services.privacy.sites import Scope
from app.services.sessions.learners import feedback_model, restore
from app.services.sessions.population_fit import fit_population
from app.tables import AuditEvent, LearnerState, Role, StudyStatus
from models.checkpoints import checkpoint_name, observation_for, write_checkpoint
from models.learners.mlp_policy import init_params
from tests.analysis.test_population_file import _steps
from tests.conftest import BLINDED, UserClientFactory, protocol_text

DEFAULT = default_protocol().protocol
CATEGORIES = tuple((c.name, len(c.questions)) for c in DEFAULT.categories)
QUESTIONS = {c.name: list(c.questions) for c in DEFAULT.categories}


def _population(path: Path, *, seed: int = 0, questions: dict[str, list[str]] | None = None):
    source = {
        "studies": ["pilot"],
        "status_when_fitted": {"pilot": "closed"},
        "questions": QUESTIONS if questions is None else questions,
    }
    population = fit_population(_steps(24, seed, CATEGORIES), source, replicates=20, seed=seed)
    write_population(path, population)
    return population


def _checkpoints(
    directory: Path, population: Population, questions: dict[str, list[str]] | None = None
) -> Path:
    """Checkpoints as `trustlab pretrain --population` writes them (weights drawn at random:
    what is checked here is what they record, not how well they adapt)."""
    trained_for = feedback_model(DEFAULT).to_json()
    for name, k in CATEGORIES:
        obs = observation_for(name)
        write_checkpoint(
            directory / checkpoint_name(name, k),
            n_arms=k,
            category=name,
            mode="online",
            rule="natural_expected",
            observation=obs,
            params=init_params(np.random.default_rng(1), obs.shape[0], 100, k),
            step_sizes=np.array([1.0, 0.8]),
            baselines=np.array([0.3, 0.3]),
            damping=0.1,
            config={
                "feedback": trained_for,
                "population": population.record(name)
                | {"questions": None if questions is None else questions[name]},
            },
            metrics={"note": "test fixture"},
            prior=np.asarray(population.training_prior(name, k)),
        )
    return directory


def _protocol(population: Path, checkpoints: Path, extra: str = "") -> str:
    table = (
        f'[learners.population]\nfile = "{population}"\ncheckpoints = "{checkpoints}"\n{extra}\n'
    )
    text = protocol_text()
    first = text.index("[[categories]]")
    return text[:first] + table + text[first:]


def _create(database: Database, name: str, text: str) -> None:
    with database.writing() as db:
        studies.create_study(db, name=name, loaded=parse_protocol(text), actor=Actor.system())


@pytest.fixture
def world(tmp_path: Path) -> tuple[Path, Path, Population]:
    file = tmp_path / "pilot.population.json"
    population = _population(file)
    return file, _checkpoints(tmp_path / "set", population), population


def test_c2_learners_record_the_population_and_start_at_its_prior(
    database: Database, world: tuple[Path, Path, Population]
) -> None:
    file, checkpoints, population = world
    _create(database, "main", _protocol(file, checkpoints))
    with database.writing() as db:
        entry = db.query(AuditEvent).filter_by(action="study.created", subject="main").one()
        assert entry.details["population_sha256"] == population.sha256
        assert entry.details["population_source"] == "pilot"
        for _ in range(4):  # both conditions, by the balanced allocation
            enroll_participant(db, study_name="main", actor=Actor.system())
        rows = db.query(LearnerState).filter_by(kind="meta").all()
        assert rows, "no C2 participant was enrolled"
        for row in rows:
            assert row.config["population_sha256"] == population.sha256
            assert Path(row.config["checkpoint"]).parent == checkpoints
            category = Path(row.config["checkpoint"]).name.split("-k")[0]
            start = restore(row).probabilities()
            expected = population.training_prior(category, row.n_arms)
            np.testing.assert_allclose(start, expected, rtol=1e-12)


def test_an_edited_population_file_is_refused(
    database: Database, world: tuple[Path, Path, Population]
) -> None:
    file, checkpoints, _ = world
    data = json.loads(file.read_text())
    data["content"]["categories"]["conation"]["prior"][0] = 0.99
    file.write_text(json.dumps(data))
    with pytest.raises(InvalidInput, match="does not match its recorded hash"):
        _create(database, "main", _protocol(file, checkpoints))
    with database.writing() as db:
        assert studies.count_studies(db) == 0


def test_questions_that_differ_from_the_source_are_refused(
    database: Database, world: tuple[Path, Path, Population], tmp_path: Path
) -> None:
    _, checkpoints, _ = world
    other = {name: list(texts) for name, texts in QUESTIONS.items()}
    other["affection"][1] = "Do you want to see a different room?"
    moved = tmp_path / "moved.population.json"
    _population(moved, questions=other)
    with pytest.raises(InvalidInput, match="'affection' asks other questions"):
        _create(database, "main", _protocol(moved, checkpoints))


def test_a_checkpoint_trained_for_another_population_is_refused(
    database: Database, world: tuple[Path, Path, Population], tmp_path: Path
) -> None:
    _, checkpoints, _ = world
    refit = tmp_path / "refit.population.json"
    _population(refit, seed=5)
    with pytest.raises(Conflict, match=r"was trained for population .* retrain it"):
        _create(database, "main", _protocol(refit, checkpoints))
    with pytest.raises(InvalidInput, match=r"learners.population.checkpoints: .*does not exist"):
        _create(database, "main", _protocol(refit, tmp_path / "nowhere"))


def test_a_source_study_still_enrolling_needs_a_recorded_reason(
    database: Database, world: tuple[Path, Path, Population]
) -> None:
    file, checkpoints, population = world
    _create(database, "pilot", protocol_text())  # the source, still open
    with pytest.raises(Conflict, match="fitted from pilot, which is still enrolling"):
        _create(database, "main", _protocol(file, checkpoints))
    reason = 'enrolling_reason = "pilot left open by mistake; no one enrolled since"'
    _create(database, "main", _protocol(file, checkpoints, reason))
    with database.writing() as db:
        entry = db.query(AuditEvent).filter_by(action="study.created", subject="main").one()
        assert entry.details["enrolling_sources"] == ["pilot"]
        assert entry.details["enrolling_reason"].startswith("pilot left open")
        studies.set_study_status(db, name="pilot", status=StudyStatus.CLOSED, actor=Actor.system())
    _create(database, "second", _protocol(file, checkpoints))  # closed: no reason needed
    with database.writing() as db:
        entry = db.query(AuditEvent).filter_by(action="study.created", subject="second").one()
        assert entry.details["population_sha256"] == population.sha256
        assert entry.details["enrolling_reason"] is None


def test_a_population_with_a_checkpoint_setting_is_refused_by_the_protocol(
    world: tuple[Path, Path, Population],
) -> None:
    file, checkpoints, _ = world
    text = _protocol(file, checkpoints).replace('checkpoint = "shipped"', 'checkpoint = "models/x"')
    with pytest.raises(ValueError, match=r"learners\.population"):
        parse_protocol(text)


def test_the_dashboard_shows_where_the_meta_policy_starts(
    database: Database,
    world: tuple[Path, Path, Population],
    user_client: UserClientFactory,
) -> None:
    file, checkpoints, population = world
    _create(database, "main", _protocol(file, checkpoints))
    _create(database, "plain", protocol_text())
    _create(database, "sealed", protocol_text(**BLINDED))
    staff = user_client(Role.EXPERIMENTER)
    page = staff.get("/studies/main/dashboard").text
    assert "Adaptation engine: where the meta-policy starts" in page
    assert "Meta-trained on the prior of <strong>pilot</strong>" in page
    assert population.sha256[:12] in page and "N = 24" in page
    fitted = population.categories["affection"]
    start = population.training_prior("affection", 4)
    assert QUESTIONS["affection"][2] in page  # the question texts, not indices
    assert f"{start[2]:.3f}</td>" in page and f"{fitted['prior'][2]:.2f} [" in page
    plain = staff.get("/studies/plain/dashboard").text
    assert "Meta-trained on the uniform prior" in plain and "0.250</td>" in plain
    assert "Adaptation engine" not in staff.get("/studies/sealed/dashboard").text


def test_the_report_says_where_the_prior_came_from(
    database: Database, world: tuple[Path, Path, Population]
) -> None:
    file, checkpoints, population = world
    _create(database, "main", _protocol(file, checkpoints))
    with database.writing() as db:
        for _ in range(4):
            enroll_participant(db, study_name="main", actor=Actor.system())
    with database.read_session() as db:
        dataset = load_dataset(db, scope=Scope.every_site(), study=studies.get_study(db, "main"))
    used = dataset.protocol["population"]
    assert used["sha256"] == population.sha256 and used["source"] == "pilot"
    assert set(used["categories"]) == set(QUESTIONS)
    assert dataset.manifest["population_sha256"] == population.sha256
    methods = design_paragraph(dataset.protocol, dataset.instruments)
    assert "meta-trained on the population fitted from 24 earlier participants of pilot" in methods
    conation = population.categories["conation"]
    assert f"conation: {conation['prior'][0]:.2f}".replace(": 0.", ": .") in methods
    _create(database, "plain", protocol_text())
    with database.writing() as db:
        enroll_participant(db, study_name="plain", actor=Actor.system())
    with database.read_session() as db:
        plain = load_dataset(db, scope=Scope.every_site(), study=studies.get_study(db, "plain"))
    assert "population" not in plain.protocol and plain.manifest["population_sha256"] is None


def test_a_csv_populations_questions_are_compared_through_its_checkpoints(
    database: Database, tmp_path: Path
) -> None:
    """A steps CSV carries no question texts: the checkpoints record the ones they were trained
    for (``pretrain`` reads them from the protocol), and study creation compares those."""
    file = tmp_path / "csv.population.json"
    population = fit_population(_steps(24, 0, CATEGORIES), {"steps": "pilot.csv"}, replicates=2)
    write_population(file, population)
    unknown = _checkpoints(tmp_path / "unknown", population)
    with pytest.raises(InvalidInput, match="records the questions of 'conation'"):
        _create(database, "main", _protocol(file, unknown))
    other = {name: list(texts) for name, texts in QUESTIONS.items()}
    other["cognition"][0] = "Is this the way out?"
    moved = _checkpoints(tmp_path / "moved", population, questions=other)
    with pytest.raises(InvalidInput, match="trained for other questions of 'cognition'"):
        _create(database, "main", _protocol(file, moved))
    same = _checkpoints(tmp_path / "same", population, questions=QUESTIONS)
    _create(database, "main", _protocol(file, same))


def test_a_blinded_studys_staff_report_leaves_the_prior_out(
    database: Database, world: tuple[Path, Path, Population]
) -> None:
    file, checkpoints, population = world
    text = _protocol(file, checkpoints).replace("blinded = false", "blinded = true")
    _create(database, "main", text)
    with database.writing() as db:
        for _ in range(4):  # a whole allocation block at least (sizes 2 and 4): C2 is in it
            enroll_participant(db, study_name="main", actor=Actor.system())
    with database.read_session() as db:
        study = studies.get_study(db, "main")
        staff = load_dataset(db, scope=Scope.every_site(), study=study, for_staff=True)
        command_line = load_dataset(db, scope=Scope.every_site(), study=study)
    assert "population" not in staff.protocol and staff.manifest["population_sha256"] is None
    assert command_line.protocol["population"]["sha256"] == population.sha256
