"""What both recognisers' tests share: the shipped recordings with the answer each must give,
room-quiet audio to put around words, and streaming audio in as a room does."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from app.speech.engines import UtteranceLike

DATA = Path(__file__).parent / "data"
SAMPLE_RATE = 16000
FRAME_BYTES = SAMPLE_RATE // 50 * 2
"""20 ms of 16-bit audio: what the room streams at a time."""

SHIPPED_ANSWERS = [
    ("yes", "yes"),
    ("yeah", "yes"),
    ("sure", "yes"),
    ("no", "no"),
    ("nope", "no"),
    ("no_way", "no"),
    ("maybe", None),
    ("i_dont_know", None),
    ("cough", None),
    ("silence", None),
]
"""Each WAV under data/ and the answer it must give (None: not an answer, asked again)."""


def quiet(seconds: float, seed: int = 0) -> bytes:
    """Room-quiet audio (about -60 dBFS), as a microphone sends between words."""
    noise = np.random.default_rng(seed).normal(0, 30, int(seconds * SAMPLE_RATE))
    return noise.astype("<i2").tobytes()


def feed_in_frames(utterance: UtteranceLike, pcm: bytes) -> int | None:
    """Feed ``pcm`` 20 ms at a time, as a room streams it; the byte offset of the frame on which
    the utterance heard the end of speech (None: it never did)."""
    ended_at = None
    for start in range(0, len(pcm), FRAME_BYTES):
        utterance.feed(pcm[start : start + FRAME_BYTES])
        if ended_at is None and utterance.speech_ended:
            ended_at = start
    return ended_at
