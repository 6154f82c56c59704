"""Files that hold secrets: backups, the SQLite database and the exports of study data.

They carry allocation seeds, password and token hashes or participants' answers, so only their
owner may read them (mode 0600, whatever the umask). A new one is never written through a
symbolic link (a link planted at the path would send the secrets wherever it points) and appears
complete or not at all: it is written to a temporary file beside its path and then linked into
place, which, unlike a rename, never replaces a file that appeared there meanwhile. Replacing an
existing file is a choice the caller makes explicitly (``replace=True``); it renames over it.
"""

from __future__ import annotations

import contextlib
import errno
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

from app.errors import InvalidInput

__all__ = [
    "PRIVATE_MODE",
    "create_private",
    "new_private_file",
    "refuse_existing",
    "refuse_link",
]

PRIVATE_MODE = 0o600
"""Read and write for the owner, nothing for anyone else."""

# Filesystems without hard links (FAT and exFAT USB drives) answer link() with one of these.
_NO_HARD_LINKS = {errno.EPERM, errno.EOPNOTSUPP, errno.ENOTSUP, errno.EMLINK}


def refuse_link(path: Path) -> None:
    """Raise :class:`InvalidInput` if ``path`` is a symbolic link (dangling or not)."""
    if path.is_symlink():
        raise InvalidInput(
            f"{path} is a symbolic link; give the path of a new file (trustlab never writes "
            "through a link: it could point anywhere)"
        )


def create_private(path: Path) -> bool:
    """Create an empty file at ``path`` readable by its owner only, unless something is there.

    Returns whether it was created; an existing file (or link) is left as it is.
    """
    try:
        descriptor = os.open(
            path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, PRIVATE_MODE
        )
    except FileExistsError:
        return False
    try:
        os.fchmod(descriptor, PRIVATE_MODE)  # the umask only removes bits: set them exactly
    finally:
        os.close(descriptor)
    return True


@contextlib.contextmanager
def new_private_file(target: Path, *, replace: bool = False) -> Iterator[Path]:
    """A temporary file (mode 0600) beside ``target`` to write into, published at ``target``.

    When the ``with`` block ends normally the file is flushed to disk and appears at ``target``
    in one step; if ``target`` exists by then, nothing is replaced and :class:`InvalidInput` is
    raised, unless ``replace`` (then an existing regular file is replaced in one step, never
    followed if it is a link). Whatever happens, the temporary file is gone afterwards.
    """
    refuse_link(target)
    refuse_existing(target, replace=replace)
    descriptor, name = tempfile.mkstemp(
        dir=target.parent, prefix=f".{target.name}.", suffix=".partial"
    )
    temporary = Path(name)
    try:
        os.fchmod(descriptor, PRIVATE_MODE)
        os.close(descriptor)
        yield temporary
        _sync(temporary)
        if replace:
            os.replace(temporary, target)  # renames over a link planted meanwhile, never into it
        else:
            _publish(temporary, target)
        _sync(target.parent)
    finally:
        temporary.unlink(missing_ok=True)


def refuse_existing(target: Path, *, replace: bool = False) -> None:
    """Raise :class:`InvalidInput` if ``target`` exists, unless ``replace`` and it is a regular
    file (a folder is never replaced)."""
    if not target.exists():
        return
    if not replace:
        raise InvalidInput(f"{target} exists; choose a new file name")
    if not target.is_file():
        raise InvalidInput(f"{target} exists and is not a file; choose a new file name")


def _publish(temporary: Path, target: Path) -> None:
    try:
        os.link(temporary, target)
    except FileExistsError:
        raise InvalidInput(
            f"{target} appeared while it was written; choose a new file name"
        ) from None
    except OSError as exc:
        if exc.errno not in _NO_HARD_LINKS:
            raise
        # No hard links here: rename, after one more look (a file appearing in between would be
        # replaced; on such filesystems there is no atomic way to refuse it).
        refuse_link(target)
        if target.exists():
            raise InvalidInput(
                f"{target} appeared while it was written; choose a new file name"
            ) from None
        os.rename(temporary, target)


def _sync(path: Path) -> None:
    descriptor = os.open(path, os.O_RDONLY)
    try:
        os.fsync(descriptor)
    finally:
        os.close(descriptor)
