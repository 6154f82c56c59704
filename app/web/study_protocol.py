"""A draft study's protocol in the browser: its text edited and checked as it is typed, saved as
a new version, the last change undone, every version listed (app.services.design.protocol_versions).

The page carries the SHA-256 of the protocol it was drawn with; a save from a page drawn before
someone else's save is refused with what changed, the text as typed kept on the page."""

from __future__ import annotations

from typing import Annotated

from fastapi import Form, Request
from fastapi.responses import Response

from app.deps import AdminUser, OneHopRouter, SessionDep
from app.errors import Conflict, InvalidInput
from app.protocol import MAX_PROTOCOL_BYTES, Problem, ProtocolError
from app.protocol_forms import SECTIONS
from app.services import studies
from app.services.audit import Actor
from app.services.design import protocol_versions
from app.services.design.protocol_versions import EditConflict, NotComparable
from app.tables import StudyPhase
from app.web.protocol_editor import checked_text, typed_text
from app.web.templating import redirect_with_notice, render

router = OneHopRouter(prefix="/admin", tags=["pages"], include_in_schema=False)


def _page(
    request: Request,
    db: SessionDep,
    name: str,
    *,
    text: str | None = None,
    base: str | None = None,
    reason: str = "",
    error: str = "",
    changes: str = "",
    problems: list[Problem] | None = None,
    not_comparable: list[str] | None = None,
    status_code: int = 200,
) -> Response:
    study = studies.get_study(db, name)
    return render(
        request,
        "study_protocol.html",
        {
            "study": study,
            "text": study.protocol_source if text is None else text,
            "base": study.protocol_sha256 if base is None else base,
            "reason": reason,
            "versions": protocol_versions.versions(db, study),
            "frozen": protocol_versions.frozen_because(study),
            "amendment": protocol_versions.is_amendment(study),
            "not_comparable": not_comparable or [],
            "error": error,
            "changes": changes,
            "problems": problems or [],
            "sections": SECTIONS,
        },
        status_code=status_code,
    )


@router.get("/studies/{name}/protocol")
def protocol_page(request: Request, db: SessionDep, admin: AdminUser, name: str) -> Response:
    """The study's protocol: editable while it is a draft, with every version."""
    return _page(request, db, name)


@router.post("/studies/{name}/protocol")
def save(
    request: Request,
    db: SessionDep,
    admin: AdminUser,
    name: str,
    base: Annotated[str, Form(max_length=64)],
    text: Annotated[str, Form(max_length=MAX_PROTOCOL_BYTES)] = "",
    reason: Annotated[str, Form(max_length=protocol_versions.REASON_MAX)] = "",
) -> Response:
    """Save the text as the next version; problems, a frozen study or a newer version keep
    the page with the text as typed."""
    text = typed_text(text)
    loaded, problems = checked_text(text)

    def kept(
        error: str, status_code: int, changes: str = "", not_comparable: list[str] | None = None
    ) -> Response:
        """The page again with everything as typed; after a refused save, to be saved over the
        current version (None: the study's), the changes shown above it."""
        return _page(
            request,
            db,
            name,
            text=text,
            base=None if changes else base,
            reason=reason,
            error=error,
            changes=changes,
            problems=problems,
            not_comparable=not_comparable,
            status_code=status_code,
        )

    if loaded is None:
        return kept("the protocol has problems: see the list beside the text", 422)
    try:
        saved = protocol_versions.save_protocol(
            db,
            name=name,
            loaded=loaded,
            base_sha256=base,
            actor=Actor.of_user(admin),
            reason=reason,
        )
    except EditConflict as exc:
        db.rollback()
        return kept(exc.message, 409, exc.changes)
    except NotComparable as exc:
        db.rollback()
        return kept("this change needs a new study", 409, not_comparable=exc.problems)
    except (InvalidInput, Conflict) as exc:
        db.rollback()
        return kept(exc.message, exc.status_code)
    notice = "Nothing changed." if saved is None else f"Saved as version {saved.number}."
    return redirect_with_notice(request, f"/admin/studies/{name}/protocol", notice)


@router.post("/studies/{name}/protocol/undo")
def undo(
    request: Request,
    db: SessionDep,
    admin: AdminUser,
    name: str,
    base: Annotated[str, Form(max_length=64)],
) -> Response:
    """Save the version before the current one again (audited)."""
    try:
        saved = protocol_versions.undo_last_change(
            db, name=name, base_sha256=base, actor=Actor.of_user(admin)
        )
    except EditConflict as exc:
        db.rollback()
        return _page(request, db, name, error=exc.message, changes=exc.changes, status_code=409)
    except (InvalidInput, Conflict) as exc:
        db.rollback()
        return _page(request, db, name, error=exc.message, status_code=exc.status_code)
    except ProtocolError as exc:  # the earlier text no longer passes (a checkpoint gone)
        db.rollback()
        return _page(request, db, name, problems=exc.problems, status_code=422)
    return redirect_with_notice(
        request, f"/admin/studies/{name}/protocol", f"Undone: saved as version {saved.number}."
    )


@router.post("/studies/{name}/protocol/check")
def check(
    request: Request,
    db: SessionDep,
    admin: AdminUser,
    name: str,
    text: Annotated[str, Form(max_length=MAX_PROTOCOL_BYTES)] = "",
) -> Response:
    """The problems of the text as typed (an htmx fragment); for a live study also what it
    changes against the version in force, as a diff."""
    study = studies.get_study(db, name)
    text = typed_text(text)
    _, problems = checked_text(text)
    return render(
        request,
        "_protocol_problems.html",
        {
            "problems": problems,
            "checked": True,
            "amendment_changes": protocol_versions.amendment_changes(db, study, text),
        },
    )


@router.post("/studies/{name}/split")
def split(
    request: Request,
    db: SessionDep,
    admin: AdminUser,
    name: str,
    text: Annotated[str, Form(max_length=MAX_PROTOCOL_BYTES)],
    new_name: Annotated[str, Form(max_length=64)],
    title: Annotated[str, Form(max_length=400)] = "",
) -> Response:
    """Start a new study (a draft) from a changed protocol that the live study cannot take:
    the split the comparability check asks for. The live study keeps its version."""
    study = studies.get_study(db, name)
    text = typed_text(text)
    loaded, problems = checked_text(text)
    if loaded is None:
        return _page(request, db, name, text=text, problems=problems, status_code=422)
    number = protocol_versions.current_number(db, study)
    try:
        studies.create_study(
            db,
            name=new_name.strip(),
            loaded=loaded,
            actor=Actor.of_user(admin),
            title=title,
            started_from=f"split from study {study.name} version {number}",
            phase=StudyPhase.DRAFT,
        )
    except (InvalidInput, Conflict) as exc:
        db.rollback()
        return _page(
            request,
            db,
            name,
            text=text,
            error=f"the new study was not created: {exc.message}",
            status_code=exc.status_code,
        )
    return redirect_with_notice(
        request,
        f"/admin/studies/{new_name.strip()}/design/study",
        f"Started {new_name.strip()} from the changed protocol, as a draft; "
        f"{study.name} keeps version {number}.",
    )
