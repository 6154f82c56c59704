"""Admin pages: the list of accounts and new ones (each account's own page: app.web.accounts),
new studies from protocol files, opening and closing studies, unblinding a blinded one."""

from __future__ import annotations

from typing import Annotated

from fastapi import File, Form, Request, UploadFile
from fastapi.responses import Response

from app.deps import AdminUser, OneHopRouter, SessionDep
from app.errors import Conflict, InvalidInput
from app.inputs import STUDY_NAME
from app.protocol import ProtocolError, parse_protocol
from app.services import blinding, studies
from app.services.audit import Actor
from app.services.staff import accounts, users
from app.tables import Role, StudyStatus
from app.web.templating import redirect_with_notice, render

router = OneHopRouter(prefix="/admin", tags=["pages"], include_in_schema=False)

MAX_PROTOCOL_BYTES = 512 * 1024


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


def _new_study_form(error: str, name: str, title: str) -> dict[str, str]:
    """The New study form's values, with the name rule in the server's own words (the browser's
    "match the requested format" does not say what the format is)."""
    return {"error": error, "name": name, "title": title, "name_rule": STUDY_NAME.sentence}


@router.get("/studies/new")
def new_study_form(request: Request, admin: AdminUser) -> Response:
    """Upload a protocol file to create a study."""
    return render(request, "admin_new_study.html", _new_study_form("", "", ""))


@router.post("/studies")
def create_study(
    request: Request,
    db: SessionDep,
    admin: AdminUser,
    name: Annotated[str, Form(max_length=64)],
    protocol: Annotated[UploadFile, File()],
    title: Annotated[str, Form(max_length=400)] = "",
) -> Response:
    """Create a study from an uploaded protocol TOML file."""
    raw = protocol.file.read(MAX_PROTOCOL_BYTES + 1)
    error = ""
    if len(raw) > MAX_PROTOCOL_BYTES:
        error = f"the protocol file is larger than {MAX_PROTOCOL_BYTES // 1024} KiB"
    else:
        try:
            loaded = parse_protocol(raw.decode("utf-8"), source=protocol.filename or "protocol")
        except UnicodeDecodeError:
            error = "the protocol file is not UTF-8 text"
        except ProtocolError as exc:
            error = str(exc)
    if not error:
        try:
            studies.create_study(
                db, name=name.strip(), loaded=loaded, actor=Actor.of_user(admin), title=title
            )
        except (InvalidInput, Conflict) as exc:
            db.rollback()
            error = exc.message
    if error:
        return render(
            request,
            "admin_new_study.html",
            _new_study_form(error, name, title),
            status_code=422,
        )
    return redirect_with_notice(request, f"/studies/{name.strip()}", "Study created.")


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
