"""Speech synthesis on the server, for room clients whose browser has no voices.

Headless and minimal Linux installs (and some kiosk browsers) have no speech-synthesis voices, so
the room would show captions only. The server synthesises the line with espeak-ng instead (the
Debian package ``espeak-ng``; offline, free to use) and the page plays the WAV. Each line is
synthesised once per process and kept in memory: a study has a few dozen lines, each asked many
times. Without espeak-ng the room falls back to captions; the server says why once in its log and
the endpoint answers 503 with one line.
"""

from __future__ import annotations

import logging
import shutil
import struct
import subprocess
import threading
from collections import OrderedDict

from app.errors import TrustlabError

log = logging.getLogger(__name__)

PROGRAM = "espeak-ng"
VOICE = "en-us"
WORDS_PER_MINUTE = 150
SYNTHESIS_TIMEOUT_SECONDS = 15.0
CACHED_LINES = 512
"""More than any study's lines (K questions per category, a reply per level, its rules)."""


class SpeechUnavailable(TrustlabError):
    """The server cannot synthesise speech right now (espeak-ng is missing or failed)."""

    status_code = 503


class Synthesiser:
    """Turns a line into WAV bytes with espeak-ng, once per line (thread-safe)."""

    def __init__(
        self,
        program: str | None = None,
        *,
        voice: str = VOICE,
        words_per_minute: int = WORDS_PER_MINUTE,
        cached_lines: int = CACHED_LINES,
    ) -> None:
        self.program = program if program is not None else shutil.which(PROGRAM)
        self.voice = voice
        self.words_per_minute = words_per_minute
        self._cached_lines = cached_lines
        self._cache: OrderedDict[str, bytes] = OrderedDict()
        self._lock = threading.Lock()
        self._said_missing = False

    @property
    def available(self) -> bool:
        return self.program is not None

    def wav(self, text: str, language: str = "en") -> bytes:
        """The line spoken in ``language`` (its espeak-ng voice), as a WAV file;
        SpeechUnavailable when it cannot be made."""
        voice = self.voice if language == "en" else language.lower()
        key = f"{voice}\n{text}"
        with self._lock:
            cached = self._cache.get(key)
            if cached is not None:
                self._cache.move_to_end(key)
                return cached
        audio = self._synthesise(text, voice)
        with self._lock:
            self._cache[key] = audio
            while len(self._cache) > self._cached_lines:
                self._cache.popitem(last=False)
        return audio

    def _synthesise(self, text: str, voice: str) -> bytes:
        if self.program is None:
            self._log_missing_once()
            raise SpeechUnavailable(
                "speech synthesis is unavailable: espeak-ng is not installed on the server "
                "(the room shows captions only)"
            )
        command = [self.program, "-v", voice, "-s", str(self.words_per_minute), "--stdout"]
        try:
            done = subprocess.run(  # the text goes in on stdin: never parsed as an option
                command,
                input=text.encode(),
                capture_output=True,
                timeout=SYNTHESIS_TIMEOUT_SECONDS,
                check=False,
            )
        except (OSError, subprocess.TimeoutExpired) as exc:
            log.warning("speech synthesis failed: %s", exc)
            raise SpeechUnavailable(f"speech synthesis failed: {exc}") from None
        if done.returncode != 0 or not done.stdout.startswith(b"RIFF"):
            why = done.stderr.decode(errors="replace").strip().splitlines()[:1]
            log.warning("speech synthesis failed: %s exited %d %s", PROGRAM, done.returncode, why)
            raise SpeechUnavailable(f"speech synthesis failed: {PROGRAM} exited {done.returncode}")
        return with_true_sizes(done.stdout)

    def _log_missing_once(self) -> None:
        if not self._said_missing:
            self._said_missing = True
            log.warning(
                "speech synthesis: %s is not installed (apt-get install espeak-ng); rooms in "
                "browsers without voices show captions only",
                PROGRAM,
            )


def with_true_sizes(wav: bytes) -> bytes:
    """The WAV with its RIFF and data sizes set to what it holds.

    espeak-ng writing to a pipe cannot seek back, so it leaves both at 0x7FFFFFFF; some browsers'
    decoders refuse (or wait for) a file that claims 2 GB."""
    data = wav.find(b"data", 12)
    if not wav.startswith(b"RIFF") or data < 0 or len(wav) < data + 8:
        return wav
    fixed = bytearray(wav)
    fixed[4:8] = struct.pack("<I", len(wav) - 8)
    fixed[data + 4 : data + 8] = struct.pack("<I", len(wav) - data - 8)
    return bytes(fixed)
