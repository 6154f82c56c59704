"""Study pages: the list, one study with its participants, enrolment and withdrawal, and its
consent text's versions (an admin adds one from the study page)."""

from __future__ import annotations

from typing import Annotated

from fastapi import Form, Request
from fastapi.responses import Response

from app.deps import (
    AdminUser,
    AnalystUser,
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
from app.services.analysis_views import overview
from app.services.audit import Actor
from app.services.participants import enrolment
from app.services.privacy import consent, erasure, retention, sites
from app.tables import ParticipantStatus, Role, User
from app.web.templating import is_htmx, redirect_with_notice, render

router = OneHopRouter(tags=["pages"], include_in_schema=False)

STRATUM_FIELD_PREFIX = "stratum_"
CONSENT_TEXT_PREFIX = "text_"


@router.get("/")
def study_list(
    request: Request, db: SessionDep, user: CurrentUser, archived: bool = False
) -> Response:
    """The studies in use with their enrolment (per condition where the role may see
    conditions); ``?archived=true``: the hidden ones."""
    actor = Actor.of_user(user)
    rows = []
    for study in studies.list_studies(db, archived=archived):
        counts = enrolment.counts_by_label(db, study, actor=actor)
        rows.append(
            {
                "study": study,
                "counts": counts,
                "total": sum(sum(by_status.values()) for by_status in counts.values()),
            }
        )
    return render(
        request,
        "studies.html",
        {"rows": rows, "archived": archived, "archived_count": studies.count_archived(db)},
    )


def _study_page(
    request: Request,
    db: SessionDep,
    user: User,
    name: str,
    *,
    form_error: str = "",
    form_values: dict[str, str] | None = None,
    revealed: str = "",
    consent_error: str = "",
    consent_values: dict[str, str] | None = None,
    status_code: int = 200,
) -> Response:
    study = studies.get_study(db, name)
    protocol = studies.protocol_of(study)
    return render(
        request,
        "study.html",
        {
            "study": study,
            "protocol": protocol,
            "overview": overview.study_overview(db, study=study, actor=Actor.of_user(user)),
            "retention_due": retention.deadline(study),
            "shows_conditions": blinding.shows_conditions(study, Actor.of_user(user)),
            "neutral_groups": list(
                dict.fromkeys(blinding.condition_labels(study, Actor.of_user(user)).values())
            ),
            # Which neutral label each condition had: only once the study is unblinded.
            "blinded_as": (study.neutral_labels or {}) if study.unblinded_at else {},
            "sealed": blinding.is_sealed(study),
            "can_enrol": user.role in (Role.ADMIN, Role.EXPERIMENTER),
            "form_error": form_error,
            "form_values": form_values or {},
            "revealed": revealed,
            "stratum_prefix": STRATUM_FIELD_PREFIX,
            "language_names": {code: native_name(code) for code in protocol.study.languages},
            "site_choices": sites.choices(protocol, Actor.of_user(user)),
            "site_limit": sites.describe(Actor.of_user(user).sites)
            if Actor.of_user(user).sites is not None
            else "",
            "consent_versions": consent.versions(db, study),
            "consent_error": consent_error,
            "consent_values": consent_values or {},
            "consent_prefix": CONSENT_TEXT_PREFIX,
        },
        block="participant_table"
        if request.query_params.get("block") == "participant_table"
        else "participants",
        status_code=status_code,
    )


@router.get("/studies/{name}")
def study_page(request: Request, db: SessionDep, user: CurrentUser, name: str) -> Response:
    """One study: protocol summary, participants, enrolment form."""
    return _study_page(request, db, user, name)


@router.get("/studies/{name}/protocol.toml")
def protocol_file(db: SessionDep, user: AnalystUser, name: str) -> Response:
    """The protocol file the study was created with, byte for byte (for the roles that see
    conditions: the file names them): to keep, to start another study from, to cite."""
    study = studies.get_study(db, name)
    return Response(
        study.protocol_source,
        media_type="application/toml; charset=utf-8",
        headers={
            "Content-Disposition": f'attachment; filename="{study.name}-protocol.toml"',
            "X-Content-SHA256": study.protocol_sha256,
        },
    )


@router.post("/studies/{name}/participants")
def enrol(
    request: Request, db: SessionDep, user: ExperimenterUser, name: str, fields: FormFields
) -> Response:
    """Enrol a participant from the form and reveal their allocation once."""
    strata = {
        key.removeprefix(STRATUM_FIELD_PREFIX): value
        for key, value in fields.items()
        if key.startswith(STRATUM_FIELD_PREFIX)
    }
    actor = Actor.of_user(user)
    try:
        result = enrolment.enroll_participant(
            db,
            study_name=name,
            actor=actor,
            code=fields.get("code", "").strip() or None,
            strata=strata,
            language=fields.get("language", "").strip() or None,
            site=fields.get("site", "").strip() or None,
        )
    except (InvalidInput, Conflict, PermissionDenied) as exc:
        db.rollback()
        return _study_page(
            request,
            db,
            user,
            name,
            form_error=exc.message,
            form_values=fields,
            status_code=exc.status_code,
        )
    label = enrolment.condition_label(studies.get_study(db, name), result.condition, actor=actor)
    revealed = f"Enrolled {result.participant.code}: allocated to {label}."
    if is_htmx(request):  # the allocation is shown once, inside the part htmx swaps in
        return _study_page(request, db, user, name, revealed=revealed)
    return redirect_with_notice(request, f"/studies/{name}", revealed)


@router.get("/studies/{name}/participants/{code}/withdraw")
def withdraw_form(
    request: Request, db: SessionDep, user: ExperimenterUser, name: str, code: str
) -> Response:
    """Ask what to do with the data (the protocol's options) and for confirmation before
    withdrawing a participant, or before erasing someone already withdrawn."""
    return _withdraw_page(request, db, user, name, code)


def _withdraw_page(
    request: Request,
    db: SessionDep,
    user: User,
    name: str,
    code: str,
    *,
    form_error: str | None = None,
    status_code: int = 200,
    chosen: str = "",
    reason: str = "",
) -> Response:
    """The form; a refused one comes back with every choice made (``chosen`` data option, the
    reason), so that submitting it again does what was chosen, not the first option."""
    study = studies.get_study(db, name)
    participant = enrolment.get_participant(db, study, code, actor=Actor.of_user(user))
    options = enrolment.withdrawal_options(study)
    if participant.status == ParticipantStatus.WITHDRAWN:
        options = tuple(o for o in options if o == enrolment.ERASE)
        if not options:
            raise Conflict(f"participant {code!r} is already withdrawn (their data is kept)")
    return render(
        request,
        "withdraw.html",
        {
            "study": study,
            "participant": participant,
            "options": options,
            "form_error": form_error,
            "chosen": chosen,
            "reason": reason,
        },
        status_code=status_code,
    )


@router.post("/studies/{name}/participants/{code}/withdraw")
def withdraw(
    request: Request,
    db: SessionDep,
    settings: SettingsDep,
    user: ExperimenterUser,
    name: str,
    code: str,
    reason: Annotated[str, Form(max_length=2000)] = "",
    data: Annotated[str, Form(max_length=16)] = enrolment.KEEP,
    confirm_code: Annotated[str, Form(max_length=64)] = "",
) -> Response:
    """Withdraw a participant keeping their data, or erase everything they gave the study
    (which needs their code typed again)."""
    actor = Actor.of_user(user)
    if data == enrolment.KEEP:
        enrolment.withdraw_participant(db, study_name=name, code=code, actor=actor, reason=reason)
        return redirect_with_notice(request, f"/studies/{name}", f"Withdrew {code}.")
    if data != enrolment.ERASE:
        raise InvalidInput(
            f"choose what happens to the data: {enrolment.KEEP} or {enrolment.ERASE}"
        )
    if confirm_code.strip() != code:
        return _withdraw_page(
            request,
            db,
            user,
            name,
            code,
            form_error=f"Type {code} to confirm that everything they gave is to be erased.",
            status_code=422,
            chosen=data,
            reason=reason,
        )
    result = erasure.erase_participant(
        db, study_name=name, code=code, actor=actor, secret=settings.secret, reason=reason
    )
    return render(request, "erased.html", {"study": studies.get_study(db, name), "result": result})


@router.post("/admin/studies/{name}/consent")
def add_consent_version(
    request: Request, db: SessionDep, admin: AdminUser, name: str, fields: FormFields
) -> Response:
    """Add the next version of the consent text (confirmed on the form; audited)."""
    studies.get_study(db, name)  # an unknown study is a 404, not a form error
    texts = {
        key.removeprefix(CONSENT_TEXT_PREFIX): value
        for key, value in fields.items()
        if key.startswith(CONSENT_TEXT_PREFIX)
    }
    try:
        if fields.get("confirm") != "yes":
            raise InvalidInput("tick the box to confirm the new text; nothing was added")
        added = consent.add_version(
            db,
            study_name=name,
            texts=texts,
            actor=Actor.of_user(admin),
            label=fields.get("label", ""),
            reason=fields.get("reason", ""),
        )
    except (InvalidInput, Conflict) as exc:
        db.rollback()
        return _study_page(
            request,
            db,
            admin,
            name,
            consent_error=exc.message,
            consent_values=dict(fields),
            status_code=exc.status_code,
        )
    return redirect_with_notice(
        request,
        f"/studies/{name}",
        f"Added version {added.number} ({added.label}) of the consent text.",
    )
