"""Static files are linked by content version and cached accordingly (app/web/assets.py): the
current version is immutable, anything else is revalidated, and an edit changes the URL."""

from __future__ import annotations

import os
import re
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from starlette.applications import Starlette

from app.tables import Role
from app.web.assets import IMMUTABLE, REVALIDATE, VersionedStaticFiles, asset, content_version
from tests.conftest import Lab, UserClientFactory, sqlite_only

LINK = re.compile(r'(?:src|href)="(/static/[^"]+)"')
ICON = re.compile(r'<link rel="icon" href="(/static/[^"]+)"')


@pytest.fixture
def served(tmp_path: Path) -> tuple[Path, TestClient]:
    (tmp_path / "js").mkdir()
    (tmp_path / "js" / "chart.js").write_text("draw(1);\n")
    app = Starlette()
    app.mount("/static", VersionedStaticFiles(directory=tmp_path), name="static")
    return tmp_path, TestClient(app)


def test_only_the_current_version_is_immutable(served: tuple[Path, TestClient]) -> None:
    root, client = served
    version = content_version("js/chart.js", root)
    assert version is not None and len(version) == 16
    current = client.get(f"/static/js/chart.js?v={version}")
    assert current.status_code == 200 and current.text == "draw(1);\n"
    assert current.headers["cache-control"] == IMMUTABLE
    for stale in ("/static/js/chart.js", "/static/js/chart.js?v=0000000000000000"):
        response = client.get(stale)
        assert response.status_code == 200 and response.headers["cache-control"] == REVALIDATE
    revalidated = client.get(
        "/static/js/chart.js", headers={"If-None-Match": current.headers["etag"]}
    )
    assert revalidated.status_code == 304 and revalidated.headers["cache-control"] == REVALIDATE
    assert client.get("/static/js/none.js").status_code == 404


def test_an_edited_file_gets_a_new_version(served: tuple[Path, TestClient]) -> None:
    root, client = served
    before = content_version("js/chart.js", root)
    target = root / "js" / "chart.js"
    target.write_text("draw(2);\n")
    stat = target.stat()
    os.utime(target, ns=(stat.st_atime_ns, stat.st_mtime_ns + 1_000_000))
    after = content_version("js/chart.js", root)
    assert after is not None and after != before
    assert client.get(f"/static/js/chart.js?v={before}").headers["cache-control"] == REVALIDATE
    assert client.get(f"/static/js/chart.js?v={after}").headers["cache-control"] == IMMUTABLE


def test_paths_outside_the_directory_have_no_version(served: tuple[Path, TestClient]) -> None:
    root, _ = served
    assert content_version("../etc/passwd", root) is None
    assert content_version("js/missing.js", root) is None
    with pytest.raises(FileNotFoundError, match="make install"):
        asset("js/no-such-script.js")


@sqlite_only("files and links, not storage")
def test_staff_pages_link_every_static_file_by_version(
    lab: Lab, user_client: UserClientFactory
) -> None:
    admin = user_client(Role.ADMIN)
    pages = (f"/studies/{lab.study}/dashboard", f"/studies/{lab.study}/analysis", "/api/v1/docs")
    seen: set[str] = set()
    for page in pages:
        response = admin.get(page)
        assert response.status_code == 200, page
        links = LINK.findall(response.text)
        assert links, page
        for link in links:
            assert "?v=" in link, (page, link)
            seen.add(link)
    assert any("plotly-cartesian.min.js" in link for link in seen)
    for link in seen:
        fetched = admin.get(link)
        assert fetched.status_code == 200, link
        assert fetched.headers["cache-control"] == IMMUTABLE, link


@pytest.mark.parametrize("engine_name", ["sqlite"], indirect=True)  # files, not storage
def test_every_page_has_a_favicon(lab: Lab) -> None:
    """Staff, tablet and room pages link one icon by version, and a browser that asks at the
    root anyway (a JSON answer, a bookmark) gets the same file, not a 404 (issue 35)."""
    code = lab.enrol_and_assign()
    token = lab.experimenter.post(f"/api/v1/studies/{lab.study}/participants/{code}/link")
    client = TestClient(lab.app)
    pages = ["/login", f"/stations/{lab.station}/room", f"/t/{token.json()['token']}"]
    for page in pages:
        icons = ICON.findall(client.get(page).text)
        assert len(icons) == 1 and "?v=" in icons[0], page
    icon = client.get(icons[0])
    assert icon.status_code == 200 and icon.content[:4] == b"\x00\x00\x01\x00"  # an ICO file
    root = client.get("/favicon.ico")
    assert root.status_code == 200 and root.content == icon.content
    assert root.headers["content-type"] == "image/x-icon"
