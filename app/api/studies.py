"""Studies and their participants over JSON."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Request, status
from sqlalchemy import select
from sqlalchemy.orm import Session

from app.api.schemas import (
    ConditionCount,
    ConsentStandingOut,
    Enrolled,
    EnrolmentRequest,
    ErasureOut,
    ErasureRequest,
    ParticipantOut,
    PilotResetOut,
    ShippedProtocol,
    StudyCreate,
    StudyPhaseChange,
    StudyStatusChange,
    StudySummary,
    TabletLink,
    Withdrawal,
)
from app.deps import AdminUser, CurrentUser, ExperimenterUser, SessionDep, SettingsDep
from app.errors import InvalidInput
from app.protocol import ProtocolError, parse_protocol, shipped_protocol, shipped_protocol_files
from app.services import blinding, studies
from app.services.audit import Actor
from app.services.design import study_phases
from app.services.participants import enrolment, questionnaires, tablet_tokens
from app.services.privacy import consent, erasure, sites
from app.tables import Participant, Study, StudyPhase, StudyStatus

router = APIRouter(prefix="/studies", tags=["studies"])
protocols_router = APIRouter(prefix="/protocols", tags=["studies"])


@protocols_router.get("")
def list_shipped_protocols(user: CurrentUser) -> list[ShippedProtocol]:
    """The protocols trustlab ships, to start a study from (``shipped`` of a new study)."""
    rows = []
    for file in shipped_protocol_files():
        loaded = shipped_protocol(file)
        info = loaded.protocol.study
        rows.append(
            ShippedProtocol(
                file=file,
                title=info.title,
                description=info.description,
                languages=info.languages,
                sha256=loaded.sha256,
            )
        )
    return rows


def _summary(db: SessionDep, study: Study, actor: Actor) -> StudySummary:
    protocol = studies.protocol_of(study)
    return StudySummary(
        name=study.name,
        title=study.title,
        status=study.status,
        phase=study.phase,
        live_at=study.live_at,
        pilots=study_phases.pilot_count(db, study),
        created_at=study.created_at,
        protocol_sha256=study.protocol_sha256,
        blinded=protocol.study.blinded,
        unblinded_at=study.unblinded_at,
        enrolment=[
            ConditionCount(label=label, **by_status)
            for label, by_status in enrolment.counts_by_label(db, study, actor=actor).items()
        ],
    )


def _consent(standing: consent.Standing | None) -> ConsentStandingOut | None:
    if standing is None:
        return None
    return ConsentStandingOut(
        current_version=standing.current,
        accepted_version=standing.accepted,
        declined_version=standing.declined,
        reconsent_needed=standing.outdated,
        before_next_session=standing.outdated and standing.required,
    )


def _participant(
    db: Session,
    study: Study,
    participant: Participant,
    actor: Actor,
    standing: consent.Standing | None = None,
) -> ParticipantOut:
    if standing is None and participant.erased_at is None:
        standing = consent.standing(db, participant, study)
    return ParticipantOut(
        code=participant.code,
        condition=enrolment.condition_label(study, participant.allocation.condition, actor=actor),
        stratum=participant.stratum,
        status=participant.status,
        enrolled_at=participant.enrolled_at,
        withdrawn_at=participant.withdrawn_at,
        locked=participant.locked_at is not None,
        language=participant.language,
        site=participant.site,
        pilot=participant.pilot,
        consent=_consent(standing),
    )


@router.get("")
def list_studies(db: SessionDep, user: CurrentUser) -> list[StudySummary]:
    """Every study, newest first."""
    actor = Actor.of_user(user)
    return [_summary(db, study, actor) for study in studies.list_studies(db)]


@router.post("", status_code=status.HTTP_201_CREATED)
def create_study(body: StudyCreate, db: SessionDep, admin: AdminUser) -> StudySummary:
    """Create a study (admin) from protocol TOML, a shipped protocol or a copy of a study's."""
    given = [
        key for key in ("protocol_toml", "shipped", "copy_of") if getattr(body, key) is not None
    ]
    if len(given) != 1:
        raise InvalidInput("give exactly one of protocol_toml, shipped and copy_of")
    try:
        if body.protocol_toml is not None:
            loaded = parse_protocol(body.protocol_toml, source="protocol_toml")
            started_from = "text protocol_toml"
        else:
            loaded, started_from = studies.starting_protocol(
                db, shipped=body.shipped, copy_of=body.copy_of
            )
    except ProtocolError as exc:
        raise InvalidInput(str(exc)) from exc
    study = studies.create_study(
        db,
        name=body.name,
        loaded=loaded,
        actor=Actor.of_user(admin),
        title=body.title,
        started_from=started_from,
        phase=StudyPhase(body.phase),
    )
    return _summary(db, study, Actor.of_user(admin))


@router.get("/{name}")
def get_study(name: str, db: SessionDep, user: CurrentUser) -> StudySummary:
    """One study."""
    return _summary(db, studies.get_study(db, name), Actor.of_user(user))


@router.get("/{name}/protocol")
def get_protocol(name: str, db: SessionDep, user: CurrentUser) -> dict[str, Any]:
    """The study's validated protocol; blinded roles see neutral condition labels only."""
    study = studies.get_study(db, name)
    protocol = studies.protocol_of(study)
    data = protocol.model_dump(mode="json")
    actor = Actor.of_user(user)
    if not blinding.shows_conditions(study, actor):
        # Listed by label: the protocol's order of the conditions would tell which is which.
        data["conditions"] = [
            {"id": label, "label": label}
            for label in dict.fromkeys(blinding.condition_labels(study, actor).values())
        ]
        data["learners"] = {}
    return data


@router.post("/{name}/status")
def set_status(
    name: str, body: StudyStatusChange, db: SessionDep, admin: AdminUser
) -> StudySummary:
    """Open or close enrolment (admin)."""
    actor = Actor.of_user(admin)
    study = studies.set_study_status(db, name=name, status=StudyStatus(body.status), actor=actor)
    return _summary(db, study, actor)


@router.post("/{name}/phase")
def set_phase(name: str, body: StudyPhaseChange, db: SessionDep, admin: AdminUser) -> StudySummary:
    """Move a study between draft, pilot and live (admin; audited). Going live freezes the
    protocol and starts the concealed sequence; a live study stays live (409)."""
    actor = Actor.of_user(admin)
    study = study_phases.set_phase(db, name=name, phase=StudyPhase(body.phase), actor=actor)
    return _summary(db, study, actor)


@router.post("/{name}/pilot/reset")
def reset_pilot(name: str, db: SessionDep, admin: AdminUser) -> PilotResetOut:
    """Delete every pilot participant of the study and all their data (admin; audited)."""
    reset = study_phases.reset_pilot(db, name=name, actor=Actor.of_user(admin))
    return PilotResetOut(participants=reset.participants, removed=reset.removed)


@router.post("/{name}/unblind")
def unblind(name: str, db: SessionDep, admin: AdminUser) -> StudySummary:
    """Lift a closed blinded study's blinding for good (admin; audited): staff then see the
    conditions and the learners' probabilities, confidence levels and reply history."""
    actor = Actor.of_user(admin)
    return _summary(db, blinding.unblind(db, name=name, actor=actor), actor)


@router.get("/{name}/participants")
def list_participants(name: str, db: SessionDep, user: CurrentUser) -> list[ParticipantOut]:
    """Participants in enrolment order."""
    study = studies.get_study(db, name)
    actor = Actor.of_user(user)
    standings = consent.standings(db, study)  # one query for everyone
    current = consent.current_number(db, study.id)
    required = studies.protocol_of(study).questionnaires.consent.reconsent_before_next_session
    return [
        _participant(
            db,
            study,
            p,
            actor,
            None
            if p.erased_at is not None
            else standings.get(p.id, consent.Standing(current, None, None, required)),
        )
        for p in enrolment.list_participants(db, study, actor=actor)
    ]


@router.get("/{name}/participants/{code}")
def get_participant(name: str, code: str, db: SessionDep, user: CurrentUser) -> ParticipantOut:
    """One participant: status, condition (sealed while blinded), language, site and where
    they stand with the consent text (re-consent needed, and whether it holds their next
    session back)."""
    study = studies.get_study(db, name)
    actor = Actor.of_user(user)
    return _participant(db, study, enrolment.get_participant(db, study, code, actor=actor), actor)


@router.post("/{name}/participants", status_code=status.HTTP_201_CREATED)
def enrol(name: str, body: EnrolmentRequest, db: SessionDep, user: ExperimenterUser) -> Enrolled:
    """Enrol a participant and reveal their allocation (once)."""
    actor = Actor.of_user(user)
    result = enrolment.enroll_participant(
        db,
        study_name=name,
        actor=actor,
        code=body.code,
        strata=body.strata,
        language=body.language,
        site=body.site,
    )
    study = studies.get_study(db, name)
    replaced = result.allocation.replaces_participant_id
    # A dropout replaced is of the same stratum, so of the same site when sites stratify; when
    # they do not, it may be another site's participant: then unnamed for a site-limited actor.
    replaced_code = db.scalar(
        select(Participant.code).where(Participant.id == replaced, sites.visible(actor))
    )
    return Enrolled(
        code=result.participant.code,
        condition=enrolment.condition_label(study, result.condition, actor=actor),
        stratum=result.participant.stratum,
        replaces=replaced_code,
        language=result.participant.language,
        site=result.participant.site,
    )


@router.post("/{name}/participants/{code}/withdraw")
def withdraw(
    name: str, code: str, body: Withdrawal, db: SessionDep, user: ExperimenterUser
) -> ParticipantOut:
    """Withdraw a participant; they keep their allocation and data."""
    actor = Actor.of_user(user)
    participant = enrolment.withdraw_participant(
        db, study_name=name, code=code, actor=actor, reason=body.reason
    )
    return _participant(db, studies.get_study(db, name), participant, actor)


@router.post("/{name}/participants/{code}/erase")
def erase(
    name: str,
    code: str,
    body: ErasureRequest,
    db: SessionDep,
    settings: SettingsDep,
    user: ExperimenterUser,
) -> ErasureOut:
    """Withdraw (if still active) and erase everything the participant gave the study, if the
    protocol allows erasure; the allocation slot stays."""
    if body.confirm.strip() != code:
        raise InvalidInput(f"confirm must repeat the participant's code ({code}): erasure is final")
    result = erasure.erase_participant(
        db,
        study_name=name,
        code=code,
        actor=Actor.of_user(user),
        secret=settings.secret,
        reason=body.reason,
    )
    return ErasureOut.model_validate(result.to_json())


def _link(request: Request, token: str | None, prefix: str) -> TabletLink:
    base = str(request.base_url).rstrip("/")
    return TabletLink(token=token, url=f"{base}/{prefix}/{token}" if token else None)


@router.get("/{name}/participants/{code}/link")
def get_link(
    name: str,
    code: str,
    request: Request,
    db: SessionDep,
    settings: SettingsDep,
    user: ExperimenterUser,
) -> TabletLink:
    """The participant's current tablet link (null when none is issued)."""
    participant = enrolment.get_participant(
        db, studies.get_study(db, name), code, actor=Actor.of_user(user)
    )
    return _link(request, tablet_tokens.participant_token(settings.secret, participant), "t")


@router.post("/{name}/participants/{code}/link")
def issue_link(
    name: str,
    code: str,
    request: Request,
    db: SessionDep,
    settings: SettingsDep,
    user: ExperimenterUser,
) -> TabletLink:
    """Issue (or reissue) the participant's tablet link; earlier links stop working."""
    participant = enrolment.get_participant(
        db, studies.get_study(db, name), code, actor=Actor.of_user(user), for_update=True
    )
    token = tablet_tokens.issue_participant_token(
        db, participant=participant, secret=settings.secret, actor=Actor.of_user(user)
    )
    return _link(request, token, "t")


@router.delete("/{name}/participants/{code}/link")
def revoke_link(name: str, code: str, db: SessionDep, user: ExperimenterUser) -> TabletLink:
    """Revoke the participant's tablet link."""
    participant = enrolment.get_participant(
        db, studies.get_study(db, name), code, actor=Actor.of_user(user), for_update=True
    )
    tablet_tokens.revoke_participant_token(db, participant=participant, actor=Actor.of_user(user))
    return TabletLink(token=None, url=None)


@router.post("/{name}/participants/{code}/lock")
def lock(name: str, code: str, db: SessionDep, user: ExperimenterUser) -> ParticipantOut:
    """Lock the participant's answers for analysis: the tablet's submissions are refused (409),
    new questionnaires and consent as well as revisions, until unlocked."""
    study = studies.get_study(db, name)
    participant = enrolment.get_participant(
        db, study, code, actor=Actor.of_user(user), for_update=True
    )
    questionnaires.set_locked(db, participant=participant, locked=True, actor=Actor.of_user(user))
    return _participant(db, study, participant, Actor.of_user(user))


@router.post("/{name}/participants/{code}/unlock")
def unlock(name: str, code: str, db: SessionDep, user: ExperimenterUser) -> ParticipantOut:
    """Unlock the participant's answers: new submissions and revisions are accepted again."""
    study = studies.get_study(db, name)
    participant = enrolment.get_participant(
        db, study, code, actor=Actor.of_user(user), for_update=True
    )
    questionnaires.set_locked(db, participant=participant, locked=False, actor=Actor.of_user(user))
    return _participant(db, study, participant, Actor.of_user(user))
