"""The interface's words per language, for the room's scripts (which cannot render templates).

Public, like the static files it stands beside: a catalogue holds only interface sentences, no
study's texts. The room fetches the seated participant's language when it changes
(static/js/room/words.js).
"""

from __future__ import annotations

from fastapi import APIRouter, Response
from pydantic import BaseModel, Field

from app.errors import NotFound
from app.i18n.catalogues import catalogue, ui_languages

router = APIRouter(prefix="/languages", tags=["languages"])


class WordsOut(BaseModel):
    """One language's interface messages (English message id → translation)."""

    language: str
    direction: str = Field(description="rtl or ltr, for HTML's dir attribute.")
    messages: dict[str, str]


@router.get("/{language}/words")
def words(language: str, response: Response) -> WordsOut:
    """The interface catalogue of ``language`` (404 naming the shipped ones otherwise)."""
    if language not in ui_languages():
        raise NotFound(
            f"no interface catalogue for {language!r}; shipped: {', '.join(ui_languages())}"
        )
    found = catalogue(language)
    response.headers["Cache-Control"] = "public, max-age=300"
    return WordsOut(language=language, direction=found.direction, messages=found.messages)
