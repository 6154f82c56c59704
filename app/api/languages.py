"""The interface's words per language, for the room's scripts (which cannot render templates).

Public, like the static files it stands beside: a catalogue holds only interface sentences, no
study's texts. The room fetches the seated participant's language when it changes
(static/js/room/words.js).
"""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import JSONResponse
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
def words(language: str) -> JSONResponse:
    """The interface catalogue of ``language`` (404 naming the shipped ones otherwise)."""
    if language not in ui_languages():
        raise NotFound(
            f"no interface catalogue for {language!r}; shipped: {', '.join(ui_languages())}"
        )
    words = catalogue(language)
    body = WordsOut(language=language, direction=words.direction, messages=words.messages)
    response = JSONResponse(body.model_dump())
    response.headers["Cache-Control"] = "public, max-age=300"
    return response
