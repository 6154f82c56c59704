"""A participant's page: their record, their tablet link, locking and withdrawal."""

from __future__ import annotations

from fastapi import Request
from fastapi.responses import Response

from app.deps import CurrentUser, ExperimenterUser, OneHopRouter, SessionDep, SettingsDep
from app.services import blinding, enrolment, questionnaires, studies, tablet_tokens, timeline
from app.services.audit import Actor
from app.tables import Role
from app.web.qr import qr_svg
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
    study = studies.get_study(db, name)
    participant = enrolment.get_participant(db, study, code)
    can_act = user.role in (Role.ADMIN, Role.EXPERIMENTER)
    token = tablet_tokens.participant_token(settings.secret, participant) if can_act else None
    link = f"{str(request.base_url).rstrip('/')}/t/{token}" if token else None
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
            "qr": qr_svg(link) if link else "",
        },
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
    participant = enrolment.get_participant(db, studies.get_study(db, name), code, for_update=True)
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
    participant = enrolment.get_participant(db, studies.get_study(db, name), code, for_update=True)
    tablet_tokens.revoke_participant_token(db, participant=participant, actor=Actor.of_user(user))
    return redirect_with_notice(request, _page_url(name, code), f"{code}'s tablet link revoked.")


@router.post("/studies/{name}/participants/{code}/lock")
def lock(
    request: Request, db: SessionDep, user: ExperimenterUser, name: str, code: str
) -> Response:
    """Lock the participant's answers (no more edits)."""
    participant = enrolment.get_participant(db, studies.get_study(db, name), code, for_update=True)
    questionnaires.set_locked(db, participant=participant, locked=True, actor=Actor.of_user(user))
    return redirect_with_notice(request, _page_url(name, code), f"{code}'s answers are locked.")


@router.post("/studies/{name}/participants/{code}/unlock")
def unlock(
    request: Request, db: SessionDep, user: ExperimenterUser, name: str, code: str
) -> Response:
    """Allow edits again."""
    participant = enrolment.get_participant(db, studies.get_study(db, name), code, for_update=True)
    questionnaires.set_locked(db, participant=participant, locked=False, actor=Actor.of_user(user))
    return redirect_with_notice(request, _page_url(name, code), f"{code}'s answers are unlocked.")
