"""The ``trustlab`` command: init, db, user, study and participant sub-commands."""

from __future__ import annotations

import hashlib
import json
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import typer
from typer.testing import CliRunner

from analysis.exports import EXPORT_FORMATS
from app import demo, schema
from app.cli import cli
from app.db import Database
from app.services import studies
from app.services.staff import users
from app.settings import REPO_ROOT, Settings
from tests.conftest import protocol_text, sqlite_only

runner = CliRunner()


def run(
    database_url: str, *args: str, stdin: str | None = None, var_dir: Path | None = None
) -> tuple[int, str, str]:
    env = {"TRUSTLAB_DATABASE_URL": database_url}
    if var_dir is not None:
        env["TRUSTLAB_VAR_DIR"] = str(var_dir)
    result = runner.invoke(cli, list(args), input=stdin, env=env)
    if result.exception and not isinstance(result.exception, SystemExit):
        raise result.exception
    return result.exit_code, result.stdout, result.stderr


def test_init_migrates_creates_default_study_and_admin_once(
    blank_database_url: str, tmp_path: Path
) -> None:
    code, out, _ = run(blank_database_url, "init", var_dir=tmp_path)
    assert code == 0
    assert f"schema at {schema.head_revision()} (was empty)" in out
    assert "created the default study 'default'" in out
    assert "created the admin account 'admin'" in out
    assert "created the demo study 'demo'" in out
    plan = demo.pending_demo(Settings(var_dir=tmp_path, database_url=blank_database_url))
    assert plan is not None and plan.study == "demo"
    assert (tmp_path / demo.PLAN_FILE).stat().st_mode & 0o077 == 0, "the plan holds a password"
    password = next(line.split(": ", 1)[1] for line in out.splitlines() if "password:" in line)
    assert "password:" in out.splitlines()[-2], "the password comes last, not scrolled away"
    database = Database(blank_database_url)
    with database.read_session() as db:
        assert users.authenticate(db, username="admin", password=password) is not None
    database.dispose()
    code, out, _ = run(blank_database_url, "init", var_dir=tmp_path)
    assert code == 0
    assert "password" not in out and "created" not in out


def test_init_without_demo(blank_database_url: str, tmp_path: Path) -> None:
    code, out, _ = run(blank_database_url, "init", "--no-demo", var_dir=tmp_path)
    assert code == 0 and "demo study" not in out
    assert not (tmp_path / demo.PLAN_FILE).exists()


def test_db_commands(blank_database_url: str) -> None:
    assert run(blank_database_url, "db", "current")[1].startswith("base (empty) (behind")
    head = schema.head_revision()
    assert run(blank_database_url, "db", "upgrade")[1].strip() == f"schema at {head}"
    assert run(blank_database_url, "db", "current")[1].strip() == f"{head} (up to date)"
    assert run(blank_database_url, "db", "downgrade", "base")[1].strip() == (
        "schema at base (empty)"
    )


def test_commands_refuse_an_unmigrated_database(blank_database_url: str) -> None:
    code, _, err = run(blank_database_url, "study", "list")
    assert code == 2
    assert "run `trustlab db upgrade`" in err


def test_user_create_reads_the_password_from_stdin(database_url: str) -> None:
    code, out, _ = run(
        database_url,
        "user",
        "create",
        "--username",
        "Grace",
        "--role",
        "analyst",
        "--password-stdin",
        stdin="a long enough password\n",
    )
    assert (code, out.strip()) == (0, "created analyst 'grace'")
    code, _, err = run(
        database_url,
        "user",
        "create",
        "--username",
        "grace",
        "--role",
        "analyst",
        "--password-stdin",
        stdin="a long enough password\n",
    )
    assert (code, err.strip()) == (1, "error: a user named 'grace' already exists")
    code, _, err = run(
        database_url,
        "user",
        "create",
        "--username",
        "linus",
        "--role",
        "admin",
        "--password-stdin",
        stdin="short\n",
    )
    assert (code, err.strip()) == (2, "error: a password needs at least 10 characters")
    code, _, err = run(database_url, "user", "create", "--username", "x", "--role", "boss")
    assert code == 2 and "boss" in err


def test_study_create_list_enroll_withdraw(database_url: str, tmp_path: Path) -> None:
    protocol = tmp_path / "lab.toml"
    protocol.write_text(protocol_text(**{"stratify_by = []": 'stratify_by = ["gender"]'}))
    code, out, _ = run(
        database_url, "study", "create", "--protocol", str(protocol), "--name", "lab"
    )
    assert (code, out.strip()) == (
        0,
        "created study 'lab': Fast adaptation for trust modelling (Gao et al.)",
    )
    code, out, _ = run(
        database_url,
        "participant",
        "enroll",
        "--study",
        "lab",
        "--stratum",
        "gender=female",
        "--json",
    )
    assert code == 0
    payload = json.loads(out)
    # not its place in the sequence (issue 35)
    assert set(payload) == {"code", "condition", "language", "site"}
    assert payload["code"] == "P001" and payload["condition"] in {"C1", "C2"}
    code, _, err = run(database_url, "participant", "enroll", "--study", "lab")
    assert (code, err.strip()) == (
        2,
        "error: this study stratifies by gender: give --stratum gender=VALUE",
    )
    code, _, err = run(
        database_url, "participant", "enroll", "--study", "lab", "--stratum", "gender"
    )
    assert code == 2 and "write it as key=value" in err
    code, out, _ = run(database_url, "participant", "withdraw", "--study", "lab", "--code", "P001")
    assert (code, out.strip()) == (0, "withdrew P001 from 'lab' (their data is kept)")
    code, out, _ = run(database_url, "study", "list", "--json")
    listed = json.loads(out)["studies"][0]
    assert listed["name"] == "lab"
    assert sum(by["withdrawn"] for by in listed["enrolment"].values()) == 1


def test_a_study_starts_from_a_shipped_protocol_or_a_copy(database_url: str) -> None:
    code, out, _ = run(database_url, "study", "protocols", "--json")
    shipped = {row["file"]: row for row in json.loads(out)}
    assert code == 0 and shipped["fast_adaptation_trust_sv.toml"]["languages"] == ["en", "sv"]
    swedish = ("--shipped", "fast_adaptation_trust_sv.toml")
    assert run(database_url, "study", "create", *swedish, "--name", "w1")[0] == 0
    code, out, _ = run(database_url, "study", "create", "--copy-of", "w1", "--name", "w2")
    assert (code, out.strip().split(":")[0]) == (0, "created study 'w2'")
    with Database(database_url).writing() as db:
        first, second = (studies.get_study(db, name) for name in ("w1", "w2"))
        assert second.protocol_source == first.protocol_source
    for options, said in [
        ((), "say what the study starts from: one of --protocol, --shipped, --copy-of"),
        ((*swedish, "--copy-of", "w1"), "say what the study starts from"),
        (("--shipped", "nope.toml"), "nope.toml: trustlab ships no protocol of that name"),
        (("--copy-of", "ghost"), "no study named 'ghost'"),
    ]:
        code, _, err = run(database_url, "study", "create", *options, "--name", "w3")
        assert code != 0 and said in err, (options, err)


@sqlite_only("the protocol file is refused before any query")
def test_bad_protocol_file_is_one_line_per_problem(database_url: str, tmp_path: Path) -> None:
    protocol = tmp_path / "bad.toml"
    bad = {"runs_per_session = 3": "runs_per_session = 'three'", "[2, 4]": "[2, 3]"}
    protocol.write_text(protocol_text(**bad))
    code, _, err = run(database_url, "study", "create", "--protocol", str(protocol), "--name", "x")
    assert code == 2
    assert err.strip() == (  # both kinds of problem at once (issue 35 item 9)
        f"error: {protocol}: schedule.runs_per_session: Input should be a valid integer, "
        f"unable to parse string as an integer\n  {protocol}: allocation.block_sizes[1]: "
        "block size 3 is not a positive multiple of the 2 conditions"
    )


def test_conflicts_exit_1(database_url: str) -> None:
    code, _, err = run(database_url, "participant", "withdraw", "--study", "ghost", "--code", "P1")
    assert code == 1
    assert err.strip() == "error: no study named 'ghost'; no study exists yet"


@pytest.mark.parametrize("command", [["init"], ["serve"], ["study", "list"]])
def test_unreachable_database_is_one_line_and_nonzero(command: list[str]) -> None:
    url = "postgresql+psycopg://trustlab@127.0.0.1:1/trustlab"
    completed = subprocess.run(
        [sys.executable, "-c", "from app.cli import main; main()", *command],
        capture_output=True,
        text=True,
        env={"TRUSTLAB_DATABASE_URL": url, "PATH": "/usr/bin:/bin"},
        timeout=60,
        check=False,
    )
    assert completed.returncode == 1
    lines = completed.stderr.strip().splitlines()
    assert len(lines) == 1
    assert lines[0].startswith(f"error: cannot reach the database at {url}: ")


def _commands() -> dict[str, Any]:
    """Every command that does something (not a group), by its words after ``trustlab``."""
    found: dict[str, Any] = {}

    def walk(command: Any, words: tuple[str, ...]) -> None:
        subcommands = getattr(command, "commands", None)
        if subcommands is None:
            found[" ".join(words)] = command
        for name, sub in (subcommands or {}).items():
            walk(sub, (*words, name))

    walk(typer.main.get_command(cli), ())
    return found


def _readme_entries() -> dict[str, str]:
    """The README's command list: each entry (a ``trustlab …`` line and its indented
    continuation lines) by its command words."""
    text = (REPO_ROOT / "README.md").read_text()
    block = text.split("## The `trustlab` command", 1)[1].split("```text\n", 1)[1].split("```")[0]
    commands = _commands()
    entries: dict[str, str] = {}
    words = ""
    for line in block.splitlines():
        if line.startswith("trustlab "):
            tokens = line.split()[1:]
            words = ""
            while tokens and not commands.get(words) and re.fullmatch(r"[a-z][a-z-]*", tokens[0]):
                words = f"{words} {tokens.pop(0)}".strip()
            assert words in commands, f"README: no such command (one a line): {line!r}"
            assert words not in entries, f"README lists `trustlab {words}` twice"
            entries[words] = line
        else:
            assert line.startswith(" ") and words, f"README: stray line {line!r}"
            entries[words] += "\n" + line
    return entries


def test_the_readme_lists_every_command_with_every_option() -> None:
    entries = _readme_entries()
    for words, command in _commands().items():
        assert words in entries, f"README lacks `trustlab {words}`"
        for param in command.params:
            names = [*param.opts, *param.secondary_opts]
            if param.param_type_name != "option" or "--help" in names:
                continue
            mentioned = any(re.search(rf"{name}(?![\w-])", entries[words]) for name in names)
            assert mentioned, f"README: `trustlab {words}` lacks {' / '.join(names)}"
    for export in EXPORT_FORMATS:
        assert re.search(rf"\b{export}\b", entries["export"]), f"README: export lacks {export}"


def test_help_texts_name_defaults_and_no_issue_numbers() -> None:
    served = runner.invoke(cli, ["serve", "--help"], env={"COLUMNS": "200"})
    assert "else 127.0.0.1)" in served.stdout and "else 8000)" in served.stdout
    pretrain = runner.invoke(cli, ["pretrain", "--help"], env={"COLUMNS": "200"})
    assert "protocol's feedback model (learners.feedback)" in pretrain.stdout  # no word lost
    for words in ("", *{w.rsplit(" ", 1)[0] for w in _commands() if " " in w}, *_commands()):
        shown = runner.invoke(cli, [*words.split(), "--help"], env={"COLUMNS": "200"})
        assert shown.exit_code == 0, words
        assert not re.search(r"\bissues? \d", shown.stdout, re.IGNORECASE), words


def test_the_readme_shows_the_schema_a_new_database_gets() -> None:
    """The README's sample of `make run` names the newest migration (it said 0018 at 0020)."""
    readme = (REPO_ROOT / "README.md").read_text(encoding="utf-8")
    shown = re.findall(r"schema at (\d{4}) \(was empty\)", readme)
    assert shown == [schema.head_revision()]


def test_help_texts_keep_their_bracketed_words() -> None:
    """A help text's ``[sites]`` or ``[speech]`` (a protocol table) reaches the terminal: the help
    is printed through rich, whose markup took such words for styles and dropped them
    ("(a study with ; default: all)")."""
    for words, command in _commands().items():
        texts = [command.help or "", *(getattr(p, "help", None) or "" for p in command.params)]
        bracketed = {m for text in texts for m in re.findall(r"\[[a-z_.]+\]", text)}
        if not bracketed:
            continue
        shown = runner.invoke(cli, [*words.split(), "--help"], env={"COLUMNS": "300"})
        flat = re.sub(r"[\s│]+", " ", shown.stdout)
        for word in bracketed:
            assert word in flat, f"`trustlab {words} --help` lost {word}"


def test_study_consent_adds_a_version_and_refuses_bad_files(
    database_url: str, tmp_path: Path
) -> None:
    """``study consent``: a new version from a file, printed with its hashes; an unknown study,
    an empty, unchanged or untranslated text, or a stray key is one line, nothing added."""
    protocol = tmp_path / "sv.toml"
    protocol.write_text((REPO_ROOT / "app/protocols/fast_adaptation_trust_sv.toml").read_text())
    assert run(database_url, "study", "create", "--protocol", str(protocol), "--name", "sv")[0] == 0
    new = tmp_path / "consent.toml"

    def add(text: str, *extra: str) -> tuple[int, str, str]:
        new.write_text(text)
        return run(database_url, "study", "consent", "--study", "sv", "--file", str(new), *extra)

    refusals = {
        'text = "New."\n': "translations.sv.text: missing in 'sv': every language of the "
        "study needs the text",
        'text = " "\n[translations.sv]\ntext = "Ny."\n': "text: empty in 'en': give the text",
        'txt = "New."\n': f"{new}: unknown key 'txt'; a consent file has version, text and "
        "[translations.<language>] text",
        'text = "New.\n': f"{new}: not valid TOML",
    }
    for content, message in refusals.items():
        code, _, err = add(content)
        assert code == 2 and err.startswith(f"error: {message}"), err
    new.write_text('text = "New."')
    code, _, err = run(database_url, "study", "consent", "--study", "ghost", "--file", str(new))
    assert (code, err.strip()) == (1, "error: no study named 'ghost'; known studies: sv")

    both = 'version = "2.0"\ntext = "New."\n[translations.sv]\ntext = "Ny."\n'
    code, out, _ = add(both, "--reason", "amendment approved", "--json")
    assert code == 0
    assert json.loads(out) == {
        "study": "sv",
        "version": 2,
        "label": "2.0",
        "sha256": {
            "en": hashlib.sha256(b"New.").hexdigest(),
            "sv": hashlib.sha256(b"Ny.").hexdigest(),
        },
    }
    code, _, err = add(both)
    assert (code, err.strip()) == (
        2,
        "error: unchanged: the text is version 2's (2.0) in every language; nothing added",
    )
    code, _, err = add(both.replace("Ny.", "Ny text."))  # a label is one version's only
    assert (code, err.strip()) == (
        2,
        "error: version: '2.0' is version 2's label already; give another",
    )
    code, out, _ = add(both.replace("Ny.", "Ny text.").replace('version = "2.0"\n', ""))
    assert code == 0
    assert out.startswith("added version 3 (3) of 'sv''s consent text\n  en: sha256 ")


def test_help_repeats_the_defaults_it_does_not_import() -> None:
    """``--help`` imports no settings, exports or learners (tests/app/test_cli_imports.py), so
    the values it names are repeated in the command modules: they must stay the real ones."""
    from app.cli import admin, engine, exports, runtime
    from app.inputs import MAX_ROW_ID
    from models.learners.exp3 import DEFAULT_EXP3_GAMMA

    defaults = Settings.model_fields
    served = (defaults["host"].default, defaults["port"].default)
    assert served == (admin.DEFAULT_HOST, admin.DEFAULT_PORT)
    assert tuple(EXPORT_FORMATS) == exports.FORMATS
    assert DEFAULT_EXP3_GAMMA == engine.DEFAULT_EXP3_GAMMA
    assert MAX_ROW_ID == runtime.MAX_ROW_ID
