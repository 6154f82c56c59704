"""Static files under URLs that name their content, so a browser keeps each one until it changes.

Pages link every script and style through :func:`asset`, which appends the first 16 hex digits of
the file's SHA-256 (``/static/vendor/plotly-cartesian.min.js?v=…``). A request carrying the
file's current version is answered ``immutable`` for a year: on a warm cache the dashboard's
1.5 MB of Plotly is not even revalidated. When the file changes (an upgrade, an edit) its URL
changes with it, so nobody keeps a stale copy. A request with no version, or with one that is no
longer the file's (a page rendered before an upgrade), gets the current file with ``no-cache``:
the browser may keep it but asks again (ETag) before using it, and never pins it under that name.
"""

from __future__ import annotations

import hashlib
from functools import lru_cache
from pathlib import Path
from urllib.parse import parse_qs

from fastapi import APIRouter
from starlette.responses import FileResponse, Response
from starlette.staticfiles import StaticFiles
from starlette.types import Scope

from app.settings import REPO_ROOT

STATIC_ROOT = REPO_ROOT / "static"
STATIC_URL = "/static/"
VERSION_PARAMETER = "v"
IMMUTABLE = "public, max-age=31536000, immutable"
REVALIDATE = "no-cache"
FAVICON = "favicon.ico"
"""The site icon under static/; every page template links it (``asset(FAVICON)``)."""

router = APIRouter(include_in_schema=False)


@lru_cache(maxsize=256)
def _digest(path: Path, modified_ns: int, size: int) -> str:
    """The content hash of ``path`` as it was at (``modified_ns``, ``size``): a changed file is a
    new cache key, so an edited script gets a new URL without restarting the server."""
    sha = hashlib.sha256()
    with path.open("rb") as handle:
        for chunk in iter(lambda: handle.read(1 << 20), b""):
            sha.update(chunk)
    return sha.hexdigest()[:16]


def content_version(relative: str, root: Path = STATIC_ROOT) -> str | None:
    """The current version of the file at ``relative`` under ``root``; None if it is missing or
    lies outside ``root``."""
    path = (root / relative).resolve()
    if root.resolve() not in path.parents:
        return None
    try:
        stat = path.stat()
    except OSError:
        return None
    return _digest(path, stat.st_mtime_ns, stat.st_size)


def asset(relative: str) -> str:
    """The URL a page links ``relative`` (a path under static/) by. A missing file is an error
    at render time, not a broken link the experimenter finds on a lab day."""
    version = content_version(relative)
    if version is None:
        raise FileNotFoundError(f"static/{relative} does not exist (run `make install`)")
    return f"{STATIC_URL}{relative}?{VERSION_PARAMETER}={version}"


class VersionedStaticFiles(StaticFiles):
    """Starlette's static files from one directory, with the caching policy above."""

    def __init__(self, directory: Path) -> None:
        super().__init__(directory=directory)
        self.root = directory

    async def get_response(self, path: str, scope: Scope) -> Response:
        response = await super().get_response(path, scope)
        if response.status_code in (200, 304):
            query = parse_qs(scope.get("query_string", b"").decode("latin-1"))
            asked = query.get(VERSION_PARAMETER, [""])[0]
            current = asked and asked == content_version(path, self.root)
            response.headers["cache-control"] = IMMUTABLE if current else REVALIDATE
        return response


@router.get("/favicon.ico")
def favicon() -> Response:
    """The site icon where browsers look when a page names none (a JSON answer, a bookmark):
    the same file the pages link by version, revalidated like any unversioned asset."""
    path = STATIC_ROOT / FAVICON
    return FileResponse(path, media_type="image/x-icon", headers={"cache-control": REVALIDATE})
