"""Admin pages: the list of accounts and new ones (each account's own page: app.web.accounts),
new studies from protocol files, opening and closing studies, unblinding a blinded one."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

from fastapi import File, Form, Request, UploadFile
from fastapi.responses import Response

from app.deps import AdminUser, OneHopRouter, SessionDep
from app.errors import Conflict, InvalidInput, NotFound
from app.i18n.languages import native_name
from app.inputs import STUDY_NAME
from app.protocol import (
    DEFAULT_PROTOCOL,
    MAX_PROTOCOL_BYTES,
    LoadedProtocol,
    Problem,
    ProtocolError,
    parse_protocol,
    shipped_protocol,
    shipped_protocol_files,
)
from app.services import blinding, studies
from app.services.audit import Actor
from app.services.design import study_phases
from app.services.staff import accounts, users
from app.tables import Role, StudyPhase, StudyStatus
from app.web.templating import redirect_with_notice, render

router = OneHopRouter(prefix="/admin", tags=["pages"], include_in_schema=False)


def _users_page(
    request: Request,
    db: SessionDep,
    *,
    error: str = "",
    values: dict[str, str] | None = None,
    status_code: int = 200,
) -> Response:
    return render(
        request,
        "admin_users.html",
        {
            "accounts": accounts.list_accounts(db),
            "roles": list(Role),
            "error": error,
            "values": values or {},
        },
        status_code=status_code,
    )


@router.get("/users")
def user_list(request: Request, db: SessionDep, admin: AdminUser) -> Response:
    """Accounts and a form to add one."""
    return _users_page(request, db)


@router.post("/users")
def create_user(
    request: Request,
    db: SessionDep,
    admin: AdminUser,
    username: Annotated[str, Form(max_length=64)],
    role: Annotated[str, Form(max_length=16)],
    password: Annotated[str, Form(max_length=1024)],
) -> Response:
    """Create an account."""
    try:
        users.create_user(
            db, username=username, role=role, password=password, actor=Actor.of_user(admin)
        )
    except (InvalidInput, Conflict) as exc:
        db.rollback()
        return _users_page(
            request,
            db,
            error=exc.message,
            values={"username": username, "role": role},
            status_code=exc.status_code,
        )
    return redirect_with_notice(request, "/admin/users", f"Created {username.strip().lower()}.")


@dataclass(frozen=True)
class ShippedChoice:
    """A shipped protocol as the New study form offers it."""

    file: str
    title: str
    description: str
    languages: str
    """Their native names, said as a list is ("English and svenska")."""


def _shipped_choices() -> list[ShippedChoice]:
    choices = []
    for file in shipped_protocol_files():
        study = shipped_protocol(file).protocol.study
        names = [native_name(code) for code in study.languages]
        languages = " and ".join([", ".join(names[:-1]), names[-1]] if len(names) > 1 else names)
        choices.append(ShippedChoice(file, study.title, study.description, languages))
    return choices


START_FILE, START_STUDY, START_SHIPPED = "file", "study", "shipped:"
"""What a new study starts from: an uploaded file, a copy of a study's protocol, or
``shipped:<file>``."""


def _new_study_page(
    request: Request,
    db: SessionDep,
    *,
    error: str = "",
    values: dict[str, str] | None = None,
    status_code: int = 200,
) -> Response:
    """The New study form, with the name rule in the server's own words (the browser's "match
    the requested format" does not say what the format is)."""
    values = {
        "name": "",
        "title": "",
        "start": START_SHIPPED + DEFAULT_PROTOCOL,
        "from_study": "",
        "phase": StudyPhase.DRAFT,
        **(values or {}),
    }
    return render(
        request,
        "admin_new_study.html",
        {
            "error": error,
            "values": values,
            "name_rule": STUDY_NAME.sentence,
            "shipped": _shipped_choices(),
            "studies": studies.list_studies(db),
            "start_file": START_FILE,
            "start_study": START_STUDY,
            "start_shipped": START_SHIPPED,
        },
        status_code=status_code,
    )


@router.get("/studies/new")
def new_study_form(request: Request, db: SessionDep, admin: AdminUser) -> Response:
    """Start a study from a shipped protocol, a copy of a study's, or an uploaded file."""
    return _new_study_page(request, db)


def _uploaded_protocol(protocol: UploadFile | None) -> LoadedProtocol:
    """The uploaded protocol file, validated; refusals as :class:`ProtocolError`."""
    if protocol is None or not protocol.filename:
        raise ProtocolError("protocol", [Problem("", "choose a protocol file to upload")])
    raw = protocol.file.read(MAX_PROTOCOL_BYTES + 1)
    if len(raw) > MAX_PROTOCOL_BYTES:
        reason = f"the protocol file is larger than {MAX_PROTOCOL_BYTES // 1024} KiB"
        raise ProtocolError(protocol.filename, [Problem("", reason)])
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        raise ProtocolError(
            protocol.filename, [Problem("", "the protocol file is not UTF-8 text")]
        ) from None
    return parse_protocol(text, source=protocol.filename)


def _starting_protocol(
    db: SessionDep, start: str, from_study: str, protocol: UploadFile | None
) -> tuple[LoadedProtocol, str]:
    """The protocol a new study starts from, and what it was (for the audit log)."""
    if start != START_FILE and protocol is not None and protocol.filename:
        raise InvalidInput(
            "a protocol file was chosen but the study is to start from another protocol: "
            "choose “A protocol file” to use it, or remove the file"
        )
    if start == START_FILE:
        loaded = _uploaded_protocol(protocol)
        return loaded, f"file {protocol.filename if protocol else ''}"
    if start == START_STUDY:
        if not from_study:
            raise InvalidInput("choose the study whose protocol the new one copies")
        return studies.starting_protocol(db, copy_of=from_study)
    if start.startswith(START_SHIPPED):
        return studies.starting_protocol(db, shipped=start.removeprefix(START_SHIPPED))
    raise InvalidInput("choose what the study starts from")


@router.post("/studies")
def create_study(
    request: Request,
    db: SessionDep,
    admin: AdminUser,
    name: Annotated[str, Form(max_length=64)],
    protocol: Annotated[UploadFile | None, File()] = None,
    title: Annotated[str, Form(max_length=400)] = "",
    start: Annotated[str, Form(max_length=200)] = START_FILE,
    from_study: Annotated[str, Form(max_length=64)] = "",
    phase: Annotated[str, Form(max_length=16)] = StudyPhase.LIVE,
) -> Response:
    """Create a study from a shipped protocol, a copy of a study's protocol, or an uploaded
    protocol TOML file (``start``; a client that only uploads a file need not say so)."""
    try:
        loaded, started_from = _starting_protocol(db, start, from_study, protocol)
        studies.create_study(
            db,
            name=name.strip(),
            loaded=loaded,
            actor=Actor.of_user(admin),
            title=title,
            started_from=started_from,
            phase=study_phases.parse_phase(phase),
        )
    except ProtocolError as exc:
        error = str(exc)
    except (InvalidInput, Conflict, NotFound) as exc:
        db.rollback()
        error = exc.message
    else:
        return redirect_with_notice(request, f"/studies/{name.strip()}", "Study created.")
    values = {
        "name": name,
        "title": title,
        "start": start,
        "from_study": from_study,
        "phase": phase,
    }
    return _new_study_page(request, db, error=error, values=values, status_code=422)


@router.post("/studies/{name}/status")
def set_status(
    request: Request,
    db: SessionDep,
    admin: AdminUser,
    name: str,
    status: Annotated[StudyStatus, Form()],
) -> Response:
    """Open or close a study for enrolment."""
    studies.set_study_status(db, name=name, status=status, actor=Actor.of_user(admin))
    return redirect_with_notice(request, f"/studies/{name}", f"Study is now {status.value}.")


@router.post("/studies/{name}/archive")
def set_archived(
    request: Request,
    db: SessionDep,
    admin: AdminUser,
    name: str,
    archived: Annotated[bool, Form()],
) -> Response:
    """Hide a study from the study list and the consoles (the demo, a finished study), or show
    it again; nothing is deleted."""
    study = studies.set_archived(db, name=name, archived=archived, actor=Actor.of_user(admin))
    notice = (
        f"Archived {study.title}: it is hidden from the study list and the consoles."
        if archived
        else f"{study.title} is shown again."
    )
    return redirect_with_notice(request, f"/studies/{name}", notice)


def _unblind_page(
    request: Request, db: SessionDep, name: str, *, error: str = "", status_code: int = 200
) -> Response:
    study = studies.get_study(db, name)
    return render(
        request,
        "admin_study_unblind.html",
        {
            "study": study,
            "blinded": studies.protocol_of(study).study.blinded,
            "active": blinding.unfinished_participants(db, study),
            "error": error,
        },
        status_code=status_code,
    )


@router.get("/studies/{name}/unblind")
def unblind_form(request: Request, db: SessionDep, admin: AdminUser, name: str) -> Response:
    """Say what unblinding shows, to whom, and that it cannot be undone; ask to confirm."""
    return _unblind_page(request, db, name)


@router.post("/studies/{name}/unblind")
def unblind(request: Request, db: SessionDep, admin: AdminUser, name: str) -> Response:
    """Lift the blinding for good (audited); a refusal stays on the confirmation page."""
    try:
        blinding.unblind(db, name=name, actor=Actor.of_user(admin))
    except Conflict as exc:
        db.rollback()
        return _unblind_page(request, db, name, error=exc.message, status_code=exc.status_code)
    return redirect_with_notice(
        request, f"/studies/{name}", "Unblinded: everyone now sees conditions and learners."
    )
