"""A study's phase in the browser: start the pilot, go back to draft, go live, reset the pilot
(admins; app.services.design.study_phases). Each asks first on a page of its own that says what will
happen, and a refusal stays on that page in words."""

from __future__ import annotations

from typing import Annotated

from fastapi import Form, Request
from fastapi.responses import Response

from app.deps import AdminUser, OneHopRouter, SessionDep
from app.errors import Conflict, InvalidInput
from app.services import studies
from app.services.audit import Actor
from app.services.design import study_phases
from app.tables import StudyPhase
from app.web.templating import redirect_with_notice, render

router = OneHopRouter(prefix="/admin", tags=["pages"], include_in_schema=False)

DONE = {
    StudyPhase.DRAFT: "Back to draft: edit the protocol, then pilot it again or go live.",
    StudyPhase.PILOT: "Pilot started: everyone enrolled now is a pilot participant.",
    StudyPhase.LIVE: "The study is live: its protocol is frozen and real participants enrol.",
}


def _phase_page(
    request: Request,
    db: SessionDep,
    name: str,
    *,
    to: str = "",
    reset: bool = False,
    error: str = "",
    status_code: int = 200,
) -> Response:
    study = studies.get_study(db, name)
    target = study_phases.parse_phase(to) if to else None
    current = study_phases.phase_of(study)
    return render(
        request,
        "admin_study_phase.html",
        {
            "study": study,
            "target": target,
            "reset": reset,
            "allowed": target is None or target in study_phases.NEXT_PHASES[current],
            "pilots": study_phases.pilot_count(db, study),
            "error": error,
        },
        status_code=status_code,
    )


@router.get("/studies/{name}/phase")
def phase_form(
    request: Request, db: SessionDep, admin: AdminUser, name: str, to: str = ""
) -> Response:
    """Say what moving to phase ``to`` does (going live cannot be undone); ask to confirm."""
    if not to:
        raise InvalidInput("say which phase: ?to=draft, ?to=pilot or ?to=live")
    return _phase_page(request, db, name, to=to)


@router.post("/studies/{name}/phase")
def set_phase(
    request: Request,
    db: SessionDep,
    admin: AdminUser,
    name: str,
    phase: Annotated[str, Form(max_length=16)],
) -> Response:
    """Move the study to ``phase`` (audited); a refusal stays on the confirmation page."""
    target = study_phases.parse_phase(phase)
    try:
        study_phases.set_phase(db, name=name, phase=target, actor=Actor.of_user(admin))
    except Conflict as exc:
        db.rollback()
        return _phase_page(
            request, db, name, to=phase, error=exc.message, status_code=exc.status_code
        )
    return redirect_with_notice(request, f"/studies/{name}", DONE[target])


@router.get("/studies/{name}/pilot/reset")
def reset_form(request: Request, db: SessionDep, admin: AdminUser, name: str) -> Response:
    """Say what a pilot reset deletes; ask to confirm."""
    return _phase_page(request, db, name, reset=True)


@router.post("/studies/{name}/pilot/reset")
def reset(request: Request, db: SessionDep, admin: AdminUser, name: str) -> Response:
    """Delete the study's pilot participants and their data (audited)."""
    done = study_phases.reset_pilot(db, name=name, actor=Actor.of_user(admin))
    return redirect_with_notice(request, f"/studies/{name}", done.describe().capitalize() + ".")
