"""Backups hold seeds and password hashes: never written through a link, mode 0600 whatever the
umask, and nothing at the path unless the backup is complete (SQLite and pg_dump alike)."""

from __future__ import annotations

import errno
import os
import sqlite3
import stat
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from sqlalchemy import select
from sqlalchemy.engine import make_url
from typer.testing import CliRunner

from app import backup, private_files
from app.backup import BackupFailed
from app.cli import cli
from app.db import Database
from app.errors import InvalidInput
from app.private_files import new_private_file
from app.tables import AuditEvent
from tests.conftest import POSTGRES_URL


@pytest.fixture
def umask() -> Iterator[None]:
    """The most permissive umask (0): any mode below 0600 comes from trustlab, not from it."""
    previous = os.umask(0)
    yield
    os.umask(previous)


def _mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def _backup(database_url: str, out: Path) -> tuple[int, str]:
    result = CliRunner().invoke(
        cli, ["db", "backup", "--out", str(out)], env={"TRUSTLAB_DATABASE_URL": database_url}
    )
    return result.exit_code, result.stderr


def _backups_recorded(database_url: str) -> int:
    database = Database(database_url)
    with database.read_session() as db:
        count = len(db.scalars(select(AuditEvent).where(AuditEvent.action == "db.backed_up")).all())
    database.dispose()
    return count


@pytest.mark.parametrize("points_at", ["nothing", "a file"])
def test_a_symbolic_link_at_the_path_is_refused(
    database_url: str, tmp_path: Path, points_at: str
) -> None:
    folder = tmp_path / "backups"
    folder.mkdir()
    target = folder / "elsewhere.dump"
    if points_at == "a file":
        target.write_bytes(b"keep me")
    link = folder / "backup.dump"
    link.symlink_to(target)
    code, stderr = _backup(database_url, link)
    assert code == 2
    assert stderr == (
        f"error: {link} is a symbolic link; give the path of a new file "
        "(trustlab never writes through a link: it could point anywhere)\n"
    )
    assert link.is_symlink() and os.readlink(link) == str(target)
    if points_at == "a file":
        assert target.read_bytes() == b"keep me"
        assert sorted(p.name for p in folder.iterdir()) == ["backup.dump", "elsewhere.dump"]
    else:
        assert [p.name for p in folder.iterdir()] == ["backup.dump"]
    assert _backups_recorded(database_url) == 0


@pytest.mark.parametrize("mask", [0, 0o022, 0o277], ids=["0", "022", "277"])
def test_a_backup_is_the_owners_only_whatever_the_umask(
    database_url: str, tmp_path: Path, umask: None, mask: int
) -> None:
    os.umask(mask)
    out = tmp_path / "backups" / "trustlab.dump"
    code, stderr = _backup(database_url, out)
    assert code == 0, stderr
    assert _mode(out) == 0o600
    assert [p.name for p in out.parent.iterdir()] == ["trustlab.dump"]  # no draft left
    assert _backups_recorded(database_url) == 1


def test_a_failed_sqlite_backup_leaves_nothing(tmp_path: Path) -> None:
    broken = tmp_path / "live.sqlite3"
    broken.write_bytes(b"this is not a SQLite database, though it is long enough" * 200)
    out_dir = tmp_path / "backups"
    with pytest.raises(BackupFailed, match=r"the SQLite backup of .* failed: file is not a"):
        backup.backup(f"sqlite:///{broken}", out_dir / "trustlab.sqlite3")
    assert list(out_dir.iterdir()) == []


@pytest.mark.postgres
def test_a_failed_pg_dump_leaves_nothing(tmp_path: Path) -> None:
    if not POSTGRES_URL:
        pytest.skip("PostgreSQL variant: set TRUSTLAB_TEST_POSTGRES_URL to run it")
    missing = make_url(POSTGRES_URL).set(database="tl_no_such_database")
    out_dir = tmp_path / "backups"
    with pytest.raises(BackupFailed, match=r"pg_dump failed: .*tl_no_such_database"):
        backup.backup(missing.render_as_string(hide_password=False), out_dir / "trustlab.dump")
    assert list(out_dir.iterdir()) == []


def _write_then(target: Path, meanwhile: Callable[[Path], None]) -> None:
    """Write a draft of ``target``, and call ``meanwhile(target)`` before it is published."""
    with new_private_file(target) as draft:
        draft.write_bytes(b"backup")
        meanwhile(target)


def test_the_path_stays_empty_until_the_backup_is_complete(tmp_path: Path) -> None:
    target = tmp_path / "secret.bin"
    with new_private_file(target) as draft:
        draft.write_bytes(b"half")
        assert not target.exists()
        assert draft.parent == tmp_path and _mode(draft) == 0o600
    assert target.read_bytes() == b"half"
    assert [p.name for p in tmp_path.iterdir()] == ["secret.bin"]

    def interrupted(_: Path) -> None:
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        _write_then(tmp_path / "failing.bin", interrupted)
    assert [p.name for p in tmp_path.iterdir()] == ["secret.bin"]


def test_a_file_that_appears_meanwhile_is_never_replaced(tmp_path: Path) -> None:
    def someone_else_writes(target: Path) -> None:
        target.write_bytes(b"someone else's")

    target = tmp_path / "secret.bin"
    with pytest.raises(InvalidInput, match="appeared while it was written"):
        _write_then(target, someone_else_writes)
    assert target.read_bytes() == b"someone else's"
    assert [p.name for p in tmp_path.iterdir()] == ["secret.bin"]


def test_without_hard_links_the_draft_is_renamed_into_place(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    def no_links(source: object, target: object) -> None:  # what FAT and exFAT answer
        raise OSError(errno.EPERM, "Operation not permitted")

    monkeypatch.setattr(private_files.os, "link", no_links)
    target = tmp_path / "secret.bin"
    with new_private_file(target) as draft:
        draft.write_bytes(b"backup")
    assert target.read_bytes() == b"backup" and _mode(target) == 0o600
    assert [p.name for p in tmp_path.iterdir()] == ["secret.bin"]


def test_a_new_sqlite_database_and_a_restored_one_are_the_owners_only(
    tmp_path: Path, umask: None
) -> None:
    os.umask(0o022)
    live = tmp_path / "var" / "trustlab.sqlite3"
    database = Database(f"sqlite:///{live}")
    with database.engine.connect() as connection:
        connection.exec_driver_sql("CREATE TABLE t (x INTEGER)")
        connection.exec_driver_sql("INSERT INTO t VALUES (1)")
        connection.commit()
        sidecars = sorted(p.name for p in live.parent.iterdir())
        assert sidecars == ["trustlab.sqlite3", "trustlab.sqlite3-shm", "trustlab.sqlite3-wal"]
        assert {_mode(p) for p in live.parent.iterdir()} == {0o600}
    database.dispose()

    copy = tmp_path / "backup.sqlite3"
    backup.backup(f"sqlite:///{live}", copy)
    restored = tmp_path / "restored" / "trustlab.sqlite3"
    backup.restore(f"sqlite:///{restored}", copy)
    assert _mode(restored) == 0o600
    with sqlite3.connect(restored) as check:
        assert check.execute("SELECT x FROM t").fetchall() == [(1,)]
