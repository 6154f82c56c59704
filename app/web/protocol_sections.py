"""The designer's section pages: a draft's protocol edited as forms, one page per section
(app.protocol_forms), checked as it is typed and saved as a new version like the TOML view's
saves (app.web.study_protocol, app.services.design.protocol_versions).

Every form is written into the version it was drawn from (its ``base``), so a save after someone
else's is refused with what changed, as the TOML view's is; a refused save or an added list entry
draws the form again with everything as submitted."""

from __future__ import annotations

from typing import Any

from fastapi import Request
from fastapi.responses import Response
from starlette.datastructures import FormData, UploadFile

from app.deps import AdminUser, OneHopRouter, SessionDep, SubmittedForm
from app.errors import Conflict, InvalidInput, NotFound
from app.protocol import MAX_PROTOCOL_BYTES, ProtocolError, parse_protocol
from app.protocol_forms import (
    ENTRIES,
    REMOVE,
    SECTION_SLUGS,
    SECTIONS,
    Elsewhere,
    FormField,
    Section,
    apply_form,
    form_counts,
    form_languages,
    place_problems,
    rebase_form,
    section_fields,
    shown_with,
)
from app.services import studies
from app.services.audit import Actor
from app.services.design import protocol_versions
from app.services.design.protocol_versions import EditConflict, NotComparable
from app.tables import Study
from app.web.templating import redirect_with_notice, render

router = OneHopRouter(prefix="/admin", tags=["pages"], include_in_schema=False)


def _section(slug: str) -> Section:
    section = SECTION_SLUGS.get(slug)
    if section is None:
        names = ", ".join(SECTION_SLUGS)
        raise NotFound(f"no protocol section {slug!r}; the sections are {names}")
    return section


def _base_text(db: SessionDep, study: Study, base: str) -> str:
    """The text of the version a form was drawn from; refused when the study never had it."""
    text = protocol_versions.source_of(db, study, base)
    if text is None:
        raise Conflict(
            f"the form was drawn from a protocol version {study.name!r} never had: open the "
            "section again"
        )
    return text


def _problems(text: str) -> list[tuple[str, str]]:
    """Every problem of a protocol text as ``(key path, reason)`` (none: it passes)."""
    if len(text.encode()) > MAX_PROTOCOL_BYTES:
        return [("", f"the protocol is larger than {MAX_PROTOCOL_BYTES // 1024} KiB")]
    try:
        parse_protocol(text, source="protocol")
    except ProtocolError as exc:
        return [(problem.path, problem.reason) for problem in exc.problems]
    return []


def _page(
    request: Request,
    db: SessionDep,
    study: Study,
    section: Section,
    *,
    fields: list[FormField],
    base: str,
    elsewhere: list[Elsewhere] | None = None,
    reason: str = "",
    error: str = "",
    changes: str = "",
    not_comparable: list[str] | None = None,
    split_text: str = "",
    status_code: int = 200,
) -> Response:
    return render(
        request,
        "protocol_section.html",
        {
            "study": study,
            "section": section,
            "sections": SECTIONS,
            "fields": fields,
            "base": base,
            "elsewhere": elsewhere or [],
            "reason": reason,
            "frozen": protocol_versions.frozen_because(study),
            "amendment": protocol_versions.is_amendment(study),
            "not_comparable": not_comparable or [],
            "split_text": split_text,
            "error": error,
            "changes": changes,
            "entries_suffix": ENTRIES,
            "remove_field": REMOVE,
            "version": protocol_versions.current_number(db, study),
            "source_language": studies.protocol_of(study).default_language,
        },
        status_code=status_code,
    )


def _carried_over(
    request: Request,
    db: SessionDep,
    name: str,
    section: Section,
    form: FormData,
    refused: EditConflict,
    *,
    base_text: str,
) -> Response:
    """After a save refused for someone else's: the form carried over to the current version
    (app.protocol_forms.rebase_form), each field both changed saying so."""
    study = studies.get_study(db, name)
    pairs, theirs = rebase_form(section, base_text, study.protocol_source, form)
    rebased = FormData(list[tuple[str, str | UploadFile]](pairs))
    fields, text = _drawn_again(section, study.protocol_source, rebased)
    for made in (made for top in fields for made in top.walk()):
        made.theirs = theirs.get(made.name)
    advice = (
        "Your changes are carried over to that version below (fields you both changed say "
        "so): check them and save again"
    )
    return _page(
        request,
        db,
        study,
        section,
        fields=fields,
        base=study.protocol_sha256,
        elsewhere=place_problems(fields, _problems(text)),
        reason=str(form.get("reason", "")),
        error=f"{refused.headline}. {advice}",
        changes=refused.changes,
        status_code=409,
    )


@router.get("/studies/{name}/design/{slug}")
def section_page(
    request: Request, db: SessionDep, admin: AdminUser, name: str, slug: str
) -> Response:
    """One section of the study's protocol as a form, with its current values."""
    study = studies.get_study(db, name)
    section = _section(slug)
    fields = section_fields(section, study.protocol_source)
    elsewhere = place_problems(fields, _problems(study.protocol_source))
    return _page(
        request, db, study, section, fields=fields, base=study.protocol_sha256, elsewhere=elsewhere
    )


def _drawn_again(
    section: Section, base_text: str, form: FormData, *, add: str = ""
) -> tuple[list[FormField], str]:
    """The form as submitted (one entry more in list ``add``), and the text it makes."""
    counts = form_counts(form, add)
    languages = form_languages(form) if section.slug == "languages" else []
    fields = section_fields(section, base_text, counts, languages)
    shown_with(fields, form, [str(v) for v in form.getlist(REMOVE)])
    return fields, apply_form(section, base_text, form)


@router.post("/studies/{name}/design/{slug}/check")
def check_section(
    request: Request,
    db: SessionDep,
    admin: AdminUser,
    name: str,
    slug: str,
    form: SubmittedForm,
) -> Response:
    """The problems of the protocol the form would make: each beside its field (out-of-band
    swaps), the rest in the summary; nothing is saved."""
    study = studies.get_study(db, name)
    section = _section(slug)
    fields, text = _drawn_again(section, _base_text(db, study, str(form.get("base", ""))), form)
    elsewhere = place_problems(fields, _problems(text))
    return render(
        request,
        "_section_problems.html",
        {
            "fields": fields,
            "elsewhere": elsewhere,
            "checked": True,
            "section": section,
            "study": study,
            "amendment_changes": protocol_versions.amendment_changes(db, study, text),
        },
    )


@router.post("/studies/{name}/design/{slug}")
def save_section(
    request: Request,
    db: SessionDep,
    admin: AdminUser,
    name: str,
    slug: str,
    form: SubmittedForm,
) -> Response:
    """Save the section (a new version), or draw it again with one entry more (``add``)."""
    study = studies.get_study(db, name)
    section = _section(slug)
    base = str(form.get("base", ""))
    reason = str(form.get("reason", ""))[: protocol_versions.REASON_MAX]
    base_text = _base_text(db, study, base)
    fields, text = _drawn_again(section, base_text, form, add=str(form.get("add", "")))
    elsewhere = place_problems(fields, _problems(text))
    kept: dict[str, Any] = {"fields": fields, "base": base, "reason": reason}
    if form.get("add"):
        return _page(request, db, study, section, elsewhere=elsewhere, **kept)
    problems = any(made.problems for top in fields for made in top.walk()) or elsewhere
    if problems:
        error = "the protocol would have problems: see each beside its field"
        return _page(
            request, db, study, section, elsewhere=elsewhere, error=error, status_code=422, **kept
        )
    try:
        saved = protocol_versions.save_protocol(
            db,
            name=name,
            loaded=parse_protocol(text, source="protocol"),
            base_sha256=base,
            actor=Actor.of_user(admin),
            reason=reason,
        )
    except EditConflict as exc:
        db.rollback()
        return _carried_over(request, db, name, section, form, exc, base_text=base_text)
    except NotComparable as exc:
        db.rollback()
        study = studies.get_study(db, name)
        return _page(
            request,
            db,
            study,
            section,
            elsewhere=elsewhere,
            error="this change needs a new study",
            not_comparable=exc.problems,
            split_text=text,
            status_code=409,
            **kept,
        )
    except (InvalidInput, Conflict) as exc:
        db.rollback()
        study = studies.get_study(db, name)
        return _page(
            request, db, study, section, error=exc.message, status_code=exc.status_code, **kept
        )
    notice = "Nothing changed." if saved is None else f"Saved as version {saved.number}."
    return redirect_with_notice(request, f"/admin/studies/{name}/design/{slug}", notice)
