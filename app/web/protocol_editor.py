"""A protocol's text, edited in the browser and checked as it is typed, to start a study from.

The text starts as a shipped protocol's or a study's (byte for byte) and is checked by the same
rules as study creation (app.protocol.parse_protocol), every problem at once with its key path,
while it is typed (htmx posts it to the check route, which answers with the problems only).
Creating the study stores the text as typed, comments and all.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import Form, Request
from fastapi.responses import Response

from app.deps import AdminUser, OneHopRouter, SessionDep
from app.errors import Conflict, InvalidInput, NotFound
from app.inputs import STUDY_NAME
from app.protocol import (
    DEFAULT_PROTOCOL,
    MAX_PROTOCOL_BYTES,
    LoadedProtocol,
    Problem,
    ProtocolError,
    parse_protocol,
)
from app.services import studies
from app.services.audit import Actor
from app.services.design import study_phases
from app.tables import StudyPhase
from app.web.templating import redirect_with_notice, render

router = OneHopRouter(prefix="/admin", tags=["pages"], include_in_schema=False)

SOURCE = "protocol"
"""How the problems name the text (``protocol: schedule.sessions: …``)."""


def _origin_text(db: SessionDep, start: str) -> tuple[str, str]:
    """The text a ``start`` (``shipped:FILE`` or ``study:NAME``) begins with, and its name."""
    kind, _, name = start.partition(":")
    if kind not in ("shipped", "study"):
        raise NotFound(f"no protocol to start from called {start!r} (shipped:FILE or study:NAME)")
    try:
        loaded, origin = studies.starting_protocol(
            db, **({"shipped": name} if kind == "shipped" else {"copy_of": name})
        )
    except ProtocolError as exc:  # no shipped protocol of that name
        raise NotFound(str(exc)) from None
    return loaded.source_text, origin


def typed_text(text: str) -> str:
    """A protocol's text as typed into a text area: browsers send its line breaks as CRLF,
    whatever the text had, so they are put back to the LF the protocols are written with (an
    unchanged text then keeps its SHA-256)."""
    return text.replace("\r\n", "\n")


def checked_text(text: str) -> tuple[LoadedProtocol | None, list[Problem]]:
    """The text parsed as a protocol, or every problem it has (the study's own protocol editor,
    app.web.study_protocol, checks its saves with this too)."""
    try:
        return parse_protocol(text, source=SOURCE), []
    except ProtocolError as exc:
        return None, exc.problems


def _editor(
    request: Request,
    *,
    text: str,
    start: str,
    origin: str,
    name: str = "",
    title: str = "",
    phase: str = StudyPhase.DRAFT,
    error: str = "",
    problems: list[Problem] | None = None,
    status_code: int = 200,
) -> Response:
    return render(
        request,
        "protocol_editor.html",
        {
            "text": text,
            "start": start,
            "origin": origin,
            "name": name,
            "title": title,
            "phase": phase,
            "error": error,
            "problems": problems or [],
            "name_rule": STUDY_NAME.sentence,
        },
        status_code=status_code,
    )


@router.get("/protocols/edit")
def edit_protocol(
    request: Request, db: SessionDep, admin: AdminUser, start: str = f"shipped:{DEFAULT_PROTOCOL}"
) -> Response:
    """A protocol's text to edit before a study starts from it."""
    text, origin = _origin_text(db, start)
    return _editor(request, text=text, start=start, origin=origin)


@router.post("/protocols/check")
def check_protocol(
    request: Request,
    admin: AdminUser,
    text: Annotated[str, Form(max_length=MAX_PROTOCOL_BYTES)] = "",
) -> Response:
    """The problems of the text as typed (an htmx fragment): every one at once, with its key."""
    _, problems = checked_text(typed_text(text))
    return render(request, "_protocol_problems.html", {"problems": problems, "checked": True})


@router.post("/protocols/edit")
def create_from_text(
    request: Request,
    db: SessionDep,
    admin: AdminUser,
    name: Annotated[str, Form(max_length=64)],
    start: Annotated[str, Form(max_length=200)],
    text: Annotated[str, Form(max_length=MAX_PROTOCOL_BYTES)] = "",
    title: Annotated[str, Form(max_length=400)] = "",
    phase: Annotated[str, Form(max_length=16)] = StudyPhase.LIVE,
) -> Response:
    """Create a study from the text as typed; its problems, or a name in use, keep the page.
    The audit log says what the text started as, and whether it was changed."""
    original, origin = _origin_text(db, start)
    text = typed_text(text)
    loaded, problems = checked_text(text)
    if loaded is not None:
        try:
            studies.create_study(
                db,
                name=name.strip(),
                loaded=loaded,
                actor=Actor.of_user(admin),
                title=title,
                started_from=origin if text == original else f"text edited from {origin}",
                phase=study_phases.parse_phase(phase),
            )
        except (InvalidInput, Conflict) as exc:
            db.rollback()
            error = exc.message
        else:
            return redirect_with_notice(request, f"/studies/{name.strip()}", "Study created.")
    else:
        error = "the protocol has problems: see the list beside the text"
    return _editor(
        request,
        text=text,
        start=start,
        origin=origin,
        name=name,
        title=title,
        phase=phase,
        error=error,
        problems=problems,
        status_code=422,
    )
