"""Enrolment with concealed randomisation, and withdrawal.

An allocation is revealed only here, at the moment a participant is enrolled: the study row is
locked (``SELECT … FOR UPDATE`` on PostgreSQL; SQLite's write transactions are serial anyway), the
next unrevealed entry of the participant's stratum is computed from the secret seed and stored,
and the reveal is audited, all in one transaction. ``UNIQUE(study_id, pilot, stratum,
sequence_index)`` backs the lock up: no entry can ever be handed out twice. A pilot participant
(app.services.design.study_phases) takes the next entry of the pilot's own sequence.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path

from sqlalchemy import exists, func, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, aliased

from app.errors import Conflict, InvalidInput
from app.inputs import PARTICIPANT_CODE, STRATUM_VALUE
from app.protocol import SITE_FACTOR, AllocationSpec, Protocol
from app.randomisation import entry_at, sequence_seed, stratum_key
from app.services import audit, blinding
from app.services.audit import Actor
from app.services.design.protocol_versions import current_number
from app.services.participants import languages, participant_changes
from app.services.participants.participant_changes import Change
from app.services.privacy import sites
from app.services.sessions import learners, step_store
from app.services.studies import enrolment_counts, get_study, protocol_of
from app.sql import Cursor
from app.tables import (
    Allocation,
    LearnerState,
    Participant,
    ParticipantStatus,
    RunStatus,
    SessionStatus,
    Study,
    StudyPhase,
    StudyStatus,
    utcnow,
)


@dataclass(frozen=True)
class Enrolment:
    """A newly enrolled participant and the allocation revealed for them."""

    participant: Participant
    allocation: Allocation

    @property
    def condition(self) -> str:
        """The condition id, e.g. ``C1``."""
        return self.allocation.condition


def condition_label(study: Study, condition_id: str, *, actor: Actor) -> str:
    """What this actor may see of a condition: its id, or a neutral label while the study is
    blinded (app.services.blinding)."""
    if blinding.shows_conditions(study, actor):
        return condition_id
    return blinding.neutral_label(study, condition_id)


def counts_by_label(db: Session, study: Study, *, actor: Actor) -> dict[str, dict[str, int]]:
    """Participants per status under each label ``actor`` may see, in the order to list them
    (app.services.blinding.condition_labels); conditions sharing a neutral label are pooled."""
    counts = enrolment_counts(db, study, actor=actor)
    labels = blinding.condition_labels(study, actor)
    pooled: dict[str, dict[str, int]] = {}
    for condition_id, label in labels.items():
        by_status = counts.pop(condition_id, {})
        into = pooled.setdefault(label, dict.fromkeys(ParticipantStatus, 0))
        for status, n in by_status.items():
            into[status] += n
    for condition_id, by_status in counts.items():  # a condition the protocol lacks
        pooled[condition_label(study, condition_id, actor=actor)] = by_status
    return pooled


def _validate_strata(spec: AllocationSpec, strata: Mapping[str, str]) -> dict[str, str]:
    declared = set(spec.stratify_by)
    unknown = sorted(set(strata) - declared)
    if unknown:
        expected = ", ".join(spec.stratify_by) or "nothing"
        raise InvalidInput(
            f"this study does not stratify by {', '.join(unknown)} (it stratifies by {expected})"
        )
    missing = [factor for factor in spec.stratify_by if factor not in strata]
    if missing:
        example = " ".join(f"--stratum {factor}=VALUE" for factor in missing)
        raise InvalidInput(f"this study stratifies by {', '.join(missing)}: give {example}")
    clean = {}
    for factor, raw in strata.items():
        value = str(raw).strip()
        allowed = spec.strata_values.get(factor)
        if allowed is not None and value not in allowed:
            raise InvalidInput(f"{factor}={value!r} is not one of: {', '.join(allowed)}")
        if not STRATUM_VALUE.matches(value):
            raise InvalidInput(f"{factor}: {STRATUM_VALUE.rule}")
        clean[factor] = value
    return clean


PILOT_CODE_PREFIX = "pilot-"
"""What a pilot participant's automatic code begins with (after its site's prefix)."""


def _next_code(db: Session, study: Study, site: str | None, *, pilot: bool) -> str:
    """``P001``, ``P002``…; at a site, numbered per site after its name (``uppsala-001``), so a
    code tells where the participant is and says nothing of how many the other sites have.
    A pilot participant's is ``pilot-001`` (``uppsala-pilot-001``), numbered apart: seen in a
    list or a file, it says what it is."""
    query = select(func.count()).where(
        Participant.study_id == study.id, Participant.pilot.is_(pilot)
    )
    prefix = "P"
    if site is not None:
        query = query.where(Participant.site == site)
        prefix = sites.code_prefix(site)
    if pilot:
        prefix = (prefix if site is not None else "") + PILOT_CODE_PREFIX
    number = (db.scalar(query) or 0) + 1
    while True:
        code = f"{prefix}{number:03d}"
        if not _code_taken(db, study, code):
            return code
        number += 1


def _code_taken(db: Session, study: Study, code: str) -> bool:
    query = select(Participant.id).where(Participant.study_id == study.id, Participant.code == code)
    return db.scalar(query) is not None


def _dropout_to_replace(
    db: Session, study: Study, stratum: str, *, pilot: bool
) -> Participant | None:
    """The earliest-withdrawn participant of the stratum (and of the pilot, or not) whom nobody
    replaces yet."""
    replacement = aliased(Allocation)
    return db.scalar(
        select(Participant)
        .where(
            Participant.study_id == study.id,
            Participant.stratum == stratum,
            Participant.pilot.is_(pilot),
            Participant.status == ParticipantStatus.WITHDRAWN,
            ~exists().where(replacement.replaces_participant_id == Participant.id),
        )
        .order_by(Participant.withdrawn_at, Participant.id)
        .limit(1)
    )


def _next_sequence_index(db: Session, study: Study, stratum: str, *, pilot: bool) -> int:
    last = db.scalar(
        select(func.max(Allocation.sequence_index)).where(
            Allocation.study_id == study.id,
            Allocation.stratum == stratum,
            Allocation.pilot.is_(pilot),
        )
    )
    return 0 if last is None else last + 1


def _reveal(db: Session, study: Study, protocol: Protocol, participant: Participant) -> Allocation:
    pilot = participant.pilot
    if protocol.allocation.replace_dropouts:
        dropout = _dropout_to_replace(db, study, participant.stratum, pilot=pilot)
        if dropout is not None:
            return Allocation(
                study_id=study.id,
                participant_id=participant.id,
                stratum=participant.stratum,
                condition=dropout.allocation.condition,
                replaces_participant_id=dropout.id,
                pilot=pilot,
            )
    index = _next_sequence_index(db, study, participant.stratum, pilot=pilot)
    entry = entry_at(
        sequence_seed(study.allocation_seed, pilot=pilot),
        participant.stratum,
        [condition.id for condition in protocol.conditions],
        protocol.allocation.block_sizes,
        index,
    )
    return Allocation(
        study_id=study.id,
        participant_id=participant.id,
        stratum=participant.stratum,
        sequence_index=entry.index,
        block_number=entry.block_number,
        block_size=entry.block_size,
        condition=entry.condition,
        pilot=pilot,
    )


def _create_learners(
    db: Session,
    protocol: Protocol,
    participant: Participant,
    condition: str,
    checkpoint_dir: Path | None,
) -> None:
    """One learner per category, in its initial state, in the enrolment's transaction."""
    for category in protocol.categories:
        spec = learners.learner_spec(protocol, condition, category, checkpoint_dir)
        initial = learners.build(spec).state_dict()
        db.add(
            LearnerState(
                participant_id=participant.id,
                category=category.name,
                kind=spec.kind,
                n_arms=spec.n_arms,
                config=spec.config,
                checkpoint_sha256=spec.checkpoint_sha256,
                initial_state=initial,
                state=initial,
            )
        )


def enroll_participant(
    db: Session,
    *,
    study_name: str,
    actor: Actor,
    code: str | None = None,
    strata: Mapping[str, str] | None = None,
    checkpoint_dir: Path | None = None,
    language: str | None = None,
    site: str | None = None,
    along: Callable[[Participant], None] | None = None,
) -> Enrolment:
    """Enrol a participant and reveal their allocation; commits.

    ``along``: called with the new participant before the commit, for rows that must exist
    exactly when the enrolment does (an online participation, app.online.participation); an
    IntegrityError of theirs is a Conflict like a concurrent enrolment's.

    ``language``: one of the study's languages; without it the participant gets the study's
    first, or chooses on the tablet when the protocol lets them
    (app.services.participants.languages). ``site``: one of the study's sites, required when it
    declares any, and one the actor's account may see (app.services.privacy.sites); with ``[sites]
    stratify`` it is also the stratum's ``site`` factor.

    ``code``: typed, or None for the next automatic one; at a site it begins with the site's
    name and a hyphen (``uppsala-017``), as automatic codes do, so that a code can only ever
    clash with one of its own site's (app.services.privacy.sites.check_code).

    Raises NotFound for an unknown study, Conflict for a closed or draft study or a taken code,
    PermissionDenied for a site the actor's account is not limited to, and InvalidInput for a
    malformed code (or one without its site's prefix), a language the study does not offer, a
    site it does not declare or strata that do not match the protocol.
    """
    study = get_study(db, study_name, for_update=True)
    if study.status != StudyStatus.OPEN:
        raise Conflict(f"study {study.name!r} is closed to enrolment; an admin can reopen it")
    if study.phase == StudyPhase.DRAFT:
        raise Conflict(
            f"study {study.name!r} is a draft: nobody enrols until an admin starts its pilot "
            "or takes it live"
        )
    pilot = study.phase == StudyPhase.PILOT
    protocol = protocol_of(study)
    clean_strata = _validate_strata(protocol.allocation, strata or {})
    site = sites.enrolment_site(protocol, site, actor=actor, study=study)
    if site is not None and protocol.sites is not None and protocol.sites.stratify:
        clean_strata[SITE_FACTOR] = site
    if language is not None:
        languages.offered(protocol, language, study_name=study.name)
    elif not languages.chooses_on_tablet(protocol):
        language = protocol.default_language
    if code is not None:
        code = code.strip()
        PARTICIPANT_CODE.check(code)
        # In a study with sites a typed code begins with its site's name, so it can clash only
        # with a participant of that site: "already used" never tells a limited account that
        # a code exists at a site it cannot see (app.services.privacy.sites).
        sites.check_code(code, site, study=study)
        if _code_taken(db, study, code):
            raise Conflict(f"participant code {code!r} is already used in study {study.name!r}")
    participant = Participant(
        study_id=study.id,
        code=code or _next_code(db, study, site, pilot=pilot),
        stratum=stratum_key(clean_strata),
        strata=clean_strata,
        enrolled_by=actor.name,
        language=language,
        site=site,
        pilot=pilot,
        protocol_version=current_number(db, study),
    )
    db.add(participant)
    db.flush()
    allocation = _reveal(db, study, protocol, participant)
    db.add(allocation)
    db.flush()
    _create_learners(db, protocol, participant, allocation.condition, checkpoint_dir)
    audit.record(
        db,
        actor=actor,
        action="participant.enrolled",
        study_id=study.id,
        subject=participant.code,
        details={
            "stratum": participant.stratum,
            "language": participant.language,
            "site": participant.site,
        }
        | ({"pilot": True} if pilot else {}),
    )
    audit.record(
        db,
        actor=actor,
        action="allocation.revealed",
        study_id=study.id,
        subject=participant.code,
        # Never the entry's place in the sequence or its block: with them, whoever reads the
        # log could tell the rest of a block in advance (app.services.blinding).
        details={
            "condition": allocation.condition,
            "replaces_participant_id": allocation.replaces_participant_id,
        },
    )
    participant_changes.participant_changed(db, participant, Change.ENROLLED)
    try:
        if along is not None:
            along(participant)
        db.commit()
    except IntegrityError as exc:
        db.rollback()
        raise Conflict(
            f"participant code {participant.code!r} or allocation was taken concurrently; retry"
        ) from exc
    return Enrolment(participant=participant, allocation=allocation)


def get_participant(
    db: Session, study: Study, code: str, *, actor: Actor, for_update: bool = False
) -> Participant:
    """A participant of the study by code; NotFound otherwise, and for a participant of a site
    ``actor`` may not see (app.services.privacy.sites: as if there were none)."""
    query = select(Participant).where(
        Participant.study_id == study.id, Participant.code == code, sites.visible(actor)
    )
    if for_update:
        query = query.with_for_update()
    participant = db.scalar(query)
    if participant is None:
        raise sites.not_found(study, code)
    return participant


KEEP = "keep"
ERASE = "erase"
"""The two things a withdrawal may do with the data (app.protocol.WithdrawalSpec)."""


def withdrawal_options(study: Study) -> tuple[str, ...]:
    """What the study's protocol lets a withdrawal do with the data: keep and/or erase."""
    return tuple(protocol_of(study).withdrawal.options)


def require_withdrawal_option(study: Study, option: str) -> None:
    """Refuse a withdrawal option the protocol does not allow, saying which it does."""
    options = withdrawal_options(study)
    if option not in options:
        if option == ERASE:
            raise Conflict(
                f"study {study.name!r} keeps withdrawn participants' data (its protocol's "
                "withdrawal.options has no 'erase')"
            )
        raise Conflict(
            f"study {study.name!r} erases the data of everyone who withdraws (its protocol's "
            "withdrawal.options is ['erase']): erase instead"
        )


def withdraw_participant(
    db: Session, *, study_name: str, code: str, actor: Actor, reason: str = ""
) -> Participant:
    """Mark a participant withdrawn (they keep their allocation and data); commits. Refused
    when the protocol erases everyone who withdraws (app.services.privacy.erasure does that).

    A session of theirs still running ends early with the withdrawal: the room stops offering
    its zones and the console its run buttons. They stay seated, so that a robot retrying an
    answer acknowledged before the withdrawal still gets its stored reply and a kiosk tablet
    shows them the thank-you page; the console then offers to free the station."""
    study = get_study(db, study_name)
    require_withdrawal_option(study, KEEP)
    participant = get_participant(db, study, code, actor=actor, for_update=True)
    if participant.status == ParticipantStatus.WITHDRAWN:
        raise Conflict(f"participant {code!r} is already withdrawn")
    participant.status = ParticipantStatus.WITHDRAWN
    participant.withdrawn_at = utcnow()
    participant.withdrawal_reason = reason.strip()[:2000]
    ended = _end_running_session(db, participant, actor)
    audit.record(
        db,
        actor=actor,
        action="participant.withdrawn",
        study_id=study.id,
        subject=code,
        details={"reason": participant.withdrawal_reason}
        | ({"session_ended_early": ended} if ended is not None else {}),
    )
    participant_changes.participant_changed(db, participant, Change.WITHDRAWN)
    db.commit()
    return participant


def _end_running_session(db: Session, participant: Participant, actor: Actor) -> int | None:
    """End the participant's running session (and its run) early, as the console's "End session
    early" does; its number, or None when none was running. The caller holds the participant's
    row lock, which serialises this with their prompts and answers
    (app.services.sessions.runtime)."""
    cursor = Cursor.of(db)
    run = step_store.latest_run(cursor, participant_id=participant.id)
    if run is None or run.session_status != SessionStatus.RUNNING:
        return None
    if run.run_status == RunStatus.RUNNING:
        step_store.close_run(cursor, run_id=run.run_id, status=RunStatus.ENDED_EARLY)
    step_store.close_session(
        cursor, session_id=run.session_id, status=SessionStatus.ENDED_EARLY, actor=actor.name
    )
    return run.session_number


def list_participants(db: Session, study: Study, *, actor: Actor) -> list[Participant]:
    """Every participant of the study ``actor`` may see, in enrolment order, allocations loaded;
    erased ones are left out (their rows only hold allocation slots)."""
    query = (
        select(Participant)
        .where(
            Participant.study_id == study.id,
            Participant.erased_at.is_(None),
            sites.visible(actor),
        )
        .order_by(Participant.enrolled_at, Participant.id)
    )
    return list(db.scalars(query))
