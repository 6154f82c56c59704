"""The interface's message catalogues: complete for every shipped language, in step with the
sources, refused in one line when broken, and right-to-left where the language says so."""

from __future__ import annotations

import functools
import io

import pytest
from babel.messages.catalog import Catalog
from babel.messages.mofile import write_mo
from babel.support import Translations
from jinja2 import Environment

from app.i18n import catalogues
from app.i18n.catalogues import Catalogue, Message, catalogue, catalogue_problems, read_catalog
from app.i18n.extract import extract
from app.web import templating

SHIPPED = ["de", "en", "sv"]


@functools.cache
def _extracted() -> Catalog:
    """The sources' messages, extracted once for the module (a few seconds each time)."""
    return extract()


def _ids(catalog: Catalog) -> set[str]:
    return {m.id if isinstance(m.id, str) else m.id[0] for m in catalog if m.id}


def test_english_swedish_and_german_ship_complete() -> None:
    assert catalogues.ui_languages() == SHIPPED
    for language in SHIPPED:
        assert catalogue_problems(read_catalog(language)) == [], language
        assert catalogue(language).language == language


@pytest.mark.parametrize("language", SHIPPED)
def test_every_catalogue_holds_exactly_the_messages_the_sources_use(language: str) -> None:
    """A sentence added to a participant page without a translation fails here (run
    `trustlab languages update` and translate), as does one left behind after removal."""
    in_sources, in_catalogue = _ids(_extracted()), _ids(read_catalog(language))
    assert in_sources - in_catalogue == set(), "untranslated: add them to the catalogue"
    assert in_catalogue - in_sources == set(), "no longer used: remove them"


def test_the_sources_mark_what_participants_read() -> None:
    """The extraction finds each kind of source (a template, a service sentence, an error page)."""
    ids = _ids(_extracted())
    assert {"Continue", "Please answer this question.", "This page has expired"} <= ids
    assert "Choose one of %(low)d–%(high)d." in ids  # a Message with values


def _catalog(language: str, pairs: dict[str, str], *, fuzzy: str = "") -> Catalog:
    catalog = Catalog(locale=language, domain="messages")
    for source, translation in pairs.items():
        catalog.add(source, translation, flags=("fuzzy",) if source == fuzzy else ())
    return catalog


def test_a_broken_catalogue_is_refused_naming_the_message() -> None:
    problems = catalogue_problems(
        _catalog(
            "sv",
            {
                "Enter a number from %(low)d to %(high)d.": "Skriv ett tal till %(high)d.",
                "Continue": "",
                "Thank you": "Tack",
            },
            fuzzy="Thank you",
        )
    )
    assert problems == [
        "'Enter a number from %(low)d to %(high)d.': the translation's placeholders ['high'] "
        "differ from the source's ['high', 'low']",
        "'Continue': not translated",
        "'Thank you': marked fuzzy (check it, then remove the flag)",
    ]


def test_a_language_without_a_catalogue_is_refused_in_one_line() -> None:
    reason = catalogues.check_language("fi")
    assert reason is not None and "\n" not in reason
    assert reason.startswith("no interface catalogue for 'fi'")


def test_a_sentence_is_said_in_the_catalogues_language_with_its_values() -> None:
    message = Message("Enter a number from %(low)d to %(high)d.", low=18, high=99)
    assert message == "Enter a number from 18 to 99."  # it is the English sentence
    assert catalogue("sv").say(message) == "Skriv ett tal från 18 till 99."
    assert catalogue("de").say(message) == "Geben Sie eine Zahl von 18 bis 99 ein."


def _in_memory(language: str, pairs: dict[str, str]) -> Catalogue:
    buffer = io.BytesIO()
    write_mo(buffer, _catalog(language, pairs))
    buffer.seek(0)
    return Catalogue(language, Translations(buffer), pairs)


def test_a_right_to_left_language_sets_the_pages_direction() -> None:
    arabic = _in_memory("ar", {"Continue": "متابعة"})
    context = templating._language_context(arabic)
    assert (context["lang"], context["dir"]) == ("ar", "rtl")
    page = Environment(autoescape=True).from_string(
        '<html lang="{{ lang }}" dir="{{ dir }}"><button>{{ _("Continue") }}</button></html>'
    )
    assert page.render(context) == '<html lang="ar" dir="rtl"><button>متابعة</button></html>'
    assert templating._language_context(catalogue("sv"))["dir"] == "ltr"
