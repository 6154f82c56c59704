"""Studies in several languages: the protocol's translations, each participant's language, and
everything a participant hears following it (issue: studies in the participants' languages)."""

from __future__ import annotations

import hashlib
import html
import re
import tomllib
from importlib import resources
from pathlib import Path
from typing import Any

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient

from analysis.exports import codebook_json, codebook_table, long_table, steps_table, wide_table
from analysis.methods import languages_paragraph, translation_references
from analysis.report import _per_language, build_report
from app.db import Database
from app.errors import Conflict, PermissionDenied
from app.i18n import catalogues
from app.i18n.catalogues import catalogue
from app.i18n.extract import extract
from app.i18n.protocol_texts import TRANSLATIONS, text_slots
from app.protocol import Protocol, ProtocolError, default_protocol, parse_protocol
from app.services import studies
from app.services.analysis_views import study_data
from app.services.audit import Actor
from app.services.participants import enrolment, languages, questionnaires
from app.services.privacy.sites import Scope
from app.services.sessions import verify
from app.tables import Role
from tests import participant_words as words
from tests.app.test_cli import run as cli_run
from tests.conftest import (
    EXP3_ONLY,
    PRE_STUDY_ANSWERS,
    Lab,
    UserClientFactory,
    fill_pre_study,
    sqlite_only,
    tablet_client,
)

SWEDISH = "fast_adaptation_trust_sv.toml"


def _swedish_text(**replacements: str) -> str:
    text = resources.files("app.protocols").joinpath(SWEDISH).read_text(encoding="utf-8")
    for old, new in replacements.items():
        assert old in text, f"{old!r} not in the Swedish protocol"
        text = text.replace(old, new)
    return text


def _problems(text: str) -> str:
    with pytest.raises(ProtocolError) as caught:
        parse_protocol(text, source="lab.toml")
    return str(caught.value)


def test_the_swedish_example_translates_every_participant_facing_text() -> None:
    protocol = parse_protocol(_swedish_text()).protocol
    assert protocol.study.languages == ["en", "sv"]
    swedish = protocol.in_language("sv")
    english = protocol.in_language("en")
    assert english is protocol
    assert swedish.study.languages == ["sv", "en"]  # its own first, the others still offered
    assert swedish.category("cognition").questions[1] == (
        "Här är nycklarna. Behöver du den andra nyckeln?"
    )
    assert swedish.replies.levels[-1].line(True) == "Toppen, jag visste att du skulle säga det."
    assert swedish.speech.yes[0] == "ja"
    assert swedish.questionnaires.scales[0].labels[0] == "Instämmer inte alls"
    # Every text differs from the English one: nothing was left untranslated by copying.
    slots_en = text_slots(protocol.model_dump(mode="json"))
    slots_sv = {s.path: s.source for s in text_slots(swedish.model_dump(mode="json"))}
    untranslated = [s.path for s in slots_en if slots_sv[s.path] == s.source]
    assert untranslated == []
    # Only texts change: the structure (keys, scales, learners, schedule) is the same.
    assert swedish.model_dump(exclude={"study", "categories", "replies", "speech"}).keys() == (
        english.model_dump(exclude={"study", "categories", "replies", "speech"}).keys()
    )
    assert [c.name for c in swedish.categories] == [c.name for c in english.categories]
    assert swedish.learners == english.learners and swedish.schedule == english.schedule


def test_a_translated_copy_is_built_once_and_changes_nothing_of_the_protocol() -> None:
    protocol, twin = (parse_protocol(_swedish_text()).protocol for _ in range(2))
    swedish = protocol.in_language("sv")
    assert protocol.in_language("sv") is swedish  # built once
    assert protocol == twin  # equal protocols stay equal (studies compare them)
    with pytest.raises(KeyError):
        protocol.in_language("de")  # not one of its languages: enrolment refuses it first


def test_the_swedish_example_is_the_shipped_protocol_apart_from_its_languages() -> None:
    """The two files must not drift: everything but the language keys is the same."""
    swedish = tomllib.loads(_swedish_text())
    shipped = tomllib.loads(default_protocol().source_text)
    del swedish[TRANSLATIONS]
    del swedish["study"]["languages"], swedish["study"]["language_choice"]
    assert swedish == shipped


def test_a_missing_empty_or_misshapen_translation_is_refused_with_its_key_path() -> None:
    text = _swedish_text(
        **{
            'items.tipi_3.text = "Pålitlig, självdisciplinerad."\n': "",
            'medium.text = "Nu förstår jag."': 'medium.text = " "',
            '    "Kom du hit för att leta efter dina vänner?",\n': "",
            'title = "Om dig"': 'title = "Om dig"\nitems.shoe_size.text = "Skostorlek"',
        }
    )
    problems = _problems(text)
    assert "translations.sv.instruments.tipi.items.tipi_3.text: missing in 'sv'" in problems
    assert "translations.sv.replies.medium.text: empty in 'sv'" in problems
    assert "translations.sv.categories.conation.questions: 3 entries in 'sv', 4" in problems
    assert (
        "translations.sv.instruments.demographics.items.shoe_size.text: "
        "not a participant-facing text of this protocol" in problems
    )


@pytest.mark.parametrize(
    ("languages", "expected"),
    [
        ('["en", "fi"]', "translations.fi: missing: every participant-facing text in 'fi'"),
        ('["en", "sv", "fi"]', "study.languages[2]: no interface catalogue for 'fi'"),
        ('["en"]', "translations.sv: 'sv' is not one of study.languages (en)"),
        ('["en", "xx"]', "study.languages[1]: 'xx' is not a language known to CLDR"),
        ('["en", "Swedish"]', "study.languages[1]: 'Swedish' is not a language code"),
        ('["en", "sv", "en"]', "study.languages[2]: duplicate language 'en'"),
    ],
)
def test_languages_that_cannot_be_used_are_refused(languages: str, expected: str) -> None:
    problems = _problems(_swedish_text(**{'languages = ["en", "sv"]': f"languages = {languages}"}))
    assert expected in problems


def test_a_translation_says_where_it_comes_from_or_nothing() -> None:
    """``source`` is the translation's own key (not a text to translate): the shipped Swedish
    one says it is a working translation; an empty one is refused, a missing one allowed (a
    study created before the key existed stays valid, and its report says it was not given)."""
    source = 'source = "Working translation made for trustlab'
    assert source in _swedish_text()
    empty = _swedish_text(
        **{source: 'source = " "\nunused = "Working translation made for trustlab'}
    )
    assert "translations.sv.source: must be a non-empty text in 'sv'" in _problems(empty)
    misspelt = _swedish_text(**{source: 'comment = "Working translation made for trustlab'})
    assert "translations.sv.comment: not a participant-facing text" in _problems(misspelt)
    lines = _swedish_text().splitlines()
    without = "\n".join(line for line in lines if not line.startswith("source ="))
    protocol = parse_protocol(without).protocol
    assert protocol.in_language("sv").study.title.startswith("Snabb anpassning")
    assert languages.translation_summary(protocol)["sv"]["source"] == ""


def test_a_translation_of_the_protocols_own_language_is_refused() -> None:
    text = _swedish_text() + '\n[translations.en]\nstudy.title = "Fast adaptation"\n'
    assert "translations.en: 'en' is the protocol's first language" in _problems(text)


def test_a_phrase_that_means_both_answers_in_a_translation_is_refused() -> None:
    text = _swedish_text(**{'no = ["nej", "nä", "nej tack"]': 'no = ["nej", "ja"]'})
    assert "translations.sv.speech.no[1]: 'ja' is a yes phrase too" in _problems(text)


# ------------------------------------------------------------------------- participants


@pytest.fixture
def swedish_lab(lab: Lab, database: Database) -> Lab:
    """The lab's station running the Swedish example (both conditions Exp3)."""
    text = _swedish_text(**EXP3_ONLY)
    with database.writing() as db:
        studies.create_study(db, name="sv", loaded=parse_protocol(text), actor=Actor.system())
    lab.study = "sv"
    return lab


def _enrol(lab: Lab, **body: Any) -> dict[str, Any]:
    response = lab.experimenter.post(f"/api/v1/studies/{lab.study}/participants", json=body)
    assert response.status_code == 201, response.text
    return dict(response.json())


def _seat(lab: Lab, code: str) -> None:
    seated = lab.experimenter.put(
        f"/api/v1/stations/{lab.station}/participant", json={"study": lab.study, "code": code}
    )
    assert seated.status_code == 200, seated.text


@sqlite_only("the seat's raw SQL is covered on both engines by the robot test below")
def test_enrolment_sets_the_language_or_leaves_it_to_the_tablet(swedish_lab: Lab) -> None:
    assert _enrol(swedish_lab, code="S1", language="sv")["language"] == "sv"
    assert _enrol(swedish_lab, code="S2")["language"] is None  # the protocol lets them choose
    listed = swedish_lab.experimenter.get(f"/api/v1/studies/{swedish_lab.study}/participants")
    assert {p["code"]: p["language"] for p in listed.json()} == {"S1": "sv", "S2": None}


@sqlite_only("the default is chosen before any query")
def test_a_study_in_one_language_gives_everyone_that_language(lab: Lab) -> None:
    assert _enrol(lab, code="E1")["language"] == "en"


@sqlite_only("refused before anything is written")
@pytest.mark.parametrize(
    ("language", "reason"),
    [
        ("fi", "study 'sv' is not run in 'fi': its languages are en, sv"),
        ("klingon", "'klingon' is not a language code"),
    ],
)
def test_enrolment_in_a_language_the_study_does_not_offer_is_refused(
    swedish_lab: Lab, language: str, reason: str
) -> None:
    refused = swedish_lab.experimenter.post(
        f"/api/v1/studies/{swedish_lab.study}/participants",
        json={"code": "S9", "language": language},
    )
    assert refused.status_code == 422
    assert reason in refused.json()["detail"]
    listed = swedish_lab.experimenter.get(f"/api/v1/studies/{swedish_lab.study}/participants")
    assert listed.json() == []  # nothing half-saved


def _fill_tablet(lab: Lab, code: str) -> TestClient:
    tablet = tablet_client(lab.app, lab, code)
    fill_pre_study(tablet)
    lab.tablets[code] = tablet
    return tablet


def test_the_robot_asks_and_replies_in_the_participants_language(swedish_lab: Lab) -> None:
    lab = swedish_lab
    _enrol(lab, code="S1", language="sv")
    _seat(lab, "S1")
    _fill_tablet(lab, "S1")
    lab.start_session()
    prompt = lab.prompt("cognition")
    swedish = parse_protocol(_swedish_text()).protocol.in_language("sv")
    assert prompt["question"] == swedish.category("cognition").questions[prompt["action"]]
    assert prompt["language"] == "sv"
    answered = lab.answer(prompt["step_id"], "yes")
    lines = {level.line(True) for level in swedish.replies.levels}
    assert answered["reply"] in lines
    with lab.database.read_session() as db:
        report = verify.verify_study(db, study_name=lab.study)
    assert report.ok, report.findings


@sqlite_only("the refusal is decided in Python; the step SQL is covered by the robot test")
def test_the_language_stays_once_a_session_has_started_unless_an_admin_overrides(
    swedish_lab: Lab, user_client: UserClientFactory
) -> None:
    lab = swedish_lab
    _enrol(lab, code="S1", language="sv")
    _seat(lab, "S1")
    _fill_tablet(lab, "S1")
    lab.start_session()
    first = lab.prompt("conation")
    lab.answer(first["step_id"], "no")
    with lab.database.writing() as db:
        study = studies.get_study(db, lab.study)
        participant = enrolment.get_participant(db, study, "S1", actor=Actor.system())
        protocol = studies.protocol_of(study)
        common: dict[str, Any] = {
            "participant": participant,
            "protocol": protocol,
            "study_name": lab.study,
            "language": "en",
        }
        with pytest.raises(Conflict, match="has started a session in 'sv'"):
            languages.set_language(db, actor=Actor.command_line(), **common)
        with pytest.raises(PermissionDenied, match="only an admin"):
            languages.set_language(
                db,
                actor=Actor.command_line(),
                actor_role=Role.EXPERIMENTER,
                override_reason="reads English better",
                **common,
            )
        languages.set_language(
            db,
            actor=Actor.command_line(),
            actor_role=Role.ADMIN,
            override_reason="reads English better",
            **common,
        )
    second = lab.prompt("affection")
    english = parse_protocol(_swedish_text()).protocol
    assert second["question"] == english.category("affection").questions[second["action"]]
    lab.answer(second["step_id"], "yes")
    with lab.database.read_session() as db:
        report = verify.verify_study(db, study_name=lab.study)
    assert report.ok, report.findings  # each step checked in the language it was asked in


@sqlite_only("only rendering is looked at")
def test_staff_see_the_language_on_the_study_page(
    swedish_lab: Lab, user_client: UserClientFactory
) -> None:
    _enrol(swedish_lab, code="S1", language="sv")
    page = swedish_lab.experimenter.get(f"/studies/{swedish_lab.study}")
    assert page.status_code == 200
    assert 'title="Language">sv<' in page.text
    assert "sv · Svenska" in page.text  # the enrolment form offers the study's languages


# ------------------------------------------------------------------------- the tablet


FORM_TOKEN = re.compile(r'name="csrf_token" value="([^"]+)"')


def _english_words(protocol: Protocol) -> set[str]:
    """Every English sentence a Swedish participant must not see: the interface's messages
    whose Swedish differs, and the protocol's English texts."""
    swedish = catalogue("sv")
    words = {m for m in catalogue("en").messages if swedish.gettext(m) != m and "%" not in m}
    for slot in text_slots(protocol.model_dump(mode="json")):
        words.update([slot.source] if isinstance(slot.source, str) else slot.source)
    return {w for w in words if len(w) > 3} - {"Conation"}  # (a category title, never shown)


def _visible(page: str) -> str:
    body = re.sub(r"<(script|style)\b.*?</\1>", " ", page, flags=re.S)
    body = re.sub(r"<[^>]+>", " ", body)
    return " ".join(html.unescape(body).split())


def _leaks(page: str, english: set[str]) -> list[str]:
    visible = _visible(page)
    return sorted(w for w in english if " ".join(w.split()) in visible)


@sqlite_only("rendering only; the language column's SQL is covered by the robot test")
def test_a_participant_chooses_swedish_and_the_tablet_speaks_it(
    swedish_lab: Lab, app: FastAPI
) -> None:
    lab = swedish_lab
    _enrol(lab, code="S2")
    link = lab.experimenter.post(f"/api/v1/studies/{lab.study}/participants/S2/link").json()
    tablet = TestClient(app)
    tablet.get(f"/t/{link['token']}")
    choice = tablet.get("/tablet")
    assert choice.url.path == "/tablet/language"
    assert "Svenska" in choice.text and "English" in choice.text
    token = FORM_TOKEN.search(choice.text)
    assert token
    consent = tablet.post("/tablet/language", data={"csrf_token": token[1], "language": "sv"})
    assert consent.url.path == "/tablet/consent"
    english = _english_words(parse_protocol(_swedish_text()).protocol)
    pages = [consent]
    assert '<html lang="sv" dir="ltr"' in consent.text
    assert "Innan vi börjar" in consent.text and "Spelets regler" in consent.text
    refused = tablet.post("/tablet/consent", data={"csrf_token": token[1]})
    assert refused.status_code == 422 and "Kryssa i rutan för att delta." in refused.text
    pages.append(refused)
    page = tablet.post("/tablet/consent", data={"csrf_token": token[1], "accept": "yes"})
    while page.url.path.startswith("/tablet/q/"):
        pages.append(page)
        instrument = page.url.path.rsplit("/", 1)[1]
        incomplete = tablet.post(page.url.path, data={"csrf_token": token[1]})
        assert incomplete.status_code == 422 and "Svara på den här frågan." in incomplete.text
        pages.append(incomplete)
        page = tablet.post(
            page.url.path, data={"csrf_token": token[1], **PRE_STUDY_ANSWERS[instrument]}
        )
    assert page.url.path == "/tablet/wait"
    pages.append(page)
    assert "Vänta på försöksledaren." in page.text
    swedish_words = words.known_texts("sv", parse_protocol(_swedish_text()).protocol)
    for shown in pages:
        assert 'lang="sv"' in shown.text
        assert _leaks(shown.text, english) == [], shown.url.path
        # Only Swedish: every word shown is the catalogue's or the protocol's (or a form's).
        assert words.unexplained(words.fragments(shown.text), swedish_words) == [], shown.url.path
    again = tablet.post("/tablet/language", data={"csrf_token": token[1], "language": "en"})
    assert again.status_code == 409  # chosen once; staff change it after that
    assert "Språket är redan valt." in again.text
    with lab.database.read_session() as db:
        stored = questionnaires.stored_answers(
            db,
            enrolment.get_participant(db, studies.get_study(db, "sv"), "S2", actor=Actor.system()),
            "consent",
            None,
        )
    swedish = parse_protocol(_swedish_text()).protocol.in_language("sv")
    assert stored["consent_language"] == "sv"
    assert (
        stored["consent_sha256"]
        == hashlib.sha256(swedish.questionnaires.consent.text.encode()).hexdigest()
    )


# ------------------------------------------------------------- every participant word (class D)


def test_every_participant_template_is_declared_and_marks_its_words() -> None:
    """A new tablet page (or anything a participant route renders, extends or includes) must be
    a declared participant template, whose words are all marked for translation: a literal word
    would reach a Swedish participant in English."""
    found = words.participant_templates()
    assert {"room.html", "tablet_base.html", "tablet_message.html", "_rules.html"} <= found
    undeclared = sorted(name for name in found if not words.is_participant_template(name))
    assert undeclared == [], "add them to app.i18n.extract.PARTICIPANT_TEMPLATES"
    literal = {name: words.literal_words(name) for name in sorted(found)}
    assert {name: found for name, found in literal.items() if found} == {}


def test_the_template_sweep_finds_a_literal_word_and_an_undeclared_page(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """The sweep's own check: a literal word, a literal label, a staff form, and a new page."""
    base = "<title>{{ t }}</title>{% block content %}{% endblock %}"
    (tmp_path / "tablet_base.html").write_text(base)
    (tmp_path / "tablet_new.html").write_text(
        '{% extends "tablet_base.html" %}{% block content %}<p>{% trans %}Thanks{% endtrans %}'
        '</p><p>Thank you!</p><button aria-label="Close it">{{ _("x") }}</button>'
        "<form data-staff><label>Device key</label></form>{% endblock %}"
    )
    (tmp_path / "kiosk_start.html").write_text('{% extends "tablet_base.html" %}')
    monkeypatch.setattr(words, "TEMPLATES", tmp_path)
    monkeypatch.setattr(words, "PARTICIPANT_ROUTES", ())
    found = words.participant_templates()
    assert found == {"tablet_base.html", "tablet_new.html", "kiosk_start.html"}
    assert not words.is_participant_template("kiosk_start.html")
    assert words.literal_words("tablet_new.html") == ["Thank you!", "Close it"]


def test_every_sentence_of_the_participant_scripts_goes_through_the_catalogue() -> None:
    """The room's and the tablet's scripts: a sentence is the message of _() or show(), or
    staff() says it is the operator's English on purpose."""
    scripts = words.participant_scripts()
    names = {str(path.relative_to(words.REPO_ROOT)) for path in scripts}
    assert {"static/js/room.js", "static/js/room/words.js", "static/js/tablet.js"} <= names
    assert [found for path in sorted(scripts) for found in words.bypassing_sentences(path)] == []


def test_the_script_sweep_finds_sentences_that_bypass_the_catalogue(tmp_path: Path) -> None:
    script = words.REPO_ROOT / "static" / "js" / "room" / "__sweep_check.js"
    script.write_text(
        'const a = _("Fine words"); show(el("x"), "Connected"); staff(`Key of ${station}`);\n'
        'el("b").textContent = "Connected";  // a badge in English\n'
        'const words = { online: "Online", code: "KeyY" }; const re = /"[a-z]+ [a-z]"/g;\n'
        'showNotice(_("Welcome"), `Hello ${name}, welcome`); console.warn(`no words for ${x}`);\n'
    )
    try:
        found = words.bypassing_sentences(script)
    finally:
        script.unlink()
    assert [line.split(": ", 1)[1] for line in found] == [
        "'Connected'",
        "'Online'",
        "'Hello x, welcome'",
    ]


def _swedish_tablet(lab: Lab, app: FastAPI, code: str, **body: Any) -> tuple[TestClient, str]:
    _enrol(lab, code=code, **body)
    link = lab.experimenter.post(f"/api/v1/studies/{lab.study}/participants/{code}/link").json()
    tablet = TestClient(app)
    first = tablet.get(f"/t/{link['token']}")
    token = FORM_TOKEN.search(first.text)
    assert token, first.text
    return tablet, token[1]


@sqlite_only("rendering only; the pages' SQL is covered by the robot test")
def test_the_tablets_error_and_choice_pages_speak_only_the_participants_language(
    swedish_lab: Lab, app: FastAPI, user_client: UserClientFactory
) -> None:
    """The tablet's refusals (an unknown page, an expired form, locked answers, a replaced link)
    in Swedish show Swedish only: the catalogue's sentence, or none but the heading; and the
    language-choice page asks in every language offered, each in its own words."""
    lab = swedish_lab
    protocol = parse_protocol(_swedish_text()).protocol
    swedish = words.known_texts("sv", protocol)
    tablet, token = _swedish_tablet(lab, app, "S1", language="sv")
    unknown = tablet.get("/tablet/nothing-here")
    assert unknown.status_code == 404 and "Den här sidan finns inte" in unknown.text
    expired = tablet.post("/tablet/consent", data={"csrf_token": "x", "accept": "yes"})
    assert expired.status_code == 403
    admin = user_client(Role.ADMIN)
    assert admin.post(f"/studies/{lab.study}/participants/S1/lock").status_code == 200
    locked = tablet.post("/tablet/consent", data={"csrf_token": token, "accept": "yes"})
    assert locked.status_code == 409 and "Svaren för S1 är låsta" in locked.text
    lab.experimenter.post(f"/api/v1/studies/{lab.study}/participants/S1/link")  # replaced
    replaced = tablet.get("/tablet")
    assert replaced.status_code == 401 and "Den här länken till surfplattan gäller inte" in (
        replaced.text
    )
    for page in (unknown, expired, locked, replaced):
        assert 'lang="sv"' in page.text and 'class="tablet-page"' in page.text
        assert words.unexplained(words.fragments(page.text), swedish, also=["S1"]) == [], (
            page.request.url
        )

    chooser, _ = _swedish_tablet(lab, app, "S2")
    choice = chooser.get("/tablet")
    assert choice.url.path == "/tablet/language"
    assert '<span lang="sv">Välj ditt språk</span>' in choice.text
    assert '<span lang="en">Choose your language</span>' in choice.text
    both = words.known_texts("sv", protocol) + words.known_texts("en", protocol)
    shown = words.fragments(choice.text)
    assert words.unexplained(shown, both, also=["Svenska", "English"]) == []


# ------------------------------------------------------------------------- the command line


@sqlite_only("the command line's parsing and messages; the SQL is the services' (tested above)")
def test_the_command_line_enrols_in_a_language_and_changes_it_before_a_session(
    swedish_lab: Lab, database_url: str
) -> None:
    code, out, _ = cli_run(
        database_url, "participant", "enroll", "--study", "sv", "--code", "C1", "--language", "sv"
    )
    assert code == 0 and "language sv" in out
    code, _, err = cli_run(
        database_url, "participant", "enroll", "--study", "sv", "--code", "C2", "--language", "fi"
    )
    assert code == 2 and err == "error: study 'sv' is not run in 'fi': its languages are en, sv\n"
    code, out, _ = cli_run(
        database_url, "participant", "language", "--study", "sv", "--code", "C1", "--language", "en"
    )
    assert code == 0 and out == "C1 in 'sv' now takes part in en\n"
    listed = swedish_lab.experimenter.get("/api/v1/studies/sv/participants").json()
    assert [(p["code"], p["language"]) for p in listed] == [("C1", "en")]


@sqlite_only("no database: the catalogues are files")
def test_the_command_line_lists_and_checks_the_interface_languages(database_url: str) -> None:
    code, out, _ = cli_run(database_url, "languages", "list")
    assert code == 0
    assert [line.split()[0] for line in out.splitlines()] == ["de", "en", "sv"]
    assert all(line.endswith("complete") for line in out.splitlines())
    code, out, _ = cli_run(database_url, "languages", "check", "de")
    assert (code, out) == (0, "de: complete (Deutsch)\n")
    code, _, err = cli_run(database_url, "languages", "check", "fi")
    assert code == 1 and err.startswith("fi: no interface catalogue for 'fi'")
    code, _, err = cli_run(database_url, "languages", "check", "Finnish")
    assert code == 2 and "not a language code" in err


def test_a_new_language_starts_from_the_sources(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """`trustlab languages update fi` writes a catalogue with every message to translate,
    which the checks then refuse until it is translated."""
    monkeypatch.setattr(catalogues, "LOCALES", tmp_path)
    catalogues.ui_languages.cache_clear()
    try:
        code, out, _ = cli_run("sqlite://", "languages", "update", "fi")
        assert code == 0 and out.endswith(
            f"{len(extract())} messages, {len(extract())} to translate\n"
        )
        assert catalogues.ui_languages() == ["fi"]
        assert catalogues.check_language("fi") is not None  # untranslated: refused
    finally:
        catalogues.ui_languages.cache_clear()
        catalogues.catalogue.cache_clear()


# ------------------------------------------------------------------------- exports


def test_exports_carry_each_participants_language(swedish_lab: Lab) -> None:
    """On both databases: the language column in the wide, long and steps tables and the
    codebook, and the report's count per language."""
    lab = swedish_lab
    for code, language in (("S1", "sv"), ("E1", "en")):
        _enrol(lab, code=code, language=language)
        _seat(lab, code)
        _fill_tablet(lab, code)
        lab.start_session()
        lab.run_session()  # the practice run: not in the step log
        lab.start_session()
        step = lab.prompt("conation")
        lab.answer(step["step_id"], "yes")
        ended = lab.experimenter.post(f"/api/v1/stations/{lab.station}/sessions/current/end")
        assert ended.status_code == 200, ended.text
    with lab.database.read_session() as db:
        dataset = study_data.load_dataset(
            db, scope=Scope.every_site(), study=studies.get_study(db, "sv")
        )
    expected = {"S1": "sv", "E1": "en"}
    wide = wide_table(dataset)
    assert dict(zip(wide["participant"], wide["language"], strict=True)) == expected
    for table in (long_table(dataset), steps_table(dataset)):
        assert list(table.columns[:3]) == ["participant", "condition", "language"]
        assert {
            p: table[table.participant == p]["language"].unique().tolist() for p in expected
        } == {p: [language] for p, language in expected.items()}
    assert "transcript_engine" in steps_table(dataset).columns  # how each answer was given
    book = codebook_table(dataset)
    described = book[book.column == "language"]
    assert sorted(described.file) == ["long", "steps", "wide"]
    assert set(described.label) == {"Language the participant took part in (ISO 639 code)"}
    counts = _per_language(dataset.participants)
    assert "<h3>Languages</h3>" in counts and ">sv<" in counts and ">en<" in counts
    assert _per_language(dataset.participants[dataset.participants.language == "sv"]) == ""

    # Each item's Swedish wording and the translation's source (issue 48, item 13).
    swedish = parse_protocol(_swedish_text()).protocol.in_language("sv")
    tipi = book[(book.file == "wide") & (book.column == "tipi_1")].iloc[0]
    assert tipi.label_sv == swedish.questionnaires.instruments[2].items[0].text
    assert (
        tipi.citation_sv.startswith("Gosling, S. D.") and "Arbetsöversättning" in tipi.citation_sv
    )
    assert "Translation: Working translation made for trustlab's example" in tipi.citation_sv
    assert set(book[book.file == "steps"].label_sv) == {""}  # no wording: not an item
    described = codebook_json(dataset)
    assert described["languages"] == ["en", "sv"]
    assert described["translations"]["sv"]["source"].startswith("Working translation")
    nars = next(i for i in described["instruments"] if i["name"] == "nars")
    assert nars["translations"]["sv"]["items"]["nars_1"] == (
        swedish.questionnaires.instruments[3].items[0].text
    )
    methods = languages_paragraph(dataset.protocol)
    assert "one of two languages: en and sv" in methods
    assert "sv: Working translation made for trustlab's example protocol" in methods
    assert any("Arbetsöversättning" in r for r in translation_references(dataset.protocol))
    report = build_report(dataset)
    assert html.escape(methods) in report and "[sv]</li>" in report


@sqlite_only("the page's form and refusals; the service's SQL is tested above")
def test_staff_change_the_language_on_the_participant_page(
    swedish_lab: Lab, user_client: UserClientFactory
) -> None:
    lab = swedish_lab
    _enrol(lab, code="S1", language="sv")
    page = lab.experimenter.get("/studies/sv/participants/S1")
    assert "takes part in <strong>sv</strong>" in page.text
    token = re.search(r'name="csrf_token" value="([^"]+)"', page.text)
    assert token
    changed = lab.experimenter.post(
        "/studies/sv/participants/S1/language", data={"csrf_token": token[1], "language": "en"}
    )
    assert changed.status_code == 200 and "S1 now takes part in English." in changed.text
    refused = lab.experimenter.post(
        "/studies/sv/participants/S1/language", data={"csrf_token": token[1], "language": "fi"}
    )
    assert refused.status_code == 422
    assert "study &#39;sv&#39; is not run in &#39;fi&#39;" in refused.text


@sqlite_only("rendering only")
def test_the_console_shows_the_seated_participants_language(swedish_lab: Lab) -> None:
    _enrol(swedish_lab, code="S1", language="sv")
    _seat(swedish_lab, "S1")
    console = swedish_lab.experimenter.get(f"/stations/{swedish_lab.station}")
    assert console.status_code == 200
    assert 'class="console-language"' in console.text and ">sv</span>" in console.text


@sqlite_only("rendering only; the step SQL is covered by the robot test")
def test_staff_read_the_protocols_language_beside_a_participants_translated_words(
    swedish_lab: Lab,
) -> None:
    """The console's "Next:" line names instruments in the protocol's own language (an English
    sentence with Swedish titles in it helps nobody), and a question asked in Swedish has its
    English beside it on the console and in the participant's timeline (issue 48, item 14)."""
    lab = swedish_lab
    _enrol(lab, code="S1", language="sv")
    _seat(lab, "S1")
    tablet = tablet_client(lab.app, lab, "S1")
    assert tablet.post("/api/v1/tablet/consent", json={"accept": True}).status_code == 200
    console = lab.experimenter.get(f"/stations/{lab.station}")
    expected = re.search(r"<strong>Next:</strong> ([^<]*)</p>", console.text)
    assert expected, console.text
    assert html.unescape(expected[1]) == (
        "waiting for S1 to fill in on the tablet: About you, Your experience, "
        "Ten-Item Personality Inventory, Attitudes towards robots"
    )
    fill_pre_study(tablet)
    lab.start_session()
    prompt = lab.prompt("cognition")
    english = parse_protocol(_swedish_text()).protocol.category("cognition").questions
    gloss = f'<span class="gloss muted">({english[int(str(prompt["action"]))]})</span>'
    asked = lab.experimenter.get(f"/stations/{lab.station}").text
    assert f"“{prompt['question']}”</strong> {gloss}" in asked  # the Wizard-of-Oz card
    assert f"Robot: “{prompt['question']}” {gloss}" in asked  # the last step
    lab.answer(prompt["step_id"], "yes")
    record = lab.experimenter.get(f"/studies/{lab.study}/participants/S1").text
    assert f"{prompt['question']} {gloss.replace('muted', 'muted small')}</td>" in record
