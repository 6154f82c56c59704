"""The robot-facing API: a device key speaks for one station and whoever is assigned there."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Request, Response, status
from starlette.concurrency import run_in_threadpool

from app.api import station_ops
from app.api.device_work import DeviceKey, ModelResponse, as_device, device_actor
from app.api.runtime_schemas import (
    AnswerOut,
    AnswerRequest,
    NoticeRequest,
    PresenceRequest,
    PromptOut,
    PromptRequest,
    RoomOut,
    SpeechOut,
    StationStateOut,
    StepIdPath,
)
from app.speech.synthesis import Synthesiser

router = APIRouter(prefix="/station", tags=["robot"])


@router.get("", response_model=StationStateOut)
async def get_state(request: Request, key: DeviceKey) -> ModelResponse:
    """The station's participant, session, run, open prompts and what to do next."""
    out = await as_device(
        request.app,
        key,
        write=False,
        op=lambda db, device: station_ops.state(db, station=device.seat),
    )
    return ModelResponse(out)


@router.get("/room", response_model=RoomOut)
async def get_room(request: Request, key: DeviceKey) -> ModelResponse:
    """The escape room a room client draws: the floor plan and trigger zones of the study this
    station runs (the seated participant's, else the one its console chose)."""
    out = await as_device(
        request.app,
        key,
        write=False,
        op=lambda db, device: station_ops.room(db, station=device.seat),
    )
    return ModelResponse(out)


@router.get("/speech", response_model=SpeechOut)
async def get_speech(request: Request, key: DeviceKey) -> ModelResponse:
    """What a robot that hears listens for and when an answer counts: the ``[speech]`` settings
    of the study this station runs (the seated participant's, else the one its console chose)."""
    out = await as_device(
        request.app,
        key,
        write=False,
        op=lambda db, device: station_ops.speech(db, station=device.seat),
    )
    return ModelResponse(out)


@router.get(
    "/speech/audio",
    response_class=Response,
    responses={
        200: {"content": {"audio/wav": {}}, "description": "The line spoken, as a WAV file."},
        503: {"description": "The server cannot synthesise speech (espeak-ng is missing)."},
    },
)
async def get_spoken_line(
    request: Request,
    key: DeviceKey,
    text: Annotated[str, Query(min_length=1, max_length=2000, description="The line to say.")],
) -> Response:
    """A line of the study this station runs, spoken (for a room client whose browser has no
    voices): its questions, replies, request to answer again and rules only; any other text is a
    404. Synthesised on the server with espeak-ng, once per line."""
    language = await as_device(
        request.app,
        key,
        write=False,
        op=lambda db, device: station_ops.check_spoken_line(db, station=device.seat, text=text),
    )
    synthesiser: Synthesiser = request.app.state.synthesiser
    wav = await run_in_threadpool(synthesiser.wav, text, language)
    return Response(wav, media_type="audio/wav")


@router.post(
    "/prompts",
    status_code=status.HTTP_201_CREATED,
    response_model=PromptOut,
    responses={200: {"description": "The category's open prompt, handed out again."}},
)
async def prompt(body: PromptRequest, request: Request, key: DeviceKey) -> ModelResponse:
    """Choose the question for a category with the participant's learner."""
    out = await as_device(
        request.app,
        key,
        write=True,
        op=lambda db, device: station_ops.prompt(
            db,
            station=device.seat,
            body=body,
            actor=device_actor(device),
            device_id=device.device_id,
        ),
    )
    return ModelResponse(out, status.HTTP_201_CREATED if out.created else status.HTTP_200_OK)


@router.post("/steps/{step_id}/answer", response_model=AnswerOut)
async def answer(
    step_id: StepIdPath, body: AnswerRequest, request: Request, key: DeviceKey
) -> ModelResponse:
    """Record the participant's yes/no answer (exactly once) and get the robot's reply."""
    out = await as_device(
        request.app,
        key,
        write=True,
        op=lambda db, device: station_ops.answer(
            db,
            station=device.seat,
            step_id=step_id,
            body=body,
            actor=device_actor(device),
            device_id=device.device_id,
        ),
    )
    return ModelResponse(out)


@router.post("/runs", status_code=status.HTTP_201_CREATED, response_model=StationStateOut)
async def start_run(request: Request, key: DeviceKey) -> ModelResponse:
    """Start the next run (optional: prompting after a finished run starts it too)."""
    out = await as_device(
        request.app,
        key,
        write=True,
        op=lambda db, device: station_ops.start_run(
            db, station=device.seat, actor=device_actor(device)
        ),
    )
    return ModelResponse(out, status.HTTP_201_CREATED)


@router.put("/presence", status_code=status.HTTP_204_NO_CONTENT)
async def put_presence(body: PresenceRequest, request: Request, key: DeviceKey) -> Response:
    """Say where the participant is in the room and what was last said (a room client sends this
    when it changes, at most twice a second); the operator console shows it live."""
    await as_device(
        request.app,
        key,
        write=True,
        op=lambda db, device: station_ops.presence(
            db, station=device.seat, device_id=device.device_id, body=body
        ),
    )
    return Response(status_code=status.HTTP_204_NO_CONTENT)


@router.put("/notice", status_code=status.HTTP_204_NO_CONTENT)
async def put_notice(body: NoticeRequest, request: Request, key: DeviceKey) -> Response:
    """Tell the station's operator console something this client cannot resolve itself (a robot
    bridge: it lost the robot, or an answer stayed unclear and needs a Wizard-of-Oz answer);
    ``text: null`` clears it. The console shows it beside the device at once."""
    await as_device(
        request.app,
        key,
        write=True,
        op=lambda db, device: station_ops.notice(
            db, station=device.seat, device_id=device.device_id, body=body
        ),
    )
    return Response(status_code=status.HTTP_204_NO_CONTENT)
