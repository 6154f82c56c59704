"""Enrolment and concealed randomisation against a real database (SQLite and PostgreSQL)."""

from __future__ import annotations

import contextlib
import re
import threading
from collections import Counter, defaultdict

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from sqlalchemy import func, select

from analysis.exports import EXPORT_FORMATS
from app.access import POLICY, Principal
from app.db import Database
from app.errors import Conflict, InvalidInput, NotFound
from app.protocol import parse_protocol
from app.randomisation import entry_at
from app.services import audit, studies
from app.services.audit import Actor
from app.services.participants import enrolment
from app.tables import Allocation, AuditEvent, Participant, Role, StudyStatus
from tests.conftest import Lab, UserClientFactory, protocol_text, sqlite_only

ACTOR = Actor.command_line()


def _create(database: Database, name: str, **replacements: str) -> str:
    loaded = parse_protocol(protocol_text(**replacements))
    with database.writing() as db:
        studies.create_study(db, name=name, loaded=loaded, actor=ACTOR)
    return name


def _enrol(database: Database, study: str, **kwargs: object) -> enrolment.Enrolment:
    with database.writing() as db:
        return enrolment.enroll_participant(db, study_name=study, actor=ACTOR, **kwargs)  # type: ignore[arg-type]


def test_enrolment_reveals_the_sequence_in_order(database: Database, study_name: str) -> None:
    results = [_enrol(database, study_name) for _ in range(10)]
    assert [r.participant.code for r in results] == [f"P{n:03d}" for n in range(1, 11)]
    with database.read_session() as db:
        study = studies.get_study(db, study_name)
        seed = bytes.fromhex(study.allocation_seed)
    expected = [entry_at(seed, "", ["C1", "C2"], [2, 4], i).condition for i in range(10)]
    assert [r.condition for r in results] == expected
    assert [r.allocation.sequence_index for r in results] == list(range(10))


def test_every_reveal_is_audited(database: Database, study_name: str) -> None:
    result = _enrol(database, study_name, code="A1")
    with database.read_session() as db:
        reveal = db.scalars(
            select(AuditEvent).where(AuditEvent.action == "allocation.revealed")
        ).one()
    assert reveal.subject == "A1"
    assert reveal.details["condition"] == result.condition
    assert reveal.actor_kind == "cli"


PLACE_IN_SEQUENCE = re.compile(
    r"block[ _]number|block[ _]size(?!s)|sequence[ _]index|allocation[ _]index"
    r"|position[ _]in[ _]block|allocation[ _]seed(?!_sha256)",
    re.IGNORECASE,
)
"""How a page, export or log would name an allocation's place in its sequence (issue 35, item 11:
the audit log's block numbers and sizes made 41 of the next 100 allocations certain)."""


def _admin_reads(study: str, station: str, username: str) -> list[str]:
    """Every page, read and export the access policy lets an admin fetch (a new route is swept
    without changing this test); event streams carry change types only, tablet links need a
    participant's token."""
    paths = []
    for (method, path), allowed in sorted(POLICY.items()):
        if method != "GET" or Principal.ADMIN not in allowed:
            continue
        if (
            path.endswith("/events")
            or "{token}" in path
            # an online study's public link (/join/) is a participant's page
            or path.startswith(("/static", "/api/v1/docs", "/api/v1/openapi", "/join/"))
        ):
            continue
        if "{export}" in path:
            paths += [path.format(name=study, export=export) for export in EXPORT_FORMATS]
            continue
        name = station if path.startswith(("/stations", "/api/v1/stations")) else study
        paths.append(
            path.format(
                name=name,
                code="P001",
                username=username,
                language="sv",
                device_id=1,
                number=1,
                slug="study",
            )
        )
    return paths


@pytest.mark.parametrize("engine_name", ["sqlite"])  # what is shown does not depend on the engine
def test_no_page_export_or_log_places_an_allocation_before_the_study_closes(
    lab: Lab, user_client: UserClientFactory, database: Database
) -> None:
    admin = user_client(Role.ADMIN, "auditor")
    lab.enrol_and_assign("P001")  # seated, with answers: every page and export has data
    for _ in range(5):
        enrolled = lab.experimenter.post(f"/api/v1/studies/{lab.study}/participants", json={})
        assert enrolled.status_code == 201 and not PLACE_IN_SEQUENCE.search(enrolled.text)
    with database.writing() as db:  # an entry as written before the fix: shown once closed
        audit.record(
            db,
            actor=Actor.system("tests"),
            action="allocation.revealed",
            study_id=studies.get_study(db, lab.study).id,
            subject="P001",
            details={"condition": "C1", "sequence_index": 0, "block_number": 0, "block_size": 4},
        )
        db.commit()
    leaks = {}
    for path in _admin_reads(lab.study, lab.station, "auditor"):
        response = admin.get(path)
        assert response.status_code < 500, f"{path}: {response.status_code}"
        if PLACE_IN_SEQUENCE.search(response.text):
            leaks[path] = sorted(set(PLACE_IN_SEQUENCE.findall(response.text)))
    assert leaks == {}
    assert admin.get("/admin/audit.csv").text.count("allocation.revealed") == 7

    closed = admin.post(f"/api/v1/studies/{lab.study}/status", json={"status": "closed"})
    assert closed.status_code == 200
    assert "block number" in admin.get("/admin/audit").text
    assert admin.get("/admin/audit.csv").text.count("block_number") == 1  # the old entry only


@pytest.mark.parametrize("code", ["", " ", "x" * 33, "a b", "-lead", "P1;drop"])
@sqlite_only("a malformed code is refused before any query")
def test_malformed_codes_are_refused(database: Database, study_name: str, code: str) -> None:
    with pytest.raises(InvalidInput, match="participant code"):
        _enrol(database, study_name, code=code)


def test_duplicate_code_unknown_study_and_closed_study(database: Database, study_name: str) -> None:
    _enrol(database, study_name, code="P7")
    with pytest.raises(Conflict, match="already used"):
        _enrol(database, study_name, code="P7")
    with pytest.raises(NotFound, match="no study named 'nope'; known studies: default"):
        _enrol(database, "nope")
    with database.writing() as db:
        studies.set_study_status(db, name=study_name, status=StudyStatus.CLOSED, actor=ACTOR)
    with pytest.raises(Conflict, match="closed to enrolment"):
        _enrol(database, study_name)
    with database.read_session() as db:
        assert db.scalar(select(func.count()).select_from(Participant)) == 1
        assert db.scalar(select(func.count()).select_from(Allocation)) == 1


STRATIFIED = {
    "stratify_by = []": 'stratify_by = ["gender"]\nstrata_values = { gender = ["female", "male"] }'
}


def test_strata_must_match_the_protocol(database: Database) -> None:
    study = _create(database, "strat", **STRATIFIED)
    with pytest.raises(InvalidInput, match="stratifies by gender: give --stratum gender=VALUE"):
        _enrol(database, study)
    with pytest.raises(InvalidInput, match="does not stratify by site"):
        _enrol(database, study, strata={"gender": "female", "site": "b"})
    with pytest.raises(InvalidInput, match="not one of: female, male"):
        _enrol(database, study, strata={"gender": "other"})
    result = _enrol(database, study, strata={"gender": "male"})
    assert result.participant.stratum == "gender=male"
    with database.read_session() as db:
        assert db.scalar(select(func.count()).select_from(Participant)) == 1


def test_withdrawn_keep_their_allocation_and_do_not_free_it(
    database: Database, study_name: str
) -> None:
    first = _enrol(database, study_name)
    with database.writing() as db:
        enrolment.withdraw_participant(
            db, study_name=study_name, code=first.participant.code, actor=ACTOR, reason="ill"
        )
    with pytest.raises(Conflict, match="already withdrawn"), database.writing() as db:
        enrolment.withdraw_participant(
            db, study_name=study_name, code=first.participant.code, actor=ACTOR
        )
    second = _enrol(database, study_name)
    assert second.allocation.sequence_index == 1
    with database.read_session() as db:
        kept = db.scalar(
            select(Allocation).where(Allocation.participant_id == first.participant.id)
        )
        assert kept is not None and kept.condition == first.condition


def test_replacement_takes_the_dropouts_condition_once(database: Database) -> None:
    study = _create(database, "replace", **{"replace_dropouts = false": "replace_dropouts = true"})
    first = _enrol(database, study)
    second = _enrol(database, study)
    with database.writing() as db:
        enrolment.withdraw_participant(
            db, study_name=study, code=first.participant.code, actor=ACTOR
        )
    replacement = _enrol(database, study)
    assert replacement.condition == first.condition
    assert replacement.allocation.sequence_index is None
    assert replacement.allocation.replaces_participant_id == first.participant.id
    following = _enrol(database, study)
    assert following.allocation.sequence_index == 2  # the replacement used no sequence entry
    assert second.allocation.sequence_index == 1


STRATA_VALUES = st.sampled_from(["female", "male"])
EVENTS = st.lists(
    st.one_of(
        st.tuples(st.just("enrol"), STRATA_VALUES),
        st.tuples(st.just("withdraw"), st.integers(0, 40)),
    ),
    min_size=1,
    max_size=30,
)


@settings(
    max_examples=12,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(events=EVENTS)
def test_any_enrolment_sequence_stays_balanced_per_stratum(
    database: Database, events: list[tuple[str, object]]
) -> None:
    """Property: per stratum, C1 and C2 never differ by more than half the largest block (2)."""
    with database.read_session() as db:
        name = f"prop-{db.scalar(select(func.count()).select_from(AuditEvent))}"
    _create(database, name, **STRATIFIED)
    enrolled: list[str] = []
    counts: dict[str, Counter[str]] = defaultdict(Counter)
    for kind, value in events:
        if kind == "enrol":
            result = _enrol(database, name, strata={"gender": str(value)})
            enrolled.append(result.participant.code)
            stratum_counts = counts[result.participant.stratum]
            stratum_counts[result.condition] += 1
            assert abs(stratum_counts["C1"] - stratum_counts["C2"]) <= 2
        elif enrolled:
            code = enrolled[int(str(value)) % len(enrolled)]
            with database.writing() as db, contextlib.suppress(Conflict):
                enrolment.withdraw_participant(db, study_name=name, code=code, actor=ACTOR)
    # Reproducible from the seed: every stored allocation is the seed's sequence entry.
    with database.read_session() as db:
        study = studies.get_study(db, name)
        seed = bytes.fromhex(study.allocation_seed)
        for allocation in db.scalars(select(Allocation).where(Allocation.study_id == study.id)):
            assert allocation.sequence_index is not None
            expected = entry_at(
                seed, allocation.stratum, ["C1", "C2"], [2, 4], allocation.sequence_index
            )
            assert (allocation.condition, allocation.block_size) == (
                expected.condition,
                expected.block_size,
            )


def test_twenty_simultaneous_enrolments_get_distinct_allocations(
    database: Database, study_name: str
) -> None:
    barrier = threading.Barrier(20)
    results: list[enrolment.Enrolment] = []
    errors: list[BaseException] = []

    def enrol_one() -> None:
        try:
            barrier.wait(timeout=10)
            results.append(_enrol(database, study_name))
        except BaseException as exc:  # pragma: no cover - reported below
            errors.append(exc)

    threads = [threading.Thread(target=enrol_one) for _ in range(20)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=60)
    assert errors == []
    assert sorted(r.allocation.sequence_index for r in results) == list(range(20))  # type: ignore[type-var]
    assert len({r.participant.code for r in results}) == 20
    conditions = Counter(r.condition for r in results)
    assert abs(conditions["C1"] - conditions["C2"]) <= 2
