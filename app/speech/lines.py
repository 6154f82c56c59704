"""The lines a study's robot may say aloud: what the server agrees to synthesise for it.

The browser room speaks with the browser's voices where it has them, and otherwise plays audio the
server synthesises (app.speech.synthesis). The server synthesises only the study's own lines —
its questions, its replies, the request to answer again and its rules — plus the few the room
adds itself: a device key must not turn the server into a text-to-speech service for any text.
"""

from __future__ import annotations

from app.i18n.catalogues import catalogue
from app.protocol import Protocol

ROOM_LINES = ("Well done! Back to the start for the next run.",)
"""What static/js/room.js says aloud of its own (keep the two in step), as message ids: the room
says them in the participant's language."""

RECOGNISED_LANGUAGES = frozenset({"en"})
"""The languages the server's offline recognisers know (Whisper tiny.en and pocketsphinx's
US-English model are both English only);
a participant in another language answers by button, or by the browser's recogniser where the
protocol allows a cloud recogniser."""


def spoken_lines(protocol: Protocol) -> frozenset[str]:
    """Every line the robot of a study with this protocol may say, in the protocol's language."""
    words = catalogue(protocol.default_language)
    lines: set[str] = {words.gettext(line) for line in ROOM_LINES}
    for category in protocol.categories:
        lines.update(category.questions)
    for level in protocol.replies.levels:
        lines.update(line for line in (level.text, level.yes, level.no) if line)
    lines.add(protocol.speech.reprompt)
    lines.update(protocol.study.rules)
    return frozenset(lines)
