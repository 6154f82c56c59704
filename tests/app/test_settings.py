"""Settings say what they do: the secret key's description matches what the key signs."""

from __future__ import annotations

import gc

from fastapi.testclient import TestClient

from app.main import create_app
from app.settings import Settings
from tests.conftest import Lab, sqlite_only


def test_the_secret_key_description_names_everything_it_signs() -> None:
    description = Settings.model_fields["secret_key"].description or ""
    for use in ("sign-in form", "tablet forms", "notice", "tablet and kiosk links"):
        assert use in description, use
    assert "sign-in sessions do not use it" in description
    assert "var/secret_key" in description


def test_another_secret_keeps_sign_ins_and_links_but_hides_the_links(
    lab: Lab, settings: Settings
) -> None:
    code = lab.enrol_and_assign(questionnaires=False)
    link = f"/api/v1/studies/{lab.study}/participants/{code}/link"
    token = lab.experimenter.post(link).json()["token"]
    other = Settings(
        _env_file=None,  # type: ignore[call-arg]
        database_url=settings.database_url,
        var_dir=settings.var_dir,
        secret_key="another-secret-another-secret-0123456789",
        sqlite_synchronous="NORMAL",
    )
    with TestClient(create_app(other)) as experimenter, TestClient(create_app(other)) as tablet:
        experimenter.cookies = lab.experimenter.cookies
        experimenter.headers["X-CSRF-Token"] = lab.experimenter.headers["X-CSRF-Token"]
        assert experimenter.get(link).json() == {"token": None, "url": None}  # cannot show it
        page = tablet.get("/api/v1/tablet", headers={"Authorization": f"Bearer {token}"})
        assert page.status_code == 200 and page.json()["participant"] == code  # still works


@sqlite_only("the garbage collector's state, not the database, is looked at")
def test_a_served_app_freezes_its_start_up_heap_and_thaws_it_at_shutdown(
    settings: Settings,
) -> None:
    assert settings.freeze_heap_at_start is False  # the tests' own apps leave the heap alone
    with TestClient(create_app(settings)):
        assert gc.get_freeze_count() == 0
    served = settings.model_copy(update={"freeze_heap_at_start": True})  # the default
    assert Settings.model_fields["freeze_heap_at_start"].default is True
    with TestClient(create_app(served)):
        assert gc.get_freeze_count() > 0  # what existed at start is out of full collections
    assert gc.get_freeze_count() == 0  # handed back when the server stops
