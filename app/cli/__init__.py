"""The ``trustlab`` command: set-up, serving, accounts, studies, enrolment and more.

Every sub-command reports a mistake the user can fix as one line ``error: …`` on stderr with a
non-zero exit status (1: refused by the current state, 2: bad input), never a traceback.
"""

from __future__ import annotations

import gc
import os
import threading

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
    online,
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
online.register(cli)


STARTUP_SECONDS = 1.0
"""How long a command runs with the garbage collector paused (see :func:`pause_collector`)."""


def pause_collector(seconds: float = STARTUP_SECONDS) -> threading.Timer:
    """Pause the cyclic garbage collector for a command's first ``seconds``; the timer that
    resumes it.

    What a command allocates first is the modules it imports (SQLAlchemy, pandas, the tables),
    none of it garbage, and the collections they set off were a tenth of a short command's time
    (bench/cli.py). A command that runs longer (serve, bots, a training) has it back after
    that; one that ends sooner never needed it. A process forked meanwhile resumes it at once:
    the timer's thread is not forked with it."""
    gc.disable()
    resume = threading.Timer(seconds, gc.enable)
    resume.daemon = True
    resume.start()
    return resume


os.register_at_fork(after_in_child=gc.enable)


def main() -> None:
    """Console-script entry point."""
    pause_collector()
    cli()
