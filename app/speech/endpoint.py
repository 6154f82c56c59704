"""Hearing that a participant has finished speaking (endpointing), frame by frame.

The room streams audio while a question is open and must decide when to stop listening and
answer. Speech has started once a few frames in a short stretch sound like speech (a click or a
door is one frame, a word is several); it has ended once, after that, the last
:data:`END_SILENCE_SECONDS` were nearly all non-speech (a stray noisy frame in the pause does not
restart the wait).

A frame is speech when pocketsphinx's voice-activity detector says so **and** it is at least
:data:`SPEECH_ABOVE_FLOOR_DB` louder than the room's noise floor. The detector alone calls a
murmur of background talkers speech for ever (in babble at 10 dB SNR an utterance never ended);
the floor is the level the room keeps returning to, tracked per utterance (it falls quickly to a
quieter frame and rises slowly while nobody speaks), so the same rule serves a silent booth and a
noisy lab without a fixed level for either.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np
from pocketsphinx import Vad

FRAME_SECONDS = 0.02
END_SILENCE_SECONDS = 0.6
START_WINDOW_FRAMES = 10
"""Speech starts when :data:`START_SPEECH_FRAMES` of the last this many frames are speech."""
START_SPEECH_FRAMES = 5
END_SPEECH_FRAMES_ALLOWED = 3
"""Frames classified as speech the closing silence may still contain."""
VAD_MODE = 3
"""The detector's strictest mode: the least likely to call room noise speech."""
SPEECH_ABOVE_FLOOR_DB = 7.0
"""How far above the noise floor a frame must be to count as speech: above the frame-to-frame
swing of steady noise and babble (a few dB), below a voice at 10 dB SNR."""
FLOOR_FALL = 0.3
"""Fraction of the gap the floor closes per frame towards a quieter frame (falls within ~0.1 s)."""
FLOOR_RISE_DB = 0.06
"""Most the floor rises per non-speech frame (3 dB a second): a voice cannot lift it, a room
that got louder is followed within seconds."""
HANGOVER_FRAMES = 5
"""Frames after a run of speech that still count as speech for the end of speech (the detector's
own hangover): the fading tail of a word is part of it, so the wait starts after the word. A
lone loud frame (a knock, a peak of the babble) gets none, so it cannot hold the end off."""
QUIETEST_FLOOR_DBFS = -70.0
"""The floor never counts as lower than this: digital silence (a gated or synthetic stream)
would otherwise make any faint hiss 'speech'."""


def level_dbfs(pcm: bytes) -> float:
    """The frame's RMS level in dB relative to full scale (-120 for digital silence)."""
    samples = np.frombuffer(pcm, "<i2").astype(np.float64) / 32768.0
    power = float(np.mean(samples**2)) if samples.size else 0.0
    return 10.0 * math.log10(power) if power > 1e-12 else -120.0


class Endpointer:
    """Feed any amount of 16 kHz int16 audio; :attr:`speech_ended` says when to stop listening."""

    def __init__(self, sample_rate: int = 16000) -> None:
        self._vad = Vad(VAD_MODE, sample_rate, FRAME_SECONDS)
        self._frame_bytes = self._vad.frame_bytes
        self._pending = b""
        self._recent: deque[bool] = deque(maxlen=START_WINDOW_FRAMES)
        self._closing: deque[bool] = deque(maxlen=round(END_SILENCE_SECONDS / FRAME_SECONDS))
        self.frames = 0
        self.speech_started = False
        self.speech_ended = False
        self._hangover = 0
        self._run = 0
        self.floor_dbfs: float | None = None
        """The tracked noise floor (None before the first frame)."""
        self.first_speech_frame = -1
        """Index of the first frame of the stretch that started speech (-1 before it)."""
        self.last_speech_frame = -1
        """Index (in :data:`FRAME_SECONDS` frames) of the last frame classified as speech."""
        self.last_word_frame = -1
        """Index of the last frame of a run of speech frames (two or more: a word, not a lone
        loud frame of the room)."""

    def feed(self, pcm: bytes) -> None:
        """Classify every whole frame in ``pcm`` (a partial frame waits for the next call)."""
        data = self._pending + pcm
        whole = len(data) - len(data) % self._frame_bytes
        for start in range(0, whole, self._frame_bytes):
            speech = self._is_speech(data[start : start + self._frame_bytes])
            self._run = self._run + 1 if speech else 0
            word = self._run >= 2
            if word:
                self.last_word_frame = self.frames
            self._hangover = HANGOVER_FRAMES if word else max(0, self._hangover - 1)
            self._frame(speech, speech or self._hangover > 0)
        self._pending = data[whole:]

    def _is_speech(self, frame: bytes) -> bool:
        level = level_dbfs(frame)
        floor = level if self.floor_dbfs is None else self.floor_dbfs
        loud = level > max(floor, QUIETEST_FLOOR_DBFS) + SPEECH_ABOVE_FLOOR_DB
        speech = loud and self._vad.is_speech(frame)
        if level < floor:
            floor += FLOOR_FALL * (level - floor)
        elif not speech:
            floor += min(FLOOR_RISE_DB, level - floor)
        self.floor_dbfs = floor
        return speech

    def _frame(self, speech: bool, held: bool) -> None:
        """One frame: ``speech`` as classified, ``held`` with the hangover (for the end)."""
        if speech:
            self.last_speech_frame = self.frames
        self.frames += 1
        self._recent.append(speech)
        self._closing.append(held)
        if not self.speech_started and sum(self._recent) >= START_SPEECH_FRAMES:
            self.speech_started = True
            self.first_speech_frame = self.frames - len(self._recent)
            self._closing.clear()
        elif self.speech_started and not self.speech_ended:
            full = len(self._closing) == self._closing.maxlen
            self.speech_ended = full and sum(self._closing) <= END_SPEECH_FRAMES_ALLOWED


class SpeechBuffer:
    """One answer's audio, kept in memory as it streams in, with the endpointer that watches it.

    Both engines' utterances (app.speech.whisper, app.speech.recognizer) hold one: they share
    how audio is taken in, when speech started and ended, and which stretch is decoded; each
    decides only how to decode that stretch. Once closed it takes no more audio, and
    :meth:`padded_speech` is the last use of the audio (it is let go of at once)."""

    def __init__(self, sample_rate: int = 16000) -> None:
        self._endpointer = Endpointer(sample_rate)
        self._frame_bytes = round(sample_rate * FRAME_SECONDS) * 2
        self._audio = bytearray()
        self.closed = False

    @property
    def speech_started(self) -> bool:
        """Something that sounds like speech was heard."""
        return self._endpointer.speech_started

    @property
    def speech_ended(self) -> bool:
        """Speech was heard and then at least ~0.6 s of (near) silence: time to answer."""
        return self._endpointer.speech_ended

    def feed(self, pcm: bytes) -> None:
        """More audio (mono int16 LE, any length)."""
        if self.closed:
            raise RuntimeError("this utterance is finished")
        self._audio += pcm
        self._endpointer.feed(pcm)

    def close(self) -> None:
        """Take no more audio (an utterance finishes once only)."""
        if self.closed:
            raise RuntimeError("this utterance is finished")
        self.closed = True

    def drop(self) -> bool:
        """Close and forget the audio unheard; False if it was closed already."""
        if self.closed:
            return False
        self.closed = True
        self._audio = bytearray()
        return True

    def complete_stretch(self, pad_seconds: float) -> tuple[int, int] | None:
        """Byte offsets (first, end) of the padded speech stretch as it stands, once all of it
        has arrived (the padding after the last speech frame included), else None. While the
        participant stays quiet it is the stretch :meth:`padded_speech` will give, so it can be
        decoded during the endpointer's wait (:meth:`audio`); speech that resumes moves its end.
        Audio is only ever appended, so equal offsets mean equal bytes."""
        if self.closed or not self._endpointer.speech_started:
            return None
        first, end = self._bounds(pad_seconds)
        return (first, end) if len(self._audio) >= end else None

    def audio(self, first: int, end: int) -> bytes:
        """A copy of the audio between two byte offsets (the buffer keeps it)."""
        return bytes(self._audio[first:end])

    def padded_speech(self, pad_seconds: float) -> tuple[int, bytes]:
        """The speech the endpointer marked, with ``pad_seconds`` either side (soft onsets and
        final consonants), as (its first byte's offset in the utterance, its bytes); (0, b"")
        when no speech started. The buffer lets go of the audio."""
        audio = self._audio
        self._audio = bytearray()
        if not self._endpointer.speech_started:
            return 0, b""
        first, last = self._bounds(pad_seconds)
        return first, bytes(audio[first : min(last, len(audio) - len(audio) % 2)])

    def _bounds(self, pad_seconds: float) -> tuple[int, int]:
        """Byte offsets of the padded speech stretch (its end may lie beyond the audio yet).

        It ends after the last *word* (a run of speech frames), not after the last lone frame
        the detector called speech: a knock or a peak of babble in the closing quiet is no part
        of the answer, and would otherwise move the stretch and void a decode started early. A
        final consonant heard as a lone frame right after the word is inside the padding."""
        endpointer = self._endpointer
        pad = round(pad_seconds / FRAME_SECONDS)
        last_frame = endpointer.last_word_frame
        if last_frame < endpointer.first_speech_frame:  # only lone frames: keep them all
            last_frame = endpointer.last_speech_frame
        first = max(0, endpointer.first_speech_frame - pad) * self._frame_bytes
        last = (last_frame + 1 + pad) * self._frame_bytes
        return first, last
