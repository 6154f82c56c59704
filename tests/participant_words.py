"""What may stand on a participant's screen: the catalogue's words and the protocol's, nothing else.

Shared by tests/app/test_languages.py (templates, scripts and the tablet's pages as the server
renders them) and tests/e2e/test_languages.py (the room as Chromium draws it). Three checks:

- :func:`participant_templates` follows every template a participant route renders through what
  it extends and includes, so a new tablet page is found without anyone listing it;
- :func:`literal_words` finds text in a template that is neither marked for translation nor in an
  element marked ``data-staff`` (the operator's device-key form: English on purpose);
- :func:`bypassing_sentences` finds a sentence in a script that is not the message of ``_()`` or
  ``show()`` (nor ``staff()``, English on purpose; nor a console message);
- :func:`unexplained` finds visible text of a rendered page that is not a text of the catalogue or
  the protocol in the page's language.
"""

from __future__ import annotations

import fnmatch
import re
from collections.abc import Iterable
from html.parser import HTMLParser
from pathlib import Path
from typing import ClassVar

from jinja2 import Environment, meta

from app.i18n.catalogues import read_catalog
from app.i18n.extract import PARTICIPANT_SCRIPTS, PARTICIPANT_TEMPLATES
from app.i18n.protocol_texts import text_slots
from app.protocol import Protocol
from app.settings import REPO_ROOT

TEMPLATES = REPO_ROOT / "templates"
PARTICIPANT_ROUTES = ("app/web/tablet_pages.py", "app/web/room.py", "app/http.py")
"""The modules that render participant pages (the tablet's, the room's, the tablet's errors)."""
STAFF_ONLY_IN_ROUTES = {"error.html"}
"""Rendered by app/http.py for staff pages only (its tablet paths render tablet_message.html)."""


def is_participant_template(name: str) -> bool:
    """Whether ``name`` (under templates/) is declared a participant template."""
    return any(fnmatch.fnmatch(name, pattern) for pattern in PARTICIPANT_TEMPLATES)


def _references(name: str) -> set[str]:
    source = (TEMPLATES / name).read_text(encoding="utf-8")
    environment = Environment(extensions=["jinja2.ext.i18n"])
    found = meta.find_referenced_templates(environment.parse(source))
    return {reference for reference in found if reference}


def participant_templates() -> set[str]:
    """Every template a participant sees: those the participant routes render, every page that
    extends the tablet's base page, and all that these extend or include, transitively."""
    rendered = set()
    for module in PARTICIPANT_ROUTES:
        text = (REPO_ROOT / module).read_text(encoding="utf-8")
        rendered |= set(re.findall(r"\"(\w+\.html)\"", text)) - STAFF_ONLY_IN_ROUTES
    every = {path.name for path in TEMPLATES.glob("*.html")}
    rendered |= {name for name in every if "tablet_base.html" in _references(name)}
    seen: set[str] = set()
    todo = list(rendered)
    while todo:
        name = todo.pop()
        if name not in seen:
            seen.add(name)
            todo.extend(_references(name))
    return seen


class _Text(HTMLParser):
    """The text and the words in attributes of an HTML page (or template), outside script and
    style and outside elements marked ``data-staff``."""

    VOID: ClassVar[set[str]] = {
        "meta",
        "link",
        "input",
        "br",
        "img",
        "hr",
        "source",
        "area",
        "base",
        "col",
        "wbr",
    }
    WORDY = ("title", "aria-label", "placeholder", "alt", "aria-keyshortcuts")

    def __init__(self) -> None:
        super().__init__(convert_charrefs=True)
        self.fragments: list[str] = []
        self._stack: list[tuple[str, bool]] = []

    def _skipping(self) -> bool:
        return any(skip for _, skip in self._stack)

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        named = dict(attrs)
        skip = tag in ("script", "style") or "data-staff" in named
        if not skip and not self._skipping():
            self.fragments += [named[a] or "" for a in self.WORDY if named.get(a)]
        if tag not in self.VOID:
            self._stack.append((tag, skip))

    def handle_startendtag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        self.handle_starttag(tag, attrs)
        if tag not in self.VOID:
            self.handle_endtag(tag)

    def handle_endtag(self, tag: str) -> None:
        for index in range(len(self._stack) - 1, -1, -1):
            if self._stack[index][0] == tag:
                del self._stack[index:]
                return

    def handle_data(self, data: str) -> None:
        if not self._skipping() and data.strip():
            self.fragments.append(data)


def fragments(page: str) -> list[str]:
    """The pieces of text a page shows (and says in its title, labels and placeholders)."""
    parser = _Text()
    parser.feed(page)
    return [" ".join(f.split()) for f in parser.fragments]


LETTERS = re.compile(r"[^\W\d_]{2,}")
"""A word: two or more letters in a row (a lone letter, a number or a symbol says nothing)."""


def literal_words(name: str) -> list[str]:
    """Words written literally in a participant template, outside ``{% trans %}``, ``_()`` and
    elements marked ``data-staff``."""
    source = (TEMPLATES / name).read_text(encoding="utf-8")
    source = re.sub(r"{#.*?#}", " ", source, flags=re.S)
    source = re.sub(r"{%-?\s*trans\b.*?endtrans\s*-?%}", " ", source, flags=re.S)
    source = re.sub(r"{%.*?%}", " ", source, flags=re.S)
    source = re.sub(r"{{.*?}}", " ", source, flags=re.S)
    attribute = re.compile(r'^[\w-]+="[^"]*"$')  # a block of attributes, e.g. body_attrs
    return [f for f in fragments(source) if LETTERS.search(f) and not attribute.match(f)]


# ------------------------------------------------------------------------------ scripts


def participant_scripts() -> set[Path]:
    """The declared participant scripts, the scripts the participant templates load, and every
    module those import."""
    found = {p for pattern in PARTICIPANT_SCRIPTS for p in REPO_ROOT.glob(pattern)}
    for name in participant_templates():
        text = (TEMPLATES / name).read_text(encoding="utf-8")
        found |= {REPO_ROOT / "static" / s for s in re.findall(r"asset\('(js/[\w/.-]+)'\)", text)}
    todo = list(found)
    while todo:
        script = todo.pop()
        for module in re.findall(r"from\s+\"(\.{1,2}/[\w/.-]+)\"", script.read_text()):
            imported = (script.parent / module).resolve()
            if "vendor" not in imported.parts and imported not in found:
                found.add(imported)
                todo.append(imported)
    return found


def _literals(code: str) -> Iterable[tuple[int, str]]:
    """(offset, text) of every string and template literal of a script (``${…}`` shown as x),
    skipping comments and regular-expression literals."""
    i, n, last = 0, len(code), ""
    while i < n:
        c = code[i]
        if code.startswith("//", i):
            i = code.find("\n", i) if "\n" in code[i:] else n
        elif code.startswith("/*", i):
            i = code.index("*/", i) + 2
        elif c in "\"'`":
            j, text = i + 1, []
            while code[j] != c:
                if code[j] == "\\":
                    text.append(code[j : j + 2])
                    j += 2
                elif c == "`" and code.startswith("${", j):
                    depth, j = 1, j + 2
                    while depth:
                        depth += {"{": 1, "}": -1}.get(code[j], 0)
                        j += 1
                    text.append("x")
                else:
                    text.append(code[j])
                    j += 1
            yield i, "".join(text)
            i, last = j + 1, c
        elif c == "/" and (last in "(,=:[!&|?{};+" or last == ""):
            j, in_class = i + 1, False
            while code[j] != "/" or in_class:
                if code[j] == "\\":
                    j += 1
                elif code[j] == "[":
                    in_class = True
                elif code[j] == "]":
                    in_class = False
                j += 1
            i, last = j + 1, "/"
        else:
            if not c.isspace():
                last = c if not (c.isalnum() or c in "_$") else "a"
                if code.startswith("return", i) and not code[i + 6 : i + 7].isalnum():
                    last, i = "", i + 6
                    continue
            i += 1


SENTENCE = re.compile(r"[^\W\d_]{2,}[\s ]+[^\W\d_]|^[A-Z][a-z]+[.…!?:]*$")
"""A literal that reads as words to a person: two words, or one capitalised word ("Connected")."""

MARKED = re.compile(
    r"(?:\b_|\bstaff|\bconsole\.\w+)\(\s*$"  # _("…"), staff("…"), console.warn("…")
    r"|\bshow\((?:[^()]|\([^()]*\))*,\s*$"  # show(node, "…")
    # The socket's own words (a close reason, a refusal's detail): the room shows them to
    # English rooms only (serverWords in static/js/room.js), as it does the server's.
    r"|\.close\(\s*\d+\s*,\s*$|\b(?:reason|detail)(?:\s*:|\s*\|\|)\s*$"
    # A CSS selector ("main form"): words for the browser, not for a person.
    r"|\b(?:querySelector(?:All)?|closest|matches)\(\s*$"
)

TECHNICAL = {"Bearer x"}
"""Literals that read like words but are protocol, not language (an HTTP auth scheme)."""


def bypassing_sentences(script: Path) -> list[str]:
    """Sentences in a participant script that do not go through the catalogue."""
    code = script.read_text(encoding="utf-8")
    found = []
    for offset, text in _literals(code):
        if text in TECHNICAL or not SENTENCE.search(text):
            continue
        if not MARKED.search(code[max(0, offset - 200) : offset]):
            line = code.count("\n", 0, offset) + 1
            found.append(f"{script.relative_to(REPO_ROOT)}:{line}: {text!r}")
    return found


# ------------------------------------------------------------------------------ rendered pages


def known_texts(language: str, protocol: Protocol | None = None) -> list[str]:
    """Every text of ``language``'s catalogue (each plural form too) and of the protocol in
    ``language``, longest first."""
    texts: set[str] = set()
    for message in read_catalog(language):
        if message.id:
            strings = message.string if isinstance(message.string, tuple) else (message.string,)
            texts.update(s for s in strings if s)
    if protocol is not None:
        localised = protocol.in_language(language)
        for slot in text_slots(localised.model_dump(mode="json")):
            texts.update([slot.source] if isinstance(slot.source, str) else slot.source)
    return sorted(texts, key=len, reverse=True)


def _pattern(text: str) -> str:
    escaped = re.escape(" ".join(text.split()))
    return re.sub(r"%\\\(\w+\\\)[sd]", ".+?", escaped)


def unexplained(shown: Iterable[str], known: list[str], *, also: Iterable[str] = ()) -> list[str]:
    """The pieces of ``shown`` with a word that is not part of a known text (nor of ``also``:
    what the page shows of the participant, e.g. their code)."""
    worded = [t for t in [*also, *known] if LETTERS.search(re.sub(r"%\(\w+\)[sd]", "", t))]
    patterns = [re.compile(_pattern(t), re.IGNORECASE) for t in worded]
    normalised = [" ".join(t.split()).lower() for t in [*known, *also]]
    left = []
    for piece in shown:
        piece = " ".join(piece.split())
        if not LETTERS.search(piece) or any(piece.lower() in text for text in normalised):
            continue
        rest = piece
        for pattern in patterns:
            rest = pattern.sub(" ", rest)
            if not LETTERS.search(rest):
                break
        if LETTERS.search(rest):
            left.append(piece)
    return left
