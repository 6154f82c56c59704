"""The endpointer in a noisy room: it must hear a word end in babble (the detector alone calls
background talkers speech for ever) and must not take steady noise for speech."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from app.speech.endpoint import FRAME_SECONDS, Endpointer, SpeechBuffer, level_dbfs
from app.speech.recognizer import SAMPLE_RATE, read_wav

DATA = Path(__file__).parent / "data"
FRAME = round(SAMPLE_RATE * FRAME_SECONDS)
PAD = 0.2


def samples(name: str) -> np.ndarray:
    return np.frombuffer(read_wav(DATA / f"{name}.wav"), "<i2").astype(np.float64)


def rms(signal: np.ndarray) -> float:
    return float(np.sqrt(np.mean(signal**2)))


def babble(seconds: float, seed: int) -> np.ndarray:
    """A murmur of talkers: the shipped recordings, many at once at random offsets, plus pink
    noise, at unit RMS."""
    rng = np.random.default_rng(seed)
    length = int(seconds * SAMPLE_RATE)
    murmur = np.zeros(length)
    talkers = [samples(n) for n in ("maybe", "i_dont_know", "sure", "nope", "yeah", "no_way")]
    for _ in range(int(seconds * 16)):
        talker = talkers[int(rng.integers(len(talkers)))]
        start = int(rng.integers(0, length - talker.size))
        murmur[start : start + talker.size] += talker / rms(talker)
    spectrum = np.fft.rfft(rng.normal(size=length))
    frequencies = np.fft.rfftfreq(length, 1 / SAMPLE_RATE)
    frequencies[0] = frequencies[1]
    pink = np.fft.irfft(spectrum / np.sqrt(frequencies), length)
    mixed = murmur / rms(murmur) + pink / rms(pink)
    return mixed / rms(mixed)


def frames_until_end(pcm: bytes) -> int | None:
    endpointer = Endpointer(SAMPLE_RATE)
    for index in range(len(pcm) // (2 * FRAME)):
        endpointer.feed(pcm[index * 2 * FRAME : (index + 1) * 2 * FRAME])
        if endpointer.speech_ended:
            return index
    return None


def to_pcm(signal: np.ndarray) -> bytes:
    return np.clip(np.rint(signal), -32768, 32767).astype("<i2").tobytes()


@pytest.mark.parametrize("seed", range(1, 9))
def test_a_word_in_babble_at_10_db_ends_after_the_pause(seed: int) -> None:
    word = samples("yes")
    lead, tail = int(0.6 * SAMPLE_RATE), int(1.2 * SAMPLE_RATE)
    speech = np.concatenate([np.zeros(lead), word, np.zeros(tail)])
    noise = babble(speech.size / SAMPLE_RATE, seed) * rms(word) / 10 ** (10 / 20)
    ended = frames_until_end(to_pcm(speech + noise))
    word_end = (lead + word.size) // FRAME
    assert ended is not None, "the end of speech was not heard in babble at 10 dB"
    assert word_end + 10 <= ended <= word_end + 45


def test_steady_loud_noise_alone_is_not_speech() -> None:
    endpointer = Endpointer(SAMPLE_RATE)
    rng = np.random.default_rng(5)
    steady = rng.normal(0, 3000, 3 * SAMPLE_RATE)  # about -21 dBFS of hiss
    endpointer.feed(to_pcm(steady))
    assert not endpointer.speech_started
    assert endpointer.floor_dbfs is not None and -24 < endpointer.floor_dbfs < -18


def test_levels_are_relative_to_full_scale() -> None:
    assert level_dbfs(to_pcm(np.full(FRAME, 32767.0))) == pytest.approx(0.0, abs=0.01)
    assert level_dbfs(bytes(2 * FRAME)) == -120.0


def test_a_lone_loud_frame_in_the_closing_quiet_does_not_move_the_stretch() -> None:
    word = samples("yes")
    word = word[: word.size - word.size % FRAME]  # the knock falls on one whole frame
    loudest = int(np.argmax(np.convolve(word**2, np.ones(FRAME), "valid")))
    knock = word[loudest : loudest + FRAME]  # one frame of the vowel: the detector's speech
    rng = np.random.default_rng(3)
    lead, pause, tail = (rng.normal(0, 30, int(s * SAMPLE_RATE)) for s in (0.3, 0.5, 1.0))
    buffer = SpeechBuffer(SAMPLE_RATE)
    buffer.feed(to_pcm(np.concatenate([lead, word, pause])))
    before = buffer.complete_stretch(PAD)
    buffer.feed(to_pcm(np.concatenate([knock, tail])))
    endpointer = buffer._endpointer
    assert endpointer.last_speech_frame > endpointer.last_word_frame + 20  # the knock was speech
    assert before is not None and buffer.complete_stretch(PAD) == before
    first, stretch = buffer.padded_speech(PAD)
    assert (first, first + len(stretch)) == before
    assert buffer.speech_ended


def test_the_stretch_is_complete_only_once_its_padding_has_arrived() -> None:
    word = to_pcm(samples("nope"))
    buffer = SpeechBuffer(SAMPLE_RATE)
    buffer.feed(bytes(2 * FRAME * 15) + word)
    assert buffer.complete_stretch(PAD) is None  # the padding after the word is still to come
    buffer.feed(bytes(2 * FRAME * 20))
    stretch = buffer.complete_stretch(PAD)
    assert stretch is not None
    assert buffer.audio(*stretch) == buffer.padded_speech(PAD)[1]
    buffer.close()
    assert buffer.complete_stretch(PAD) is None  # closed: nothing more is decoded early
