"""Which interface messages exist: found in the participant-facing sources, as Babel finds them.

The catalogues must hold exactly these (tests/app/test_catalogues.py), so a sentence added to a
tablet page or the room without a translation fails the tests instead of reaching a participant
in English. ``trustlab languages new/update`` writes them into a ``.po`` file for a translator.
"""

from __future__ import annotations

from babel.messages.catalog import Catalog
from babel.messages.extract import extract_from_dir
from babel.messages.pofile import write_po

from app.i18n.catalogues import DOMAIN, SOURCE_LANGUAGE, path_of, read_catalog
from app.settings import REPO_ROOT

PARTICIPANT_TEMPLATES = (
    "tablet_*.html",
    "_tablet_progress.html",
    "_rules.html",
    "room.html",
    "online_*.html",
)
"""The templates (under templates/) whose words participants read. Every template a tablet or
room route renders, and everything it extends or includes, must be one of these, and their only
words are marked for translation (or, the room's device-key form, marked ``data-staff``):
tests/app/test_languages.py fails on a new one left out or a literal word in one."""

PARTICIPANT_SCRIPTS = (
    "static/js/room.js",
    "static/js/room/*.js",
    "static/js/tablet.js",
    "static/js/online_check.js",
)
"""The scripts participant pages load: every sentence in them goes through ``_()``/``show()``
(or ``staff()``, English on purpose for the lab's staff); tests/app/test_languages.py scans them
and the scripts the participant templates load for any other."""

SOURCES: list[tuple[str, str]] = [
    *((f"templates/{pattern}", "jinja2.ext:babel_extract") for pattern in PARTICIPANT_TEMPLATES),
    *((pattern, "javascript") for pattern in PARTICIPANT_SCRIPTS),
    ("app/**.py", "python"),
]
"""Where participants' words are written, and how to read each kind of file. Staff pages are
English only and not listed."""

OPTIONS = {
    "templates/**.html": {
        "trim_blocks": "true",
        "lstrip_blocks": "true",
        "newstyle_gettext": "true",
    },
}
KEYWORDS = {
    "_": None,  # templates' _() and the room's scripts
    "gettext": None,
    "ngettext": (1, 2),
    "Message": None,  # Python: app.i18n.catalogues.Message
    "show": (2,),  # the room's scripts: show(node, message) (static/js/room/words.js)
}


def extract() -> Catalog:
    """Every interface message of the sources, with where it occurs."""
    found = Catalog(locale=None, domain="messages", project="trustlab", fuzzy=False)
    for filename, lineno, message, _comments, context in extract_from_dir(
        REPO_ROOT,
        method_map=SOURCES,
        options_map=OPTIONS,
        keywords=KEYWORDS,
        directory_filter=_not_vendored,
    ):
        found.add(message, locations=[(filename, lineno)], context=context)
    return found


def _not_vendored(path: str) -> bool:
    """Leave out other people's code, the tests, and the robot bridges (which say only the
    protocol's texts, and whose ROS messages are also called ``Message``)."""
    skipped = ("node_modules", "vendor", ".venv", "tests", "robots")
    return not any(part in path.split("/") for part in skipped)


def update(language: str) -> tuple[int, int]:
    """Bring the language's ``.po`` file in line with the sources: new messages added
    untranslated, gone ones dropped, translations kept. Creates the file for a new language.
    Returns (messages, untranslated)."""
    template = extract()
    path = path_of(language)
    if path.is_file():
        catalog = read_catalog(language)
        catalog.update(template, no_fuzzy_matching=True)
        catalog.obsolete.clear()
    else:
        catalog = Catalog(
            locale=language.replace("-", "_"),
            domain=DOMAIN,
            project="trustlab",
            copyright_holder="the trustlab authors",
            fuzzy=False,
        )
        catalog.update(template, no_fuzzy_matching=True)
        path.parent.mkdir(parents=True, exist_ok=True)
    if language == SOURCE_LANGUAGE:  # the source's catalogue says what the code says
        for message in catalog:
            if message.id:
                message.string = message.id
    with path.open("wb") as handle:
        write_po(handle, catalog, width=100, include_lineno=False)
    counted = [m for m in catalog if m.id]
    missing = [
        m for m in counted if not (all(m.string) if isinstance(m.string, tuple) else m.string)
    ]
    return len(counted), len(missing)
