"""The ``trustlab`` command: set-up, serving, accounts, studies, enrolment and more.

Every sub-command reports a mistake the user can fix as one line ``error: …`` on stderr with a
non-zero exit status (1: refused by the current state, 2: bad input), never a traceback.
"""

from __future__ import annotations

import typer

from app.cli import (
    accounts,
    admin,
    analysis,
    bridge,
    consent,
    engine,
    exports,
    languages,
    mixed,
    population,
    power,
    prereg,
    retention,
    robot,
    runtime,
    speech,
)
from app.cli.errors import ErrorsAsMessages

cli = typer.Typer(
    name="trustlab",
    help="Run adaptive-robot trust studies.",
    cls=ErrorsAsMessages,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
)
admin.register(cli)
consent.register(cli)
accounts.register(cli)
runtime.register(cli)
robot.register(cli)
bridge.register(cli)
analysis.register(cli)
mixed.register(cli)
power.register(cli)
prereg.register(cli)
exports.register(cli)
engine.register(cli)
population.register(cli)
speech.register(cli)
languages.register(cli)
retention.register(cli)


def main() -> None:
    """Console-script entry point."""
    cli()
