"""Studies: creation from a validated protocol, lookup, opening and closing, hiding from lists."""

from __future__ import annotations

import secrets
from typing import Any

from sqlalchemy import func, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from app.errors import Conflict, InvalidInput, NotFound
from app.inputs import STUDY_NAME
from app.protocol import (
    LoadedProtocol,
    Protocol,
    parse_protocol,
    protocol_from_dict,
    shipped_protocol,
)
from app.services import audit
from app.services.audit import Actor
from app.services.sessions import populations
from app.tables import (
    Allocation,
    Participant,
    ParticipantStatus,
    ProtocolVersion,
    Study,
    StudyPhase,
    StudyStatus,
    utcnow,
)

DEFAULT_STUDY_NAME = "default"
TITLE_MAX_LENGTH = 200


def study_title(given: str | None, loaded: LoadedProtocol) -> str:
    """The title a new study gets: the one given (trimmed), else the protocol's.

    Two studies of one protocol (a pilot and the main study, the demo) would otherwise show the
    same title everywhere; the lab names each when it creates it."""
    title = " ".join((given or "").split())
    if not title:
        return loaded.protocol.study.title
    if len(title) > TITLE_MAX_LENGTH:
        raise InvalidInput(f"a study title has at most {TITLE_MAX_LENGTH} characters")
    return title


def draw_neutral_labels(protocol: Protocol) -> dict[str, str] | None:
    """A blinded study's condition id → neutral label, the protocol's labels shuffled with the
    system's secure randomness (None when the protocol is not blinded)."""
    if not protocol.study.blinded:
        return None
    labels = protocol.neutral_labels()
    shuffled = secrets.SystemRandom().sample(labels, len(labels))
    return {
        condition.id: label for condition, label in zip(protocol.conditions, shuffled, strict=True)
    }


def create_study(
    db: Session,
    *,
    name: str,
    loaded: LoadedProtocol,
    actor: Actor,
    title: str | None = None,
    started_from: str | None = None,
    phase: StudyPhase = StudyPhase.LIVE,
) -> Study:
    """Create an open study with a fresh secret allocation seed (and, if blinded, a fresh secret
    assignment of neutral labels: :func:`draw_neutral_labels`); commits. ``title``: see
    :func:`study_title`; ``started_from``: where the protocol came from, for the audit log
    (``shipped F``, ``study S``, ``file F``); ``phase``: live (ready for its participants, as
    a study from a finished protocol file is), or a draft to edit, preview and pilot first
    (app.services.design.study_phases)."""
    STUDY_NAME.check(name)
    shown_title = study_title(title, loaded)
    if db.scalar(select(Study.id).where(Study.name == name)) is not None:
        raise Conflict(f"a study named {name!r} already exists")
    population = check_population_use(db, loaded.protocol)
    study = Study(
        name=name,
        title=shown_title,
        protocol=loaded.protocol.model_dump(mode="json"),
        protocol_source=loaded.source_text,
        protocol_sha256=loaded.sha256,
        allocation_seed=secrets.token_hex(32),
        neutral_labels=draw_neutral_labels(loaded.protocol),
        created_by=actor.name,
        phase=phase,
        live_at=utcnow() if phase == StudyPhase.LIVE else None,
    )
    db.add(study)
    try:
        db.flush()  # PostgreSQL: a concurrent creation of the same name is refused here
    except IntegrityError:
        db.rollback()
        raise Conflict(f"a study named {name!r} already exists") from None
    db.add(
        ProtocolVersion(
            study_id=study.id,
            number=1,
            sha256=loaded.sha256,
            source=loaded.source_text,
            saved_by=actor.name,
            phase=phase,
        )
    )
    audit.record(
        db,
        actor=actor,
        action="study.created",
        study_id=study.id,
        subject=name,
        details={"protocol_sha256": loaded.sha256, "phase": str(phase)}
        | ({"started_from": started_from} if started_from else {})
        | (population or {}),
    )
    db.commit()
    return study


def starting_protocol(
    db: Session, *, shipped: str | None = None, copy_of: str | None = None
) -> tuple[LoadedProtocol, str]:
    """A shipped protocol (by file name) or a copy of study ``copy_of``'s, exactly one, and
    what :func:`create_study`'s ``started_from`` calls it."""
    if (shipped is None) == (copy_of is None):
        raise InvalidInput("start from a shipped protocol or from a copy of a study's, one")
    if shipped is not None:
        return shipped_protocol(shipped), f"shipped {shipped}"
    assert copy_of is not None
    return protocol_copy(db, copy_of), f"study {copy_of}"


def protocol_copy(db: Session, name: str) -> LoadedProtocol:
    """The protocol study ``name`` was created with, as its file (comments and all), to start
    another study from: a pilot's main study, the next wave of a study."""
    study = get_study(db, name)
    return parse_protocol(study.protocol_source, source=f"the protocol of study {name}")


def check_population_use(db: Session, protocol: Protocol) -> dict[str, Any] | None:
    """Check the protocol's population before a study is created from it; what the audit log
    records of it (None when the protocol names no population). Here, above both, because it
    joins the population (app.services.sessions.populations) with the learners' checkpoints
    (app.services.sessions.learners), which are built from the population.

    Raises
    ------
    InvalidInput
        For an unusable file, a category the population lacks or whose questions differ, or a
        missing or broken checkpoint.
    Conflict
        For a checkpoint trained for another population, or a source study still enrolling
        without ``enrolling_reason``.
    """
    population = populations.population_of(protocol)
    if population is None:
        return None
    for category in protocol.categories:  # the questions first: a wrong file, not checkpoints
        try:
            population.prior(category.name, len(category.questions), list(category.questions))
        except ValueError as exc:
            raise InvalidInput(f"{populations.KEY}.file: {exc}") from None
    from app.services.sessions import learners  # the engine (numpy) only for such a protocol

    for category in protocol.categories:
        path = populations.checkpoint_path(protocol, category)
        try:
            checkpoint = learners.checkpoint_at(path, len(category.questions))
        except ValueError as exc:
            raise InvalidInput(f"{populations.KEY}.checkpoints: {exc}") from None
        populations.check_trained_for(checkpoint, population, category)
        # The feedback model the checkpoint was trained for: now rather than at enrolment.
        learners.accepted_mismatch(protocol, checkpoint)
    return populations.check_sources(db, protocol, population)


_protocol_cache: dict[tuple[int, str], Protocol] = {}


def protocol_of(study: Study) -> Protocol:
    """The study's validated protocol (parsed once per process and protocol version)."""
    key = (study.id, study.protocol_sha256)
    protocol = _protocol_cache.get(key)
    if protocol is None:
        protocol = protocol_from_dict(study.protocol, source=f"study {study.name!r}")
        if len(_protocol_cache) > 256:
            _protocol_cache.clear()
        _protocol_cache[key] = protocol
    return protocol


def protocol_by_id(db: Session, *, study_id: int, protocol_sha256: str) -> Protocol:
    """The protocol of a study known by id and protocol hash (a robot's seat, app.services.
    step_store): from the process's cache, loading the study only on a miss."""
    protocol = _protocol_cache.get((study_id, protocol_sha256))
    if protocol is not None:
        return protocol
    study = db.get(Study, study_id)
    if study is None:  # pragma: no cover - the seat was read in this transaction
        raise NotFound(f"study {study_id} does not exist")
    return protocol_of(study)


def get_study(db: Session, name: str, *, for_update: bool = False) -> Study:
    """The study with this name, optionally row-locked; NotFound names the known studies."""
    query = select(Study).where(Study.name == name)
    if for_update:
        query = query.with_for_update()
    study = db.scalar(query)
    if study is None:
        known = db.scalars(select(Study.name).order_by(Study.name).limit(10)).all()
        hint = f"; known studies: {', '.join(known)}" if known else "; no study exists yet"
        raise NotFound(f"no study named {name!r}{hint}")
    return study


def list_studies(db: Session, *, archived: bool | None = None) -> list[Study]:
    """Studies newest first: every one (``archived=None``), or only the shown or archived ones."""
    query = select(Study).order_by(Study.created_at.desc(), Study.id.desc())
    if archived is not None:
        query = query.where(
            Study.archived_at.is_not(None) if archived else Study.archived_at.is_(None)
        )
    return list(db.scalars(query))


def count_archived(db: Session) -> int:
    """How many studies are hidden from the everyday lists."""
    query = select(func.count()).select_from(Study).where(Study.archived_at.is_not(None))
    return db.scalar(query) or 0


def set_archived(db: Session, *, name: str, archived: bool, actor: Actor) -> Study:
    """Hide a study from the study list and the consoles, or show it again; commits.

    Nothing is deleted or closed: its pages, exports and API stay as they were, and a participant
    already seated somewhere carries on."""
    study = get_study(db, name, for_update=True)
    if (study.archived_at is not None) == archived:
        return study
    study.archived_at = utcnow() if archived else None
    audit.record(
        db,
        actor=actor,
        action="study.archived" if archived else "study.unarchived",
        study_id=study.id,
        subject=study.name,
    )
    db.commit()
    return study


def count_studies(db: Session) -> int:
    """How many studies exist (first start creates the default one when there are none)."""
    return db.scalar(select(func.count()).select_from(Study)) or 0


def enrolment_counts(
    db: Session, study: Study, *, actor: Actor, pilot: bool = False
) -> dict[str, dict[str, int]]:
    """Participants per condition and status: ``{condition: {status: n}}``, of the sites
    ``actor`` may see (app.services.privacy.sites); the live participants, or the pilot's."""
    query = (
        select(Allocation.condition, Participant.status, func.count())
        .join(Participant, Participant.id == Allocation.participant_id)
        .where(Allocation.study_id == study.id, Participant.pilot.is_(pilot))
    )
    if actor.sites is not None:
        query = query.where(Participant.site.in_(sorted(actor.sites)))
    rows = db.execute(query.group_by(Allocation.condition, Participant.status)).all()
    counts: dict[str, dict[str, int]] = {
        c.id: dict.fromkeys(ParticipantStatus, 0) for c in protocol_of(study).conditions
    }
    for condition, status, n in rows:
        counts.setdefault(condition, dict.fromkeys(ParticipantStatus, 0))[status] = n
    return counts


def set_study_status(db: Session, *, name: str, status: StudyStatus, actor: Actor) -> Study:
    """Open or close a study for enrolment; commits."""
    study = get_study(db, name, for_update=True)
    if study.status == status:
        return study
    if status is StudyStatus.OPEN and study.unblinded_at is not None:
        raise Conflict(
            f"study {name!r} has been unblinded: participants enrolled now would run unblinded, "
            "so it stays closed (create a new study for more participants)"
        )
    study.status = status
    study.closed_at = utcnow() if status is StudyStatus.CLOSED else None
    audit.record(
        db,
        actor=actor,
        action=f"study.{'closed' if status is StudyStatus.CLOSED else 'opened'}",
        study_id=study.id,
        subject=study.name,
    )
    db.commit()
    return study
