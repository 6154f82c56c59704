"""The room's microphone socket: spoken answers streamed to the server and recognised there.

A scripted recogniser stands in for the offline engine (its accuracy is the recogniser's own
tests' and the bench's business): it "hears" speech in non-zero samples and its end in the silent
frame that follows, and reports what the test scripted. What is tested here is the socket: where
audio goes, when an answer is recorded (once, through the path every answer takes), and what a
client that sends the wrong thing is told.
"""

from __future__ import annotations

import asyncio
import dataclasses
import io
import os
import shutil
import subprocess
import tempfile
import uuid
import wave
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import func, select
from starlette.websockets import WebSocketDisconnect

from app.protocol import ProtocolError, parse_protocol
from app.services import studies
from app.services.audit import Actor
from app.speech.engines import EngineSettings
from app.speech.pool import RecognitionUnavailable, RecognizerPool
from app.speech.synthesis import with_true_sizes
from app.speech.vocabulary import Vocabulary
from app.speech.wav import decode_wav
from app.tables import Answer, AnswerAudio
from tests.conftest import EXP3_ONLY, Lab, protocol_text

AUDIO = "/api/v1/station/audio"
FRAME = 3200
"""Bytes of a 0.1 s frame of 16 kHz 16-bit audio."""
SPEECH = bytes(range(1, 201)) * (FRAME // 200)
"""A frame the scripted recogniser takes for speech (its bytes are found again if stored)."""
SILENCE = bytes(FRAME)
SIGNATURE = SPEECH[:400]
"""Bytes of the spoken audio that nothing else writes: found in a file, the audio was stored."""

pytestmark = pytest.mark.timeout(60)


@dataclass(frozen=True)
class Heard:
    """A recognition as app.speech.recognizer reports it."""

    answer: str | None
    transcript: str
    confidence: float
    engine: str = "scripted 1.0"
    seconds: float = 0.01


@dataclass
class ScriptedUtterance:
    script: list[Heard]
    loops_seen: list[bool]
    finished: list[ScriptedUtterance]
    abandoned: list[ScriptedUtterance]
    spoke: bool = False
    ended: bool = False

    def feed(self, pcm: bytes) -> None:
        try:
            asyncio.get_running_loop()
            self.loops_seen.append(True)  # fed on the event loop: the test fails on it
        except RuntimeError:
            self.loops_seen.append(False)
        if any(pcm):
            self.spoke = True
        elif self.spoke:
            self.ended = True

    @property
    def speech_ended(self) -> bool:
        return self.ended

    def finish(self) -> Heard:
        self.finished.append(self)  # the real one gives its decoders back to the pool here
        return self.script.pop(0) if self.spoke else Heard(None, "", 0.0)

    def abandon(self) -> None:
        self.abandoned.append(self)  # the real one gives its decoders back, undecoded


@dataclass
class ScriptedRecognizer:
    """Every utterance hears the next scripted recognition."""

    script: list[Heard] = field(default_factory=list)
    vocabularies: list[Vocabulary] = field(default_factory=list)
    engines: list[EngineSettings] = field(default_factory=list)
    loops_seen: list[bool] = field(default_factory=list)
    finished: list[ScriptedUtterance] = field(default_factory=list)
    abandoned: list[ScriptedUtterance] = field(default_factory=list)

    def utterance(self) -> ScriptedUtterance:
        return ScriptedUtterance(self.script, self.loops_seen, self.finished, self.abandoned)


@pytest.fixture
def recognizer(lab: Lab) -> ScriptedRecognizer:
    scripted = ScriptedRecognizer()

    def make(vocabulary: Vocabulary, engine: EngineSettings) -> ScriptedRecognizer:
        scripted.vocabularies.append(vocabulary)
        scripted.engines.append(engine)
        return scripted

    lab.app.state.recognizers = RecognizerPool(make)
    return scripted


def _receive(ws: Any, *types: str) -> dict[str, Any]:
    message: dict[str, Any] = ws.receive_json()
    assert message["type"] in types, message
    return message


def _open_step(lab: Lab, category: str = "conation") -> int:
    step: int = lab.prompt(category)["step_id"]  # type: ignore[assignment]
    return step


def _speak(ws: Any, frames: int = 3) -> None:
    for _ in range(frames):
        ws.send_bytes(SPEECH)
    ws.send_bytes(SILENCE)


def _answers(lab: Lab) -> list[Answer]:
    with lab.database.read_session() as db:
        return list(db.scalars(select(Answer)).all())


def _recordings(lab: Lab) -> int:
    with lab.database.read_session() as db:
        return int(db.scalar(select(func.count()).select_from(AnswerAudio)) or 0)


def _seated_in(lab: Lab, name: str, **replacements: str) -> Lab:
    """``lab`` running a study ``name`` of the shipped protocol with ``replacements``."""
    loaded = parse_protocol(protocol_text(**EXP3_ONLY, **replacements))
    with lab.database.writing() as db:
        studies.create_study(db, name=name, loaded=loaded, actor=Actor.system())
    other = dataclasses.replace(lab, study=name)
    other.enrol_and_assign()
    other.start_session()
    return other


def test_a_spoken_yes_is_recognised_on_the_server_and_recorded_once(
    lab: Lab, recognizer: ScriptedRecognizer
) -> None:
    lab.enrol_and_assign()
    lab.start_session()
    step = _open_step(lab)
    recognizer.script.append(Heard("yes", "yeah", 0.91))
    with lab.robot.websocket_connect(AUDIO) as ws:
        hello = _receive(ws, "hello")
        assert (hello["station"], hello["sample_rate"]) == ("lab-1", 16000)
        ws.send_json({"type": "start", "id": 1, "step_id": step})
        listening = _receive(ws, "listening")
        assert (listening["id"], listening["step_id"], listening["max_seconds"]) == (1, step, 15)
        _speak(ws)
        answered = _receive(ws, "answer")
        assert (answered["id"], answered["step_id"]) == (1, step)
        assert answered["heard"] == {
            "transcript": "yeah",
            "confidence": 0.91,
            "engine": "scripted 1.0",
        }
        assert answered["data"]["answer"] == "yes" and answered["data"]["reply"]
        ws.send_json({"type": "ping", "id": "p"})
        assert _receive(ws, "pong")["id"] == "p"
    stored = _answers(lab)
    assert [
        (a.answer, a.modality, a.transcript, a.transcript_confidence, a.transcript_engine)
        for a in stored
    ] == [(True, "speech", "yeah", 0.91, "scripted 1.0")]
    assert recognizer.loops_seen and not any(recognizer.loops_seen)  # always in worker threads
    assert recognizer.vocabularies == [
        Vocabulary.of(["yes", "yeah", "yep", "sure"], ["no", "nope", "no way"], 0.4)
    ]
    assert recognizer.engines == [EngineSettings("whisper", prompt=True)]  # the defaults
    assert lab.robot.get("/api/v1/station").json()["open_prompts"] == []
    assert _recordings(lab) == 0


def test_a_study_may_choose_pocketsphinx_and_each_engine_is_built_once(
    lab: Lab, recognizer: ScriptedRecognizer
) -> None:
    chosen = _seated_in(
        lab,
        "sphinx",
        **{
            '# engine = "whisper"': 'engine = "pocketsphinx"',
            "# prompt_phrases = true": "prompt_phrases = false",
        },
    )
    step = _open_step(chosen)
    recognizer.script += [Heard("no", "nope", 0.8)]
    with chosen.robot.websocket_connect(AUDIO) as ws:
        _receive(ws, "hello")
        ws.send_json({"type": "start", "id": 1, "step_id": step})
        _receive(ws, "listening")
        ws.send_json({"type": "cancel"})
        _receive(ws, "cancelled")
        ws.send_json({"type": "start", "id": 2, "step_id": step})
        _receive(ws, "listening")
        _speak(ws)
        assert _receive(ws, "answer")["data"]["answer"] == "no"
    # built once, shared by both listens
    assert recognizer.engines == [EngineSettings("pocketsphinx", prompt=False)]
    settings = chosen.robot.get("/api/v1/station/speech").json()
    assert (settings["engine"], settings["prompt_phrases"]) == ("pocketsphinx", False)


def test_unclear_speech_and_silence_are_asked_again_and_nothing_is_stored(
    lab: Lab, recognizer: ScriptedRecognizer
) -> None:
    lab.enrol_and_assign()
    lab.start_session()
    step = _open_step(lab)
    recognizer.script += [
        Heard(None, "maybe", 0.8),
        Heard("no", "no", 0.2),
        Heard("no", "nope", 0.7),
    ]
    with lab.robot.websocket_connect(AUDIO) as ws:
        _receive(ws, "hello")
        ws.send_json({"type": "start", "id": 1, "step_id": step})
        _receive(ws, "listening")
        _speak(ws)
        unclear = _receive(ws, "unclear")
        assert unclear["heard"]["transcript"] == "maybe"
        ws.send_json({"type": "start", "id": 2, "step_id": step})
        _receive(ws, "listening")
        _speak(ws)  # a clear word heard below the protocol's min_confidence (0.4)
        assert _receive(ws, "unclear")["heard"]["confidence"] == 0.2
        ws.send_json({"type": "start", "id": 3, "step_id": step})
        _receive(ws, "listening")
        ws.send_bytes(SILENCE)
        ws.send_json({"type": "stop", "id": 4})  # the client's listening time is up: silence
        silence = _receive(ws, "unclear")
        assert (silence["id"], silence["heard"]["transcript"]) == (3, "")
        assert _answers(lab) == []
        ws.send_json({"type": "start", "id": 5, "step_id": step})
        _receive(ws, "listening")
        _speak(ws)
        assert _receive(ws, "answer")["data"]["answer"] == "no"
    assert [(a.answer, a.transcript) for a in _answers(lab)] == [(False, "nope")]


def test_audio_without_an_open_question_is_dropped_with_an_error_and_the_socket_stays(
    lab: Lab, recognizer: ScriptedRecognizer
) -> None:
    lab.enrol_and_assign()
    lab.start_session()
    with lab.robot.websocket_connect(AUDIO) as ws:
        _receive(ws, "hello")
        ws.send_bytes(SPEECH)
        ws.send_bytes(SPEECH)  # one error for a run of stray frames, not one per frame
        error = _receive(ws, "error")
        assert error["status"] == 409 and "no question is being listened to" in error["detail"]
        ws.send_json({"type": "ping", "id": 1})
        assert _receive(ws, "pong")["id"] == 1
        ws.send_json({"type": "start", "id": 2, "step_id": 999999})  # no such open step
        refused = _receive(ws, "error")
        assert (refused["id"], refused["status"]) == (2, 409)
        assert "step 999999 is not open" in refused["detail"]
        ws.send_bytes(SPEECH)
        assert _receive(ws, "error")["status"] == 409
        ws.send_json({"type": "stop", "id": 3})
        assert _receive(ws, "error")["status"] == 409
    assert _answers(lab) == [] and recognizer.loops_seen == []


@pytest.mark.parametrize(
    ("message", "status", "problem"),
    [
        ({"type": "start", "id": 7, "step_id": "one"}, 422, "step_id"),
        ({"type": "start", "id": 7, "step_id": 1, "volume": 3}, 422, "volume"),
        ({"type": "start", "id": 7}, 422, "step_id"),
        ({"type": "start", "id": 7, "step_id": 1, "idempotency_key": ""}, 422, "idempotency_key"),
        ({"type": "record", "id": 7}, 422, "type"),
        ("[1, 2", 400, "not JSON"),
    ],
)
def test_a_malformed_message_is_refused_and_the_socket_stays(
    lab: Lab, recognizer: ScriptedRecognizer, message: object, status: int, problem: str
) -> None:
    with lab.robot.websocket_connect(AUDIO) as ws:
        _receive(ws, "hello")
        if isinstance(message, str):
            ws.send_text(message)
        else:
            ws.send_json(message)
        error = _receive(ws, "error")
        assert error["status"] == status and problem in error["detail"], error
        if status == 422:
            assert error["id"] == 7
        ws.send_json({"type": "ping", "id": 8})
        assert _receive(ws, "pong")["id"] == 8


def test_more_audio_than_the_protocol_allows_is_cut_off(
    lab: Lab, recognizer: ScriptedRecognizer
) -> None:
    limited = _seated_in(
        lab, "limited", **{"max_answer_seconds = 15.0": "max_answer_seconds = 0.5"}
    )
    step = _open_step(limited)
    recognizer.script += [Heard("yes", "yes", 0.9)]  # the cut-off answer is never decoded
    with limited.robot.websocket_connect(AUDIO) as ws:
        _receive(ws, "hello")
        ws.send_json({"type": "start", "id": 1, "step_id": step})
        assert _receive(ws, "listening")["max_seconds"] == 0.5
        for _ in range(6):  # 0.6 s of speech that never ends
            ws.send_bytes(SPEECH)
        cut = _receive(ws, "error")
        assert (cut["id"], cut["status"]) == (1, 413)
        assert "cut off: more than 0.5 s of audio for one answer" in cut["detail"]
        # dropped unheard: its decoders given back without a decode
        assert (len(recognizer.abandoned), recognizer.finished) == (1, [])
        ws.send_bytes(SILENCE)  # the rest of what the client sent before it heard: dropped quietly
        ws.send_json({"type": "ping", "id": 2})
        assert _receive(ws, "pong")["id"] == 2
        assert _answers(lab) == []
        ws.send_json({"type": "start", "id": 3, "step_id": step})  # listening again works
        _receive(ws, "listening")
        _speak(ws, frames=2)
        assert _receive(ws, "answer")["data"]["answer"] == "yes"


def test_a_defect_while_listening_is_reported_and_gives_the_decoders_back(
    lab: Lab, recognizer: ScriptedRecognizer, monkeypatch: pytest.MonkeyPatch
) -> None:
    lab.enrol_and_assign()
    lab.start_session()
    step = _open_step(lab)
    recognizer.script += [Heard("yes", "yes", 0.9)]

    def broken_feed(self: ScriptedUtterance, pcm: bytes) -> None:
        raise RuntimeError("a defect in the recogniser")

    with lab.robot.websocket_connect(AUDIO) as ws:
        _receive(ws, "hello")
        ws.send_json({"type": "start", "id": 1, "step_id": step})
        _receive(ws, "listening")
        with monkeypatch.context() as patch:
            patch.setattr(ScriptedUtterance, "feed", broken_feed)
            ws.send_bytes(SPEECH)
            failed = _receive(ws, "error")
        assert (failed["id"], failed["status"]) == (1, 500)
        assert "its log has the details" in failed["detail"]
        # the failed answer is dropped unheard, its decoders given back to the pool
        assert (len(recognizer.abandoned), recognizer.finished) == (1, [])
        ws.send_json({"type": "start", "id": 2, "step_id": step})  # the socket still serves
        _receive(ws, "listening")
        _speak(ws)
        assert _receive(ws, "answer")["data"]["answer"] == "yes"
    assert [a.answer for a in _answers(lab)] == [True]


def test_an_odd_length_frame_is_refused(lab: Lab, recognizer: ScriptedRecognizer) -> None:
    lab.enrol_and_assign()
    lab.start_session()
    step = _open_step(lab)
    with lab.robot.websocket_connect(AUDIO) as ws:
        _receive(ws, "hello")
        ws.send_json({"type": "start", "id": 1, "step_id": step})
        _receive(ws, "listening")
        ws.send_bytes(b"\x01\x02\x03")
        error = _receive(ws, "error")
        assert error["status"] == 400 and "even number of bytes" in error["detail"]


def test_an_unknown_key_is_refused(lab: Lab) -> None:
    anonymous = TestClient(lab.app)
    anonymous.portal = lab.robot.portal
    with anonymous.websocket_connect(AUDIO) as ws:
        ws.send_json({"type": "auth", "key": "tlk_wrong"})
        with pytest.raises(WebSocketDisconnect) as closed:
            ws.receive_json()
        assert closed.value.code == 4401


def test_without_an_offline_recogniser_the_room_is_told_in_one_line(lab: Lab) -> None:
    def missing(vocabulary: Vocabulary, engine: EngineSettings) -> Any:
        raise RecognitionUnavailable("offline speech recognition is unavailable on this server")

    lab.app.state.recognizers = RecognizerPool(missing)
    lab.enrol_and_assign()
    lab.start_session()
    step = _open_step(lab)
    with lab.robot.websocket_connect(AUDIO) as ws:
        _receive(ws, "hello")
        ws.send_json({"type": "start", "id": 1, "step_id": step})
        error = _receive(ws, "error")
        assert error["status"] == 503 and "\n" not in error["detail"]


RECORDING_CONSENT = {
    "that you agree to take part.": "that you agree to take part. Your spoken answers are "
    "recorded as audio and stored under your code.",
    "record_audio = false": "record_audio = true",
}


def test_a_recording_study_stores_each_answers_audio(
    lab: Lab, recognizer: ScriptedRecognizer
) -> None:
    recording = _seated_in(lab, "recorded", **RECORDING_CONSENT)
    step = _open_step(recording)
    recognizer.script += [Heard(None, "hmm", 0.5), Heard("yes", "yes", 0.9)]
    with recording.robot.websocket_connect(AUDIO) as ws:
        _receive(ws, "hello")
        ws.send_json({"type": "start", "id": 1, "step_id": step})
        _receive(ws, "listening")
        _speak(ws)
        _receive(ws, "unclear")  # an unclear attempt is not stored
        ws.send_json({"type": "start", "id": 2, "step_id": step, "idempotency_key": "k1"})
        _receive(ws, "listening")
        _speak(ws, frames=2)
        _receive(ws, "answer")
    with lab.database.read_session() as db:
        (audio,) = db.scalars(select(AnswerAudio)).all()
        answer = db.get(Answer, audio.answer_id)
    assert answer is not None and answer.idempotency_key == "k1"
    assert audio.participant_id == answer.participant_id
    with wave.open(io.BytesIO(audio.wav)) as wav:
        assert (wav.getframerate(), wav.getnchannels(), wav.getsampwidth()) == (16000, 1, 2)
        assert wav.readframes(wav.getnframes()) == SPEECH * 2 + SILENCE
    assert audio.seconds == pytest.approx(0.3)


def test_recording_without_a_consent_mention_is_refused() -> None:
    text = protocol_text(**{"record_audio = false": "record_audio = true"})
    with pytest.raises(ProtocolError) as refused:
        parse_protocol(text, source="lab.toml")
    assert "speech.record_audio" in str(refused.value)
    assert "consent" in str(refused.value)
    parse_protocol(protocol_text(**RECORDING_CONSENT))  # said in the consent text: accepted


@pytest.fixture
def sqlite_files(lab: Lab, engine_name: str) -> list[Path]:
    """The SQLite database's files (the database, its WAL), for the test to search."""
    if engine_name != "sqlite":
        pytest.skip("searches the database's files: SQLite only")
    path = Path(str(lab.database.engine.url.database))
    return [path, path.with_name(path.name + "-wal")]


def _files_under(folder: Path) -> set[Path]:
    """Files below ``folder``; other tests on the machine create and remove folders under the
    temporary directory meanwhile, so a folder that vanishes during the walk is skipped
    (``os.walk`` ignores errors), where ``Path.rglob`` raises."""
    return {Path(root, name) for root, _dirs, names in os.walk(folder) for name in names}


def _read_if_still_there(path: Path) -> bytes:
    """A file's bytes, or nothing when another test removed it since it was listed."""
    try:
        return path.read_bytes() if path.stat().st_size < 64_000_000 else b""
    except (FileNotFoundError, NotADirectoryError, PermissionError):
        return b""


def test_no_audio_is_left_anywhere_after_a_session_without_recording(
    lab: Lab, recognizer: ScriptedRecognizer, sqlite_files: list[Path], tmp_path: Path
) -> None:
    """Every answer of a session by voice: no recording rows, no audio file, and the audio's
    bytes are in no file written meanwhile (the database's included)."""
    temporary = Path(tempfile.gettempdir())
    before = _files_under(tmp_path) | _files_under(temporary)
    lab.enrol_and_assign()
    lab.start_session()
    with lab.robot.websocket_connect(AUDIO) as ws:
        _receive(ws, "hello")
        expected = lab.robot.get("/api/v1/station").json()["expected"]
        while expected["action"] == "prompt":
            step = _open_step(lab, expected["categories"][0])
            recognizer.script.append(Heard("no", "no", 0.9))
            ws.send_json({"type": "start", "id": step, "step_id": step})
            _receive(ws, "listening")
            _speak(ws)
            expected = _receive(ws, "answer")["data"]["expected"]
    answers = _answers(lab)
    assert len(answers) >= 3 and {a.modality for a in answers} == {"speech"}
    assert _recordings(lab) == 0
    written = (_files_under(tmp_path) | _files_under(temporary)) - before
    assert sqlite_files[0].is_file(), "the database file to search is where the engine says"
    assert not any(p.suffix.lower() in (".wav", ".pcm", ".raw") for p in written), written
    for path in {*written, *sqlite_files}:  # other tests on the machine write here too
        assert SIGNATURE not in _read_if_still_there(path), path


def test_the_room_is_served_its_speech_settings(lab: Lab) -> None:
    lab.enrol_and_assign()
    speech = lab.robot.get("/api/v1/station/speech").json()
    assert speech["cloud_recognizer"] is False
    assert speech["record_audio"] is False
    assert speech["max_answer_seconds"] == 15.0


def test_an_answer_names_its_engine_only_when_spoken(lab: Lab) -> None:
    lab.enrol_and_assign()
    lab.start_session()
    step = _open_step(lab)
    refused = lab.robot.post(
        f"/api/v1/station/steps/{step}/answer",
        json={
            "answer": "yes",
            "idempotency_key": uuid.uuid4().hex,
            "modality": "key",
            "transcript_engine": "browser",
        },
    )
    assert refused.status_code == 422 and "transcript_engine" in refused.text
    spoken = lab.robot.post(
        f"/api/v1/station/steps/{step}/answer",
        json={
            "answer": "yes",
            "idempotency_key": uuid.uuid4().hex,
            "modality": "speech",
            "transcript": "yes",
            "transcript_engine": "browser",
        },
    )
    assert spoken.status_code == 200, spoken.text
    assert [a.transcript_engine for a in _answers(lab)] == ["browser"]


@pytest.fixture(scope="module")
def spoken_yes() -> bytes:
    """ "Yes" said by espeak-ng, as 16 kHz PCM with silence either side (a participant's answer)."""
    if shutil.which("espeak-ng") is None:
        pytest.skip("espeak-ng is not installed (apt-get install espeak-ng)")
    said = subprocess.run(
        ["espeak-ng", "-v", "en-us", "-s", "150", "--stdout"],
        input=b"yes",
        capture_output=True,
        timeout=30,
        check=True,
    ).stdout
    pause = bytes(int(0.5 * 16000) * 2)
    return pause + decode_wav(with_true_sizes(said)) + pause + pause


@pytest.mark.timeout(120)
def test_the_offline_recogniser_hears_a_streamed_yes(lab: Lab, spoken_yes: bytes) -> None:
    """The shipped recogniser behind the socket: a synthetic "yes" streamed in 100 ms frames is
    heard at the end of speech and recorded with the engine's name."""
    lab.enrol_and_assign()
    lab.start_session()
    step = _open_step(lab)
    with lab.robot.websocket_connect(AUDIO) as ws:
        _receive(ws, "hello")
        ws.send_json({"type": "start", "id": 1, "step_id": step})
        _receive(ws, "listening")
        for at in range(0, len(spoken_yes), FRAME):
            ws.send_bytes(spoken_yes[at : at + FRAME])
        answered = _receive(ws, "answer")
    assert answered["data"]["answer"] == "yes"
    assert answered["heard"]["engine"].startswith("whisper tiny.en")
    (stored,) = _answers(lab)
    assert (stored.answer, stored.modality, stored.transcript) == (True, "speech", "yes")
    assert stored.transcript_engine == answered["heard"]["engine"]
