"""Commands import only what they use (issue 49 item 1; docs/development.md, "What a command
may import").

A lab scripts these commands, so each one's start-up is paid many times over: a command that
builds no learner must not load torch, one that analyses nothing must not load the statistics
stack, and ``--help`` and the commands that need no database must not load even the database
layer. One fresh interpreter runs the whole table below through typer's CliRunner, in order,
and reports after each command which of its forbidden packages ``sys.modules`` holds. Packages
only accumulate in one process, so each row forbids no more than the row before it (checked
too): a row can then never pass because an earlier one already imported what it must not.
"""

from __future__ import annotations

import itertools
import json
import subprocess
import sys
from pathlib import Path

from app.settings import REPO_ROOT
from tests.conftest import sqlite_only

LEARNERS = frozenset({"torch"})
STATISTICS = frozenset({"scipy", "pingouin", "statsmodels", "plotly"})
DATA_FRAMES = frozenset({"pandas"})
WEB = frozenset({"fastapi", "uvicorn", "jinja2", "httpx"})
MIGRATIONS = frozenset({"alembic"})
POSTGRES_DRIVER = frozenset({"psycopg"})
DATABASE = frozenset({"sqlalchemy", "starlette", "argon2", "pydantic_settings"})
SPSS_WRITER = frozenset({"pyreadstat"})

ENGINE = frozenset({"numpy"})
NO_DATABASE = (
    LEARNERS
    | STATISTICS
    | DATA_FRAMES
    | WEB
    | MIGRATIONS
    | POSTGRES_DRIVER
    | DATABASE
    | ENGINE
    | SPSS_WRITER
)
"""``--help`` and the commands that need no database: typer and the command's own modules."""
OPENS_DATABASE = (
    LEARNERS | STATISTICS | DATA_FRAMES | WEB | MIGRATIONS | POSTGRES_DRIVER | SPSS_WRITER
)
"""Commands that read or write the (SQLite) database but analyse nothing: no Alembic either, the
schema check reads the revisions itself (app.schema)."""
NO_ENGINE = OPENS_DATABASE | ENGINE
"""Of those, the ones that touch no learner and no participant's data: not even numpy."""
TABLE_EXPORTS = LEARNERS | STATISTICS | WEB | MIGRATIONS | POSTGRES_DRIVER | SPSS_WRITER
"""Exports of the stored tables (no fitted model): the analysis package's tables and scoring on
pandas, which builds the dataset; no SciPy, statsmodels, pingouin or Plotly."""
EXPORTS = TABLE_EXPORTS - SPSS_WRITER
"""The SPSS file: the same, with its writer."""
ANALYTIC = NO_DATABASE
"""The analytic power questions: pure Python (analysis.power's F distributions, the number
formatting of analysis.apa_numbers), no SciPy, pandas or numpy."""

PASSWORD = "a long enough password"

Row = tuple[list[str], frozenset[str], str | None]
"""The command's words, the packages it must not import, its standard input."""


def chains(tmp: Path) -> list[list[Row]]:
    """The commands that build no learner, in chains run one after another in one process each:
    in a chain, each row forbids at most what the row before it forbids."""
    protocol = str(REPO_ROOT / "app" / "protocols" / "fast_adaptation_trust.toml")
    user = ["user", "create", "--username", "ann", "--role", "analyst", "--password-stdin"]
    tables = ("long-csv", "wide-csv", "steps-csv", "codebook-csv", "codebook-json")
    exports: list[Row] = [
        (
            ["export", "--study", "default", "--format", kind, "--out", str(tmp / kind)],
            EXPORTS if kind == "sav" else TABLE_EXPORTS,
            None,
        )
        for kind in (*tables, "adaptation-csv", "sav")
    ]
    power = ["power", "--effect", "between", "--groups", "2", "--sessions", "4", "--f", "0.25"]
    return [
        [
            (["--help"], NO_DATABASE, None),
            (["study", "--help"], NO_DATABASE, None),
            (["user", "create", "--help"], NO_DATABASE, None),
            (["bridge", "naoqi", "--help"], NO_DATABASE, None),
            (["languages", "list"], NO_DATABASE, None),
            (["languages", "check", "sv"], NO_DATABASE, None),
            (["db", "current"], NO_ENGINE, None),
            (["study", "list"], NO_ENGINE, None),
            (["station", "create", "lab-1"], NO_ENGINE, None),
            (["station", "list"], NO_ENGINE, None),
            (["device", "create", "--station", "lab-1"], NO_ENGINE, None),
            (user, NO_ENGINE, PASSWORD + "\n"),
            (["user", "list"], NO_ENGINE, None),
            (["user", "disable", "ann"], NO_ENGINE, None),
            (["study", "create", "--protocol", protocol, "--name", "two"], OPENS_DATABASE, None),
            (["participant", "enroll", "--study", "default"], OPENS_DATABASE, None),
            (["participant", "enroll", "--study", "two", "--code", "P9"], OPENS_DATABASE, None),
            (["participant", "withdraw", "--study", "two", "--code", "P9"], OPENS_DATABASE, None),
            (["retention", "run"], OPENS_DATABASE, None),
            *exports,
        ],
        [
            ([*power, "--rho", "0.5", "--target-power", "0.8"], ANALYTIC, None),
            ([*power, "--rho", "0.5", "--n", "24", "--json"], ANALYTIC, None),
            (
                [*power[:-2], "--n", "24", "--target-power", "0.8", "--convention", "spss"],
                ANALYTIC,
                None,
            ),
        ],
    ]


PROGRAM = """
import json, sys
from typer.testing import CliRunner
from app.cli import cli

rows, env = json.loads(sys.argv[1]), json.loads(sys.argv[2])
found = []
for words, forbidden, stdin in rows:
    result = CliRunner().invoke(cli, words, input=stdin, env=env)
    if result.exit_code != 0:
        sys.exit(f"trustlab {' '.join(words)} exited {result.exit_code}: {result.output}")
    found.append(sorted(name for name in forbidden if name in sys.modules))
print(json.dumps(found))
"""


def test_each_row_forbids_no_more_than_the_row_before(tmp_path: Path) -> None:
    for chain in chains(tmp_path):
        for (before, wider, _), (words, narrower, _) in itertools.pairwise(chain):
            assert narrower <= wider, f"{words} forbids {narrower - wider}, which {before} allows"


@sqlite_only("what is checked is which packages a command imports")
def test_commands_import_only_what_they_use(
    database_url: str, study_name: str, tmp_path: Path
) -> None:
    env = {"TRUSTLAB_DATABASE_URL": database_url, "TRUSTLAB_VAR_DIR": str(tmp_path / "var")}
    wrong = {}
    for chain in chains(tmp_path):
        rows = json.dumps([(words, sorted(forbidden), stdin) for words, forbidden, stdin in chain])
        completed = subprocess.run(
            [sys.executable, "-c", PROGRAM, rows, json.dumps(env)],
            capture_output=True,
            text=True,
            cwd=REPO_ROOT,
            timeout=300,
            check=False,
        )
        assert completed.returncode == 0, completed.stderr
        found = json.loads(completed.stdout.splitlines()[-1])
        for (words, _, _), modules in zip(chain, found, strict=True):
            if modules:
                wrong[" ".join(words)] = modules
    assert not wrong, "commands import what they do not use:\n" + "\n".join(
        f"  trustlab {words}: {', '.join(modules)}" for words, modules in wrong.items()
    )


def test_a_command_starts_with_the_collector_paused_and_gets_it_back() -> None:
    """Its imports allocate nothing that is garbage (bench/cli.py: a tenth of a short
    command's time went to collections); the collector comes back for whatever runs longer."""
    import gc

    from app.cli import pause_collector

    assert gc.isenabled()
    try:
        resume = pause_collector(0.01)
        assert not gc.isenabled()
        resume.join()
        assert gc.isenabled()
    finally:
        gc.enable()
