"""Recorded answers: the participant's voice, stored with a spoken answer only where the study's
protocol sets ``[speech] record_audio = true`` (and its consent text says so, app.protocol).

Everywhere else the audio of an answer lives in the server's memory while it is recognised and is
gone with the utterance: nothing here is called, and ``answer_audio`` stays empty.
"""

from __future__ import annotations

import io
import wave

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from app.speech.engines import SAMPLE_RATE
from app.tables import Answer, AnswerAudio

SAMPLE_WIDTH = 2
"""Bytes per sample: 16-bit signed, little-endian, mono."""


def as_wav(pcm: bytes, sample_rate: int = SAMPLE_RATE) -> bytes:
    """Raw 16-bit mono PCM as a WAV file."""
    out = io.BytesIO()
    with wave.open(out, "wb") as wav:
        wav.setnchannels(1)
        wav.setsampwidth(SAMPLE_WIDTH)
        wav.setframerate(sample_rate)
        wav.writeframes(pcm)
    return out.getvalue()


def store(db: Session, *, answer_id: int, pcm: bytes) -> None:
    """Keep the audio an answer was recognised from (once: a replayed answer keeps the first)."""
    if db.get(AnswerAudio, answer_id) is not None:
        return
    answer = db.get(Answer, answer_id)
    assert answer is not None
    db.add(
        AnswerAudio(
            answer_id=answer_id,
            participant_id=answer.participant_id,
            wav=as_wav(pcm),
            seconds=len(pcm) / (SAMPLE_RATE * SAMPLE_WIDTH),
        )
    )
    db.commit()


def count(db: Session) -> int:
    """How many recorded answers the database holds."""
    return int(db.scalar(select(func.count()).select_from(AnswerAudio)) or 0)
