"""``trustlab user …``: dashboard accounts from the server's command line.

The command line acts as an admin (app.services.audit.Actor.command_line) and shares every rule
with the admin pages through app.services.staff.accounts: the last active admin stays, disabling
ends sessions, and every change is audited. It is also the way back in when no admin can sign in:
``trustlab user unlock NAME`` ends a lockout after failed sign-ins, ``set-password`` resets a
forgotten password. Passwords are never taken from the command's arguments (they would stay in
the shell's history and show in the process list): they come from a hidden prompt on a terminal,
or from standard input with ``--password-stdin``.
"""

from __future__ import annotations

import sys
from typing import TYPE_CHECKING, Annotated

import typer

from app.cli.common import JsonFlag, emit_json, open_database, require_current_schema
from app.errors import InvalidInput
from app.roles import Role

if TYPE_CHECKING:
    from app.db import Database


user_cli = typer.Typer(help="Dashboard accounts.", no_args_is_help=True)

NameArgument = Annotated[str, typer.Argument(help="The account's username.")]
PasswordStdin = Annotated[
    bool,
    typer.Option(
        "--password-stdin", help="Read the password from standard input (one line) instead."
    ),
]


def register(cli: typer.Typer) -> None:
    """Attach these commands to the top-level ``trustlab`` command."""
    cli.add_typer(user_cli, name="user")


def on_terminal() -> bool:
    """Whether a person at a terminal can be asked for a password."""
    return sys.stdin.isatty()


def read_password(password_stdin: bool) -> str:
    """The new password: one line of standard input, or typed twice at a hidden prompt."""
    if password_stdin:
        return sys.stdin.readline().rstrip("\r\n")
    if not on_terminal():
        raise InvalidInput(
            "give the password on standard input with --password-stdin "
            "(or run the command on a terminal to be asked for it)"
        )
    password: str = typer.prompt("Password", hide_input=True, confirmation_prompt=True)
    return password


def _database() -> Database:
    from app.settings import Settings

    database = open_database(Settings())
    require_current_schema(database)
    return database


def _sessions(count: int) -> str:
    return f"{count} login session{'' if count == 1 else 's'} ended"


@user_cli.command("create")
def user_create(
    username: Annotated[str, typer.Option(help="Login name (case-insensitive).")],
    role: Annotated[Role, typer.Option(help="admin, experimenter or analyst.")],
    password_stdin: PasswordStdin = False,
) -> None:
    """Create a dashboard account."""
    from app.services.audit import Actor
    from app.services.staff import users

    password = read_password(password_stdin)
    with _database().writing() as db:
        user = users.create_user(
            db, username=username, role=role, password=password, actor=Actor.command_line()
        )
        typer.echo(f"created {user.role} {user.username!r}")


@user_cli.command("list")
def user_list(as_json: JsonFlag = False) -> None:
    """List the accounts: role, whether active, any lockout, the last sign-in."""
    from app.services.privacy import sites
    from app.services.staff import accounts

    with _database().read_session() as db:
        rows = accounts.list_accounts(db)
    if as_json:
        emit_json(
            {
                "users": [
                    {
                        "username": a.username,
                        "role": a.role,
                        "active": a.is_active,
                        "locked_until": a.locked_until.isoformat() if a.locked_until else None,
                        "last_login_at": a.last_login_at.isoformat() if a.last_login_at else None,
                        "sites": a.sites,
                    }
                    for a in rows
                ]
            }
        )
        return
    for a in rows:
        status = "active" if a.is_active else "disabled"
        if a.locked_until:
            status += f", locked until {a.locked_until:%H:%M} UTC"
        last = f"{a.last_login_at:%Y-%m-%d %H:%M} UTC" if a.last_login_at else "never signed in"
        limit = f"  ({sites.describe(a.sites)} only)" if a.sites is not None else ""
        typer.echo(f"{a.username:<24} {a.role:<13} {status:<32} {last}{limit}")


@user_cli.command("disable")
def user_disable(username: NameArgument) -> None:
    """Stop an account from signing in and end its login sessions at once."""
    from app.services.audit import Actor
    from app.services.staff import accounts

    with _database().writing() as db:
        ended = accounts.disable_user(db, username=username, actor=Actor.command_line())
    typer.echo(f"disabled {username.lower()!r} ({_sessions(ended)})")


@user_cli.command("enable")
def user_enable(username: NameArgument) -> None:
    """Let a disabled account sign in again."""
    from app.services.audit import Actor
    from app.services.staff import accounts

    with _database().writing() as db:
        accounts.enable_user(db, username=username, actor=Actor.command_line())
    typer.echo(f"enabled {username.lower()!r}")


@user_cli.command("set-password")
def user_set_password(username: NameArgument, password_stdin: PasswordStdin = False) -> None:
    """Give an account a new password and end its login sessions."""
    from app.services.audit import Actor
    from app.services.staff import accounts

    password = read_password(password_stdin)
    with _database().writing() as db:
        ended = accounts.set_password(
            db, username=username, password=password, actor=Actor.command_line()
        )
    typer.echo(f"set a new password for {username.lower()!r} ({_sessions(ended)})")


@user_cli.command("set-role")
def user_set_role(
    username: NameArgument,
    role: Annotated[Role, typer.Argument(help="admin, experimenter or analyst.")],
) -> None:
    """Give an account another role (it applies to its next request)."""
    from app.services.audit import Actor
    from app.services.staff import accounts

    with _database().writing() as db:
        old = accounts.set_role(db, username=username, role=role, actor=Actor.command_line())
    typer.echo(f"{username.lower()!r} is now {role.value} (was {old})")


@user_cli.command("unlock")
def user_unlock(username: NameArgument) -> None:
    """End a lockout after failed sign-ins now (the failures stay in the record)."""
    from app.services.audit import Actor
    from app.services.staff import accounts

    with _database().writing() as db:
        cleared = accounts.unlock_user(db, username=username, actor=Actor.command_line())
    if cleared:
        typer.echo(
            f"unlocked {username.lower()!r}: {cleared} recent failed "
            f"sign-in{'' if cleared == 1 else 's'} no longer count"
        )
    else:
        typer.echo(f"{username.lower()!r} had no recent failed sign-ins; nothing to unlock")


@user_cli.command("sites")
def user_sites(
    username: NameArgument,
    site: Annotated[
        list[str] | None,
        typer.Option(
            "--site",
            help="A site the account is limited to (repeatable; a site some study declares).",
        ),
    ] = None,
    every: Annotated[
        bool, typer.Option("--all", help="Lift the limit: the account sees every site.")
    ] = False,
) -> None:
    """Limit an experimenter's or analyst's account to some sites' participants, or lift it."""
    from app.services.audit import Actor
    from app.services.privacy import sites

    if every == bool(site):
        raise InvalidInput("give the sites (--site NAME, repeatable) or --all, not both")
    with _database().writing() as db:
        user = sites.set_user_sites(
            db, username=username, sites=None if every else site, actor=Actor.command_line()
        )
        typer.echo(f"{user.username!r} now sees {sites.describe(user.sites)}")
