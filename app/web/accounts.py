"""Account pages: an admin's page per account (role, password, disable or enable, unlock) and
every user's own page (change their password).

Accounts are named by username in URLs (exactly: app.services.staff.users.named). Every change goes
through app.services.staff.accounts, which the command line shares, so the rules (the last active
admin stays, disabling ends sessions at once) and the audit log are the same. Changes that end
someone's sign-ins are made from a page of their own that says so (disabling asks "Disable ada?"
first), as plain forms: a refusal is a page with a 4xx status, which a browser shows (htmx would not
swap it).
"""

from __future__ import annotations

from typing import Annotated

from fastapi import Form, Request
from fastapi.responses import Response

from app.deps import AdminUser, CurrentLogin, DatabaseDep, OneHopRouter, SessionDep
from app.errors import Conflict, InvalidInput, PermissionDenied, TooManyAttempts, TrustlabError
from app.services.audit import Actor
from app.services.privacy import sites
from app.services.staff import accounts, users
from app.tables import Role
from app.web.templating import redirect_with_notice, render

router = OneHopRouter(tags=["pages"], include_in_schema=False)

PasswordField = Annotated[str, Form(max_length=1024)]
WRONG_CURRENT_PASSWORD = "Your current password is not right; nothing was changed."


def _account_page(
    request: Request, db: SessionDep, username: str, *, error: str = "", status_code: int = 200
) -> Response:
    return render(
        request,
        "admin_user.html",
        {
            "account": accounts.get_account(db, username),
            "roles": list(Role),
            "error": error,
            "declared_sites": sites.declared_anywhere(db),
        },
        status_code=status_code,
    )


def _refused(request: Request, db: SessionDep, username: str, exc: TrustlabError) -> Response:
    """The account page again, saying why the change was refused (nothing was written)."""
    db.rollback()
    return _account_page(request, db, username, error=exc.message, status_code=exc.status_code)


def _done(request: Request, username: str, notice: str) -> Response:
    return redirect_with_notice(request, f"/admin/users/{username.lower()}", notice)


def _sessions(count: int) -> str:
    return f"{count} sign-in{'' if count == 1 else 's'} ended"


@router.get("/admin/users/{username}")
def account_page(request: Request, db: SessionDep, admin: AdminUser, username: str) -> Response:
    """One account: its state and the changes an admin can make."""
    return _account_page(request, db, username)


@router.get("/admin/users/{username}/disable")
def disable_form(request: Request, db: SessionDep, admin: AdminUser, username: str) -> Response:
    """Ask for confirmation before disabling an account."""
    return render(
        request, "admin_user_disable.html", {"account": accounts.get_account(db, username)}
    )


@router.post("/admin/users/{username}/disable")
def disable(request: Request, db: SessionDep, admin: AdminUser, username: str) -> Response:
    """Disable an account; its sign-ins end at once."""
    try:
        ended = accounts.disable_user(db, username=username, actor=Actor.of_user(admin))
    except (Conflict, PermissionDenied) as exc:
        return _refused(request, db, username, exc)
    return _done(request, username, f"Disabled {username.lower()} ({_sessions(ended)}).")


@router.post("/admin/users/{username}/enable")
def enable(request: Request, db: SessionDep, admin: AdminUser, username: str) -> Response:
    """Let a disabled account sign in again."""
    try:
        accounts.enable_user(db, username=username, actor=Actor.of_user(admin))
    except (Conflict, PermissionDenied) as exc:
        return _refused(request, db, username, exc)
    return _done(request, username, f"Enabled {username.lower()}.")


@router.post("/admin/users/{username}/role")
def set_role(
    request: Request,
    db: SessionDep,
    admin: AdminUser,
    username: str,
    role: Annotated[Role, Form()],
) -> Response:
    """Give an account another role (it applies to the account's next request)."""
    try:
        accounts.set_role(db, username=username, role=role, actor=Actor.of_user(admin))
    except (Conflict, PermissionDenied) as exc:
        return _refused(request, db, username, exc)
    notice = f"{username.lower()} is now {role.value}."
    if username.lower() == admin.username and role != Role.ADMIN:
        return redirect_with_notice(request, "/", notice)  # no longer allowed on admin pages
    return _done(request, username, notice)


@router.post("/admin/users/{username}/sites")
def set_sites(
    request: Request,
    db: SessionDep,
    admin: AdminUser,
    username: str,
    site: Annotated[list[str] | None, Form(max_length=40)] = None,
    every: Annotated[bool, Form()] = False,
) -> Response:
    """Limit an experimenter's or analyst's account to some sites, or lift the limit."""
    try:
        user = sites.set_user_sites(
            db,
            username=username,
            sites=None if every else (site or []),
            actor=Actor.of_user(admin),
        )
    except (Conflict, InvalidInput, PermissionDenied) as exc:
        return _refused(request, db, username, exc)
    return _done(request, username, f"{user.username} now sees {sites.describe(user.sites)}.")


def _password_page(
    request: Request, db: SessionDep, username: str, *, error: str = "", status_code: int = 200
) -> Response:
    return render(
        request,
        "admin_user_password.html",
        {"account": accounts.get_account(db, username), "error": error},
        status_code=status_code,
    )


@router.get("/admin/users/{username}/password")
def password_form(request: Request, db: SessionDep, admin: AdminUser, username: str) -> Response:
    """The form to reset an account's password, saying that its sign-ins end."""
    return _password_page(request, db, username)


@router.post("/admin/users/{username}/password")
def set_password(
    request: Request,
    db: SessionDep,
    login: CurrentLogin,
    admin: AdminUser,
    username: str,
    password: PasswordField,
    confirm: PasswordField,
) -> Response:
    """Set an account's password (a reset); its other sign-ins end."""
    try:
        if password != confirm:
            raise InvalidInput("the two new passwords differ")
        ended = accounts.set_password(
            db,
            username=username,
            password=password,
            actor=Actor.of_user(admin),
            keep_login=login.id,
        )
    except (InvalidInput, PermissionDenied) as exc:
        db.rollback()
        return _password_page(request, db, username, error=exc.message, status_code=exc.status_code)
    return _done(
        request, username, f"New password set for {username.lower()} ({_sessions(ended)})."
    )


@router.post("/admin/users/{username}/unlock")
def unlock(request: Request, db: SessionDep, admin: AdminUser, username: str) -> Response:
    """End the account's lockout after failed sign-ins."""
    try:
        cleared = accounts.unlock_user(db, username=username, actor=Actor.of_user(admin))
    except PermissionDenied as exc:
        return _refused(request, db, username, exc)
    return _done(
        request, username, f"Unlocked {username.lower()} ({cleared} failed sign-ins cleared)."
    )


def _own_page(request: Request, *, error: str = "", status_code: int = 200) -> Response:
    return render(request, "account.html", {"error": error}, status_code=status_code)


@router.get("/account")
def own_account(request: Request, login: CurrentLogin) -> Response:
    """The signed-in user's own account: change the password."""
    return _own_page(request)


@router.post("/account/password")
def change_password(
    request: Request,
    db: SessionDep,
    database: DatabaseDep,
    login: CurrentLogin,
    current_password: PasswordField,
    new_password: PasswordField,
    confirm: PasswordField,
) -> Response:
    """Change one's own password (the current one is checked, and counts towards the lockout
    like a sign-in); one's other sign-ins end."""
    try:
        if new_password != confirm:
            raise InvalidInput("the two new passwords differ")
        new_hash = accounts.new_password_hash(new_password)
        with database.writing() as counting:
            check = users.begin_password_check(
                counting,
                username=login.user.username,
                client_address=request.client.host if request.client else "",
                failed_action=users.PASSWORD_CHANGE_FAILED,
            )
    except (InvalidInput, TooManyAttempts) as exc:
        return _own_page(request, error=exc.message, status_code=exc.status_code)
    changed = accounts.change_own_password(
        db, login=login, check=check, current_password=current_password, new_hash=new_hash
    )
    if changed is users.Refusal.DISABLED:
        return _own_page(request, error="This account has been disabled.", status_code=403)
    if isinstance(changed, users.Refusal):
        return _own_page(request, error=WRONG_CURRENT_PASSWORD, status_code=403)
    return redirect_with_notice(
        request, "/account", f"Password changed ({_sessions(changed)} elsewhere)."
    )
