"""Backups and restores of a whole trustlab database.

- SQLite: the online backup API copies a consistent snapshot while the server keeps running;
  a restore copies the backup back page by page (stop the server first).
- PostgreSQL: ``pg_dump --format=custom`` and ``pg_restore --clean --single-transaction``, so a
  failed restore leaves the database as it was.

A backup holds allocation seeds and password and token hashes: it is written like every such
file (:mod:`app.private_files`), mode 0600, never through a symbolic link, and it appears at its
path complete or not at all. A restored database is checked before it is declared good: it must
open and carry a known schema revision (``trustlab verify`` then checks every study's integrity).
"""

from __future__ import annotations

import contextlib
import shutil
import sqlite3
import subprocess
from pathlib import Path

from sqlalchemy.engine import make_url

from app.errors import InvalidInput, TrustlabError
from app.private_files import create_private, new_private_file, refuse_link


class BackupFailed(TrustlabError):
    """A backup or restore tool failed; its message says why."""

    status_code = 500


def _sqlite_path(database_url: str) -> Path:
    path = make_url(database_url).database
    if not path or path == ":memory:":
        raise InvalidInput("an in-memory SQLite database cannot be backed up")
    return Path(path)


def _libpq(database_url: str) -> str:
    return make_url(database_url).set(drivername="postgresql").render_as_string(hide_password=False)


def _tool(name: str) -> str:
    found = shutil.which(name)
    if found is None:
        raise BackupFailed(f"{name} is not installed (Debian: apt-get install postgresql-client)")
    return found


def _run(command: list[str]) -> None:
    completed = subprocess.run(command, capture_output=True, text=True, check=False)
    if completed.returncode != 0:
        reason = (completed.stderr or completed.stdout).strip().splitlines()
        raise BackupFailed(f"{Path(command[0]).name} failed: {reason[-1] if reason else '?'}")


def backup(database_url: str, out: Path) -> Path:
    """Write a backup of the database to ``out`` (a new file, mode 0600).

    Nothing is ever at ``out`` but a complete backup: the dump goes to a temporary file beside it,
    which is removed if the dump fails.
    """
    refuse_link(out)
    if out.exists():
        raise InvalidInput(f"{out} exists; choose a new file name (backups never overwrite)")
    source = _sqlite_source(database_url) if _is_sqlite(database_url) else None
    out.parent.mkdir(parents=True, exist_ok=True)
    with new_private_file(out) as draft:
        if source is not None:
            _sqlite_backup(source, draft)
        else:
            _pg_dump(database_url, draft)
    return out


def _is_sqlite(database_url: str) -> bool:
    return make_url(database_url).get_backend_name() == "sqlite"


def _sqlite_source(database_url: str) -> Path:
    source = _sqlite_path(database_url)
    if not source.exists():
        raise InvalidInput(f"no database file at {source}")
    return source


def _pg_dump(database_url: str, draft: Path) -> None:
    """``pg_dump`` into the (empty, private) file ``draft``, which keeps its mode."""
    _run(
        [
            _tool("pg_dump"),
            "--format=custom",
            "--no-owner",
            f"--file={draft}",
            f"--dbname={_libpq(database_url)}",
        ]
    )


def _sqlite_backup(source: Path, draft: Path) -> None:
    """SQLite's online backup of ``source`` into the (empty) file ``draft``."""
    done = False
    try:
        with (
            contextlib.closing(sqlite3.connect(source)) as src,
            contextlib.closing(sqlite3.connect(draft)) as dst,
        ):
            src.backup(dst)
        done = True
    except sqlite3.Error as exc:
        raise BackupFailed(f"the SQLite backup of {source} failed: {exc}") from exc
    finally:
        if not done:  # a backup that failed midway may leave SQLite's files beside the draft
            for suffix in ("-journal", "-wal", "-shm"):
                draft.with_name(draft.name + suffix).unlink(missing_ok=True)


def restore(database_url: str, source: Path) -> None:
    """Replace the database's content with a backup's (everything in it is lost)."""
    if not source.is_file():
        raise InvalidInput(f"no backup file at {source}")
    backend = make_url(database_url).get_backend_name()
    if backend == "sqlite":
        target = _sqlite_path(database_url)
        target.parent.mkdir(parents=True, exist_ok=True)
        create_private(target)
        try:
            with sqlite3.connect(source) as src:
                src.execute("PRAGMA schema_version").fetchone()
                with sqlite3.connect(target) as dst:
                    src.backup(dst)
        except sqlite3.DatabaseError as exc:
            raise InvalidInput(f"{source} is not a SQLite backup: {exc}") from exc
        return
    _run(
        [
            _tool("pg_restore"),
            "--clean",
            "--if-exists",
            "--no-owner",
            "--single-transaction",
            f"--dbname={_libpq(database_url)}",
            str(source),
        ]
    )
