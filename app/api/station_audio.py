"""The room's microphone socket: spoken answers recognised on the trustlab server, offline.

A room client (static/js/room.js) streams the participant's voice while a question is open, and
the server recognises the yes or no with its offline recogniser (app.speech.pool), so no audio
leaves the lab. Protocol (docs/robot-integration.md, "The audio socket"):

- Authenticate as on the station WebSocket (``Authorization: Bearer tlk_…`` or a first
  ``{"type": "auth", "key": …}``); the server greets with ``{"type": "hello", "station": …,
  "sample_rate": 16000}``.
- ``{"type": "start", "id": …, "step_id": N}`` (optionally ``idempotency_key``) opens listening for
  the answer to the open step N; the server replies ``{"type": "listening", "id", "step_id",
  "max_seconds"}``. Then binary frames: 16 kHz mono 16-bit little-endian PCM, any length.
- When the recogniser hears the end of speech (or the client sends ``{"type": "stop"}``, its
  listening time being up), the server decides. A clear yes or no is recorded through the same
  path as every answer (modality ``speech``, with the transcript, confidence and engine) and
  answered ``{"type": "answer", "id", "step_id", "heard", "data": <the answer's reply>}``;
  anything else is ``{"type": "unclear", "id", "step_id", "heard"}`` and the room asks again
  (``heard.transcript`` is empty for silence). ``{"type": "cancel"}`` drops the audio unheard.
- Errors are ``{"type": "error", "id", "status", "detail"}`` and the socket stays open: a
  malformed start (422), a step that is not open (409), audio frames while nothing is listened to
  (409, once until the client's next message), an odd-length frame (400), or more audio for one
  answer than the protocol's ``[speech] max_answer_seconds`` (413: the answer's audio is dropped
  and nothing is recorded; send ``start`` to listen again).

Audio is held in memory while its answer is recognised and dropped with it; only a study whose
protocol sets ``[speech] record_audio = true`` stores the utterance of each recognised answer
(app.services.sessions.answer_audio). Recognition runs in worker threads: the event loop never waits
for it.
"""

from __future__ import annotations

import contextlib
import json
import logging
import uuid
from collections.abc import Awaitable
from dataclasses import dataclass, field
from typing import Annotated, Any, Literal

from fastapi import APIRouter, WebSocket, WebSocketDisconnect
from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, ValidationError
from sqlalchemy.exc import OperationalError
from starlette.concurrency import run_in_threadpool

from app.api import station_ops
from app.api.device_work import as_device, device_actor
from app.api.runtime_schemas import AnswerOut, AnswerRequest, SpeechOut
from app.api.station_ws import (
    CLOSE_UNAUTHENTICATED,
    AuthenticatedDevice,
    BadFrame,
    RequestId,
    accept_device,
    decode_frame,
    describe_invalid,
)
from app.errors import Conflict, NotAuthenticated, TrustlabError
from app.inputs import RowId
from app.services.sessions.step_store import DeviceSeat
from app.speech.engines import SAMPLE_RATE, EngineSettings, RecognitionLike, UtteranceLike
from app.speech.pool import RecognizerPool
from app.speech.vocabulary import Vocabulary

log = logging.getLogger(__name__)

router = APIRouter(tags=["robot"])

BYTES_PER_SECOND = SAMPLE_RATE * 2
ENGINE_NAME_LENGTH = 60
TRANSCRIPT_LENGTH = 200


class _Message(BaseModel):
    model_config = ConfigDict(extra="forbid")
    id: RequestId = None


class StartMessage(_Message):
    """Listen for the answer to an open step."""

    type: Literal["start"]
    step_id: RowId
    idempotency_key: str | None = Field(
        default=None,
        min_length=1,
        max_length=100,
        description="Unique per answer (the server makes one when absent).",
    )


class StopMessage(_Message):
    """The client's listening time is up: decide on what was heard so far."""

    type: Literal["stop"]


class CancelMessage(_Message):
    """Drop the audio of this answer unheard (the question was answered another way)."""

    type: Literal["cancel"]


class PingMessage(_Message):
    """Liveness check."""

    type: Literal["ping", "pong"]


AudioMessage = Annotated[
    StartMessage | StopMessage | CancelMessage | PingMessage, Field(discriminator="type")
]
_parse = TypeAdapter(AudioMessage)


@dataclass
class _Listening:
    """One answer being listened to: its step, its utterance, and how much audio it has had."""

    request_id: RequestId
    step_id: int
    idempotency_key: str
    speech: SpeechOut
    utterance: UtteranceLike
    received: int = 0
    recording: list[bytes] | None = field(default=None)

    @property
    def limit(self) -> int:
        """The most bytes of audio this answer may have."""
        return int(self.speech.max_answer_seconds * BYTES_PER_SECOND)


def _feed(utterance: UtteranceLike, pcm: bytes) -> bool:
    """Feed one frame; whether the recogniser has heard the end of speech (a worker's job)."""
    utterance.feed(pcm)
    return utterance.speech_ended


def _heard(recognition: RecognitionLike) -> dict[str, Any]:
    return {
        "transcript": recognition.transcript,
        "confidence": recognition.confidence,
        "engine": recognition.engine,
    }


class _AudioConnection:
    def __init__(self, websocket: WebSocket, device: AuthenticatedDevice) -> None:
        self.websocket = websocket
        self.device = device
        self.pool: RecognizerPool = websocket.app.state.recognizers
        self.listening: _Listening | None = None
        self.stray_reported = False
        self.quiet_until_next_message = False
        """After the server ended an answer's audio, frames the client sent before it heard so
        are dropped without an error; its next message ends the grace."""

    async def send(self, message: dict[str, Any]) -> None:
        await self.websocket.send_text(json.dumps(message, default=str))

    async def send_error(self, request_id: RequestId, status: int, detail: str) -> None:
        await self.send({"type": "error", "id": request_id, "status": status, "detail": detail})

    async def serve(self) -> None:
        await self.send(
            {"type": "hello", "station": self.device.station, "sample_rate": SAMPLE_RATE}
        )
        while True:
            message = await self.websocket.receive()
            if message["type"] == "websocket.disconnect":
                raise WebSocketDisconnect(message.get("code", 1000), message.get("reason"))
            audio = message.get("bytes")
            if isinstance(audio, bytes | bytearray):
                request_id = self.listening.request_id if self.listening else None
                handled = await self.guarded(request_id, "audio", self.audio(bytes(audio)))
            else:
                handled = await self.text(message.get("text"))
            if not handled:
                return

    async def guarded(self, request_id: RequestId, what: str, work: Awaitable[None]) -> bool:
        """Run one message's work, answering its failure on the socket; False when the
        connection was closed (the key was revoked)."""
        try:
            await work
        except NotAuthenticated:
            await self.websocket.close(CLOSE_UNAUTHENTICATED, "device key revoked")
            return False
        except TrustlabError as exc:
            await self.send_error(request_id, exc.status_code, exc.message)
        except OperationalError:
            await self.send_error(
                request_id, 503, "the database is unavailable right now; please retry"
            )
        except Exception:  # a defect: say so, log it, keep serving
            log.exception("station %s: audio %s failed", self.device.station, what)
            await self.drop()  # its decoders go back to the pool, as a cut-off's do
            await self.send_error(
                request_id, 500, "the server failed to handle this request; its log has the details"
            )
        return True

    # ------------------------------------------------------------------ text messages

    async def text(self, raw: str | None) -> bool:
        """Handle one text message; False when the connection was closed (key revoked)."""
        self.stray_reported = False
        self.quiet_until_next_message = False
        request_id: RequestId = None
        try:
            data = decode_frame(raw)
            if isinstance(data, dict):
                value = data.get("id")
                if isinstance(value, str | int) and not isinstance(value, bool):
                    request_id = value
            message = _parse.validate_python(data)
        except BadFrame as exc:
            await self.send_error(None, 400, exc.detail)
            return True
        except ValidationError as exc:
            await self.send_error(request_id, 422, describe_invalid(exc))
            return True
        return await self.guarded(message.id, message.type, self.dispatch(message))

    async def dispatch(self, message: _Message) -> None:
        if isinstance(message, PingMessage):
            if message.type == "ping":
                await self.send({"type": "pong", "id": message.id})
        elif isinstance(message, StartMessage):
            await self.start(message)
        elif isinstance(message, StopMessage):
            await self.stop(message)
        else:
            await self.drop()
            await self.send({"type": "cancelled", "id": message.id})

    async def drop(self) -> None:
        """Forget the answer being listened to, unheard: its audio goes with it, and its
        decoders go back to the recogniser's pool undecoded (a lost pair would cost the next
        answer a model load). A Whisper decode already started during the endpointer's wait
        runs out (a decode cannot be stopped) and its transcript is dropped."""
        listening, self.listening = self.listening, None
        if listening is not None:
            with contextlib.suppress(Exception):
                listening.utterance.abandon()

    async def start(self, message: StartMessage) -> None:
        await self.drop()  # a new start replaces whatever was being listened to

        def look(db: Any, device: DeviceSeat) -> tuple[SpeechOut, list[int]]:
            speech = station_ops.speech(db, station=device.seat)
            state = station_ops.state(db, station=device.seat)
            return speech, [p.step_id for p in state.open_prompts]

        speech, open_steps = await as_device(
            self.websocket.app, self.device.key, write=False, op=look
        )
        if message.step_id not in open_steps:
            raise Conflict(
                f"step {message.step_id} is not open at station {self.device.station}: "
                "listen only while its question is asked"
            )
        if not speech.offline_recognition:
            raise Conflict(
                f"the server recognises US English only, and this participant answers in "
                f"{speech.language!r}: take the answer by button"
            )
        vocabulary = Vocabulary.of(speech.yes, speech.no, speech.min_confidence)
        engine = EngineSettings.of(speech)
        recognizer = await run_in_threadpool(self.pool.get, vocabulary, engine)
        utterance = await run_in_threadpool(recognizer.utterance)
        self.listening = _Listening(
            request_id=message.id,
            step_id=message.step_id,
            idempotency_key=message.idempotency_key or uuid.uuid4().hex,
            speech=speech,
            utterance=utterance,
            recording=[] if speech.record_audio else None,
        )
        await self.send(
            {
                "type": "listening",
                "id": message.id,
                "step_id": message.step_id,
                "max_seconds": speech.max_answer_seconds,
            }
        )

    async def stop(self, message: StopMessage) -> None:
        if self.listening is None:
            raise Conflict("nothing is being listened to: send start first")
        await self.decide()

    # ------------------------------------------------------------------ audio

    async def audio(self, pcm: bytes) -> None:
        listening = self.listening
        if listening is None:
            if not (self.stray_reported or self.quiet_until_next_message):
                self.stray_reported = True
                await self.send_error(
                    None,
                    409,
                    "audio dropped: no question is being listened to (send a start message "
                    "naming the open step first)",
                )
            return
        if len(pcm) % 2:
            await self.send_error(
                listening.request_id,
                400,
                "audio frames are 16-bit samples: a frame needs an even number of bytes",
            )
            return
        listening.received += len(pcm)
        if listening.received > listening.limit:
            await self.drop()
            self.quiet_until_next_message = True
            await self.send_error(
                listening.request_id,
                413,
                f"cut off: more than {listening.speech.max_answer_seconds:g} s of audio for one "
                "answer (the protocol's [speech] max_answer_seconds); nothing was recorded, "
                "send start to listen again",
            )
            return
        if listening.recording is not None:
            listening.recording.append(pcm)
        ended = await run_in_threadpool(_feed, listening.utterance, pcm)
        if ended and self.listening is listening:
            self.quiet_until_next_message = True
            await self.decide()

    async def decide(self) -> None:
        """Recognise the answer being listened to, and record it when it is clear."""
        listening = self.listening
        assert listening is not None
        self.listening = None
        recognition = await run_in_threadpool(listening.utterance.finish)
        heard = _heard(recognition)
        answer = recognition.answer
        clear = answer in ("yes", "no") and (
            recognition.confidence >= listening.speech.min_confidence
        )
        if not clear or answer is None:
            await self.send(
                {
                    "type": "unclear",
                    "id": listening.request_id,
                    "step_id": listening.step_id,
                    "heard": heard,
                }
            )
            return
        body = AnswerRequest(
            answer=answer,
            idempotency_key=listening.idempotency_key,
            modality="speech",
            transcript=recognition.transcript[:TRANSCRIPT_LENGTH] or None,
            transcript_confidence=min(1.0, max(0.0, recognition.confidence)),
            transcript_engine=recognition.engine[:ENGINE_NAME_LENGTH] or None,
        )
        recording = b"".join(listening.recording) if listening.recording is not None else None
        step_id = listening.step_id

        def record(db: Any, device: DeviceSeat) -> AnswerOut:
            return station_ops.spoken_answer(
                db,
                station=device.seat,
                step_id=step_id,
                body=body,
                actor=device_actor(device),
                device_id=device.device_id,
                recording=recording,
            )

        try:
            out = await as_device(self.websocket.app, self.device.key, write=True, op=record)
        except TrustlabError as exc:
            if isinstance(exc, NotAuthenticated):
                raise
            await self.send(
                {
                    "type": "error",
                    "id": listening.request_id,
                    "status": exc.status_code,
                    "detail": exc.message,
                    "step_id": step_id,
                    "heard": heard,
                }
            )
            return
        await self.send(
            {
                "type": "answer",
                "id": listening.request_id,
                "step_id": step_id,
                "heard": heard,
                "data": out.model_dump(mode="json"),
            }
        )


@router.websocket("/station/audio")
async def station_audio(websocket: WebSocket) -> None:
    """A room client's microphone: its spoken answers, recognised on the server."""
    device = await accept_device(websocket)
    if device is None:
        return
    connection = _AudioConnection(websocket, device)
    try:
        with contextlib.suppress(WebSocketDisconnect):
            await connection.serve()
    finally:
        await connection.drop()
