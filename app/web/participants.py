"""A participant's page: their record, their tablet link, locking and withdrawal."""

from __future__ import annotations

from fastapi import Request
from fastapi.responses import Response

from app.deps import (
    CurrentUser,
    ExperimenterUser,
    FormFields,
    OneHopRouter,
    SessionDep,
    SettingsDep,
)
from app.errors import Conflict, InvalidInput, PermissionDenied
from app.i18n.languages import native_name
from app.services import blinding, studies
from app.services.audit import Actor
from app.services.participants import enrolment, languages, questionnaires, tablet_tokens, timeline
from app.services.privacy import consent
from app.tables import Role
from app.web.qr import tablet_link
from app.web.templating import redirect_with_notice, render

router = OneHopRouter(tags=["pages"], include_in_schema=False)


def _page_url(name: str, code: str) -> str:
    return f"/studies/{name}/participants/{code}"


@router.get("/studies/{name}/participants/{code}")
def participant_page(
    request: Request,
    db: SessionDep,
    settings: SettingsDep,
    user: CurrentUser,
    name: str,
    code: str,
) -> Response:
    """Everything recorded for one participant, and what can be done with them."""
    return _participant_page(request, db, settings, user, name, code)


def _participant_page(
    request: Request,
    db: SessionDep,
    settings: SettingsDep,
    user: CurrentUser,
    name: str,
    code: str,
    *,
    language_error: str = "",
    status_code: int = 200,
) -> Response:
    study = studies.get_study(db, name)
    participant = enrolment.get_participant(db, study, code, actor=Actor.of_user(user))
    protocol = studies.protocol_of(study)
    can_act = user.role in (Role.ADMIN, Role.EXPERIMENTER)
    token = tablet_tokens.participant_token(settings.secret, participant) if can_act else None
    link = tablet_link(request, f"/t/{token}") if token else None
    return render(
        request,
        "participant.html",
        {
            "study": study,
            "participant": participant,
            "group": enrolment.condition_label(
                study, participant.allocation.condition, actor=Actor.of_user(user)
            ),
            "timeline": timeline.participant_timeline(db, study=study, participant=participant),
            "shows_learners": blinding.shows_learners(study),
            "can_act": can_act,
            "link": link,
            "languages": [(c, native_name(c)) for c in protocol.study.languages],
            "language": languages.language_of(participant.language, protocol),
            "language_chosen": participant.language is not None,
            "language_locked": languages.has_started(db, participant),
            "is_admin": user.role == Role.ADMIN,
            "language_error": language_error,
            "consent_records": consent.records(db, participant),
            "consent_standing": consent.standing(db, participant, study),
        },
        status_code=status_code,
    )


@router.post("/studies/{name}/participants/{code}/language")
def set_language(
    request: Request,
    db: SessionDep,
    settings: SettingsDep,
    user: ExperimenterUser,
    name: str,
    code: str,
    fields: FormFields,
) -> Response:
    """Change the participant's language (after their first session: admins, with a reason)."""
    study = studies.get_study(db, name)
    language = fields.get("language", "").strip()
    try:
        languages.set_language(
            db,
            participant=enrolment.get_participant(
                db, study, code, actor=Actor.of_user(user), for_update=True
            ),
            protocol=studies.protocol_of(study),
            study_name=name,
            language=language,
            actor=Actor.of_user(user),
            actor_role=Role(user.role),
            override_reason=fields.get("reason", ""),
        )
    except (InvalidInput, Conflict, PermissionDenied) as exc:
        db.rollback()
        return _participant_page(
            request,
            db,
            settings,
            user,
            name,
            code,
            language_error=exc.message,
            status_code=exc.status_code,
        )
    return redirect_with_notice(
        request, _page_url(name, code), f"{code} now takes part in {native_name(language)}."
    )


@router.post("/studies/{name}/participants/{code}/link")
def issue_link(
    request: Request,
    db: SessionDep,
    settings: SettingsDep,
    user: ExperimenterUser,
    name: str,
    code: str,
) -> Response:
    """Issue (or reissue) the tablet link; earlier links stop working."""
    participant = enrolment.get_participant(
        db, studies.get_study(db, name), code, actor=Actor.of_user(user), for_update=True
    )
    tablet_tokens.issue_participant_token(
        db, participant=participant, secret=settings.secret, actor=Actor.of_user(user)
    )
    return redirect_with_notice(
        request, _page_url(name, code), f"New tablet link for {code}; earlier links no longer work."
    )


@router.post("/studies/{name}/participants/{code}/link/revoke")
def revoke_link(
    request: Request, db: SessionDep, user: ExperimenterUser, name: str, code: str
) -> Response:
    """Revoke the tablet link."""
    participant = enrolment.get_participant(
        db, studies.get_study(db, name), code, actor=Actor.of_user(user), for_update=True
    )
    tablet_tokens.revoke_participant_token(db, participant=participant, actor=Actor.of_user(user))
    return redirect_with_notice(request, _page_url(name, code), f"{code}'s tablet link revoked.")


@router.post("/studies/{name}/participants/{code}/lock")
def lock(
    request: Request, db: SessionDep, user: ExperimenterUser, name: str, code: str
) -> Response:
    """Lock the participant's answers (no more edits)."""
    participant = enrolment.get_participant(
        db, studies.get_study(db, name), code, actor=Actor.of_user(user), for_update=True
    )
    questionnaires.set_locked(db, participant=participant, locked=True, actor=Actor.of_user(user))
    return redirect_with_notice(request, _page_url(name, code), f"{code}'s answers are locked.")


@router.post("/studies/{name}/participants/{code}/unlock")
def unlock(
    request: Request, db: SessionDep, user: ExperimenterUser, name: str, code: str
) -> Response:
    """Allow edits again."""
    participant = enrolment.get_participant(
        db, studies.get_study(db, name), code, actor=Actor.of_user(user), for_update=True
    )
    questionnaires.set_locked(db, participant=participant, locked=False, actor=Actor.of_user(user))
    return redirect_with_notice(request, _page_url(name, code), f"{code}'s answers are unlocked.")
