"""The designer's section forms (issue 50, item 2): every shipped protocol round-trips through
every section unchanged; an edit changes only its own lines; entries are added and removed;
problems are said beside their fields, live and on save, with what was typed kept; translations
are edited beside the first language; the version check holds as in the TOML view."""

from __future__ import annotations

import html
import re
from typing import Any

import pytest
from fastapi.testclient import TestClient
from starlette.datastructures import FormData

from app.db import Database
from app.protocol import parse_protocol, shipped_protocol, shipped_protocol_files
from app.protocol_forms import (
    ENTRIES,
    REMOVE,
    SECTION_SLUGS,
    SECTIONS,
    apply_form,
    place_problems,
    rebase_form,
    section_fields,
)
from app.services import studies
from app.services.audit import Actor
from app.tables import Role, StudyPhase
from tests.conftest import UserClientFactory, sqlite_only

SV = "fast_adaptation_trust_sv.toml"
NAME = "designed"


def _as_submitted(text: str, slug: str, **changes: str) -> dict[str, Any]:
    """The section's form as a browser would send it untouched, with ``changes``."""
    form: dict[str, Any] = {}
    for top in section_fields(SECTION_SLUGS[slug], text):
        for made in top.walk():
            if made.kind == "list":
                form[made.name + ENTRIES] = str(len(made.children))
            elif made.kind == "checkbox":
                if made.value:
                    form[made.name] = "on"
            elif made.kind != "group":
                form[made.name] = made.value
    form.update(changes)
    return form


def _changed_lines(before: str, after: str) -> list[tuple[str, str]]:
    old, new = before.splitlines(), after.splitlines()
    assert len(old) == len(new)
    return [(a, b) for a, b in zip(old, new, strict=True) if a != b]


@pytest.mark.parametrize("file", shipped_protocol_files())
def test_every_shipped_protocol_round_trips_through_every_section(file: str) -> None:
    text = shipped_protocol(file).source_text
    for section in SECTIONS:
        assert apply_form(section, text, _as_submitted(text, section.slug)) == text, section.slug


def test_an_edit_changes_its_own_lines_only_and_keeps_the_comments() -> None:
    text = shipped_protocol(SV).source_text
    edited = apply_form(
        SECTION_SLUGS["conditions"],
        text,
        _as_submitted(text, "conditions", **{"conditions[0].label": "Exp3, the baseline"}),
    )
    assert _changed_lines(text, edited) == [
        ('label = "Exp3 bandit"', 'label = "Exp3, the baseline"')
    ]
    translated = apply_form(
        SECTION_SLUGS["languages"],
        text,
        _as_submitted(
            text,
            "languages",
            **{"translations.sv.instruments.demographics.items.age.text": "Din ålder?"},
        ),
    )
    assert _changed_lines(text, translated) == [
        ('items.age.text = "Hur gammal är du (i år)?"', 'items.age.text = "Din ålder?"')
    ]
    protocol = parse_protocol(translated).protocol.in_language("sv")
    assert protocol.questionnaires.instruments[0].items[0].text == "Din ålder?"


def test_entries_are_added_and_removed_and_a_blank_new_one_is_left_out() -> None:
    text = shipped_protocol(SV).source_text
    room = SECTION_SLUGS["room"]
    counts = {"room.walls": 3}
    fields = section_fields(room, text, counts)
    walls = next(f for top in fields for f in top.walk() if f.name == "room.walls")
    assert [entry.new for entry in walls.children] == [False, False, True]
    form = _as_submitted(text, "room")
    form |= {
        "room.walls" + ENTRIES: "3",
        "room.walls[2].x1": "1",
        "room.walls[2].z1": "3",
        "room.walls[2].x2": "2",
        "room.walls[2].z2": "3",
    }
    submitted = FormData([*form.items(), (REMOVE, "room.walls[0]")])
    after = parse_protocol(apply_form(room, text, submitted)).protocol.room
    assert after is not None
    assert [(w.x1, w.z1, w.x2, w.z2) for w in after.walls] == [
        (5.3, 2.0, 5.3, 6.0),
        (1.0, 3.0, 2.0, 3.0),
    ]
    blank = FormData([*_as_submitted(text, "room").items(), ("room.walls" + ENTRIES, "3")])
    assert apply_form(room, text, blank) == text


def test_problems_go_beside_their_fields() -> None:
    text = shipped_protocol(SV).source_text
    section = SECTION_SLUGS["conditions"]
    form = _as_submitted(
        text,
        "conditions",
        **{
            "conditions" + ENTRIES: "3",
            "conditions[2].id": "C3",
            "conditions[2].label": "Exact",
            "conditions[2].learner": "bayes",
            "learners.exp3.gamma": "lots",
        },
    )
    edited = apply_form(section, text, form)
    with pytest.raises(Exception) as refused:
        parse_protocol(edited)
    problems = [(p.path, p.reason) for p in refused.value.problems]  # type: ignore[attr-defined]
    fields = section_fields(section, text, {"conditions": 3})
    elsewhere = place_problems(fields, problems)
    gamma = next(f for top in fields for f in top.walk() if f.name == "learners.exp3.gamma")
    assert gamma.problems and "valid number" in gamma.problems[0]
    assert [(other.text.split(":")[0], other.section) for other in elsewhere] == [
        ("allocation.block_sizes[0]", SECTION_SLUGS["allocation"]),
        ("allocation.block_sizes[1]", SECTION_SLUGS["allocation"]),
    ]  # another section's, with where to put them right


def _draft(database: Database, file: str = SV) -> None:
    with database.writing() as db:
        studies.create_study(
            db,
            name=NAME,
            loaded=shipped_protocol(file),
            actor=Actor.system(),
            phase=StudyPhase.DRAFT,
        )


def _base(page: str) -> str:
    found = re.search(r'name="base" value="([0-9a-f]{64})"', page)
    assert found is not None
    return found.group(1)


@pytest.fixture
def admin(user_client: UserClientFactory) -> TestClient:
    return user_client(Role.ADMIN)


@sqlite_only("forms rendered and parsed; saving a version is tested on both engines")
def test_a_section_saved_in_the_browser_is_the_next_version(
    database: Database, admin: TestClient
) -> None:
    _draft(database)
    page = admin.get(f"/admin/studies/{NAME}/design/study")
    assert page.status_code == 200
    assert 'name="schedule.sessions" value="4"' in page.text
    assert "A whole number, at least 1, at most 50." in page.text  # the rule, from the model
    text = shipped_protocol(SV).source_text
    form = _as_submitted(text, "study", **{"schedule.sessions": "3"})
    form |= {"base": _base(page.text), "reason": "three sessions"}
    checked = admin.post(f"/admin/studies/{NAME}/design/study/check", data=form)
    assert "No problems" in checked.text
    saved = admin.post(f"/admin/studies/{NAME}/design/study", data=form)
    assert "Saved as version 2." in saved.text
    with database.read_session() as db:
        study = studies.get_study(db, NAME)
        assert studies.protocol_of(study).schedule.sessions == 3
        assert _changed_lines(text, study.protocol_source) == [("sessions = 4", "sessions = 3")]
    # The TOML view shows the same protocol; the stale form is refused with what changed.
    toml_view = admin.get(f"/admin/studies/{NAME}/protocol")
    assert "sessions = 3" in html.unescape(toml_view.text)
    stale = admin.post(
        f"/admin/studies/{NAME}/design/study", data=form | {"schedule.sessions": "5"}
    )
    assert stale.status_code == 409 and "+sessions = 3" in html.unescape(stale.text)
    assert 'name="schedule.sessions" value="5"' in stale.text  # what was typed stays
    assert "someone else too, to: <q>3</q>" in stale.text
    carried = {"base": _base(stale.text), "schedule.sessions": "5"}
    again = admin.post(
        f"/admin/studies/{NAME}/design/study", data=_as_submitted(text, "study") | carried
    )
    assert "Saved as version 3." in again.text


def test_a_stale_form_is_carried_over_to_the_current_version() -> None:
    """Each field the form changed keeps its value, every other takes the current one: saving
    the carried-over form undoes nobody's change."""
    base = shipped_protocol(SV).source_text
    theirs = apply_form(
        SECTION_SLUGS["speech"],
        base,
        _as_submitted(base, "speech", **{"speech.reprompt": "Pardon? Yes or no."}),
    )
    mine = _as_submitted(base, "speech", **{"speech.attempts": "2", "speech.listen_seconds": "6"})
    pairs, both = rebase_form(SECTION_SLUGS["speech"], base, theirs, mine)
    assert both == {}
    merged = parse_protocol(apply_form(SECTION_SLUGS["speech"], theirs, FormData(pairs)))
    speech = merged.protocol.speech
    assert (speech.reprompt, speech.attempts, speech.listen_seconds) == (
        "Pardon? Yes or no.",
        2,
        6.0,
    )
    clash = _as_submitted(base, "speech", **{"speech.reprompt": "Say again?"})
    pairs, both = rebase_form(SECTION_SLUGS["speech"], base, theirs, clash)
    assert both == {"speech.reprompt": "Pardon? Yes or no."}
    assert dict(pairs)["speech.reprompt"] == "Say again?"


@sqlite_only("forms rendered and parsed; saving a version is tested on both engines")
def test_a_refused_section_keeps_what_was_typed_and_says_why_beside_it(
    database: Database, admin: TestClient
) -> None:
    _draft(database)
    page = admin.get(f"/admin/studies/{NAME}/design/study")
    text = shipped_protocol(SV).source_text
    form = _as_submitted(text, "study", **{"schedule.sessions": "0", "study.title": ""})
    form["base"] = _base(page.text)
    live = admin.post(f"/admin/studies/{NAME}/design/study/check", data=form)
    assert 'id="problems-f-schedule_sessions" hx-swap-oob="true"><p class="error">' in live.text
    assert "2 problems" in live.text
    refused = admin.post(f"/admin/studies/{NAME}/design/study", data=form)
    assert refused.status_code == 422
    assert 'name="schedule.sessions" value="0"' in refused.text
    assert "greater than or equal to 1" in refused.text
    added = admin.post(
        f"/admin/studies/{NAME}/design/conditions",
        data=_as_submitted(text, "conditions") | {"base": _base(page.text), "add": "conditions"},
    )
    assert added.status_code == 200 and 'name="conditions[2].label"' in added.text
    assert "new</span>" in added.text
    with database.read_session() as db:
        assert studies.get_study(db, NAME).protocol_source == text  # nothing saved


@sqlite_only("forms rendered and parsed; saving a version is tested on both engines")
def test_translations_are_edited_beside_the_first_language(
    database: Database, admin: TestClient
) -> None:
    _draft(database)
    page = admin.get(f"/admin/studies/{NAME}/design/languages")
    assert "Do you want to escape the room?" in page.text  # the English, beside
    assert "Vill du ta dig ut ur rummet?" in page.text  # the Swedish, to edit
    text = shipped_protocol(SV).source_text
    form = _as_submitted(text, "languages", **{"study.languages": "en\nsv\nde"})
    form["base"] = _base(page.text)
    refused = admin.post(f"/admin/studies/{NAME}/design/languages", data=form)
    assert refused.status_code == 422
    assert 'name="translations.de.study.title"' in refused.text  # a column for German
    assert "missing: every participant-facing text in &#39;de&#39;" in refused.text


@pytest.mark.parametrize("engine_name", ["sqlite"], indirect=True)  # pages, not storage
def test_every_section_page_draws_for_a_live_study_as_an_amendment_and_a_pilot_frozen(
    exp3_study: str, admin: TestClient, database: Database
) -> None:
    _draft(database)
    assert admin.post(f"/api/v1/studies/{NAME}/phase", json={"phase": "pilot"}).status_code == 200
    for section in SECTIONS:
        live = admin.get(f"/admin/studies/{exp3_study}/design/{section.slug}")
        assert live.status_code == 200 and 'id="protocol-amendment"' in live.text
        assert '<fieldset class="stack plain">' in live.text  # editable, as an amendment
        pilot = admin.get(f"/admin/studies/{NAME}/design/{section.slug}")
        assert pilot.status_code == 200 and 'id="protocol-frozen"' in pilot.text
        assert '<fieldset class="stack plain" disabled>' in pilot.text
    missing = admin.get(f"/admin/studies/{exp3_study}/design/nowhere")
    assert missing.status_code == 404
