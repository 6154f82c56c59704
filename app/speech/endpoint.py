"""Hearing that a participant has finished speaking (endpointing), frame by frame.

The room streams audio while a question is open and must decide when to stop listening and
answer. Speech has started once a few frames in a short stretch sound like speech (a click or a
door is one frame, a word is several); it has ended once, after that, the last
:data:`END_SILENCE_SECONDS` were nearly all non-speech (a stray noisy frame in the pause does not
restart the wait). Frames are classified by pocketsphinx's own voice-activity detector.
"""

from __future__ import annotations

from collections import deque

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
        self.last_speech_frame = -1
        """Index (in :data:`FRAME_SECONDS` frames) of the last frame classified as speech."""

    def feed(self, pcm: bytes) -> None:
        """Classify every whole frame in ``pcm`` (a partial frame waits for the next call)."""
        data = self._pending + pcm
        whole = len(data) - len(data) % self._frame_bytes
        for start in range(0, whole, self._frame_bytes):
            self._frame(self._vad.is_speech(data[start : start + self._frame_bytes]))
        self._pending = data[whole:]

    def _frame(self, speech: bool) -> None:
        if speech:
            self.last_speech_frame = self.frames
        self.frames += 1
        self._recent.append(speech)
        self._closing.append(speech)
        if not self.speech_started and sum(self._recent) >= START_SPEECH_FRAMES:
            self.speech_started = True
            self._closing.clear()
        elif self.speech_started and not self.speech_ended:
            full = len(self._closing) == self._closing.maxlen
            self.speech_ended = full and sum(self._closing) <= END_SPEECH_FRAMES_ALLOWED
