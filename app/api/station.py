"""The robot-facing API: a device key speaks for one station and whoever is assigned there."""

from __future__ import annotations

from fastapi import APIRouter, Request, Response, status

from app.api import station_ops
from app.api.device_work import DeviceKey, as_device, device_actor
from app.api.runtime_schemas import (
    AnswerOut,
    AnswerRequest,
    PromptOut,
    PromptRequest,
    StationStateOut,
    StepIdPath,
)

router = APIRouter(prefix="/station", tags=["robot"])


@router.get("")
async def get_state(request: Request, key: DeviceKey) -> StationStateOut:
    """The station's participant, session, run, open prompts and what to do next."""
    return await as_device(
        request.app,
        key,
        write=False,
        op=lambda db, device: station_ops.state(db, station=device.seat),
    )


@router.post(
    "/prompts",
    status_code=status.HTTP_201_CREATED,
    responses={200: {"description": "The category's open prompt, handed out again."}},
)
async def prompt(
    body: PromptRequest, request: Request, key: DeviceKey, response: Response
) -> PromptOut:
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
    if not out.created:
        response.status_code = status.HTTP_200_OK
    return out


@router.post("/steps/{step_id}/answer")
async def answer(
    step_id: StepIdPath, body: AnswerRequest, request: Request, key: DeviceKey
) -> AnswerOut:
    """Record the participant's yes/no answer (exactly once) and get the robot's reply."""
    return await as_device(
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


@router.post("/runs", status_code=status.HTTP_201_CREATED)
async def start_run(request: Request, key: DeviceKey) -> StationStateOut:
    """Start the next run (optional: prompting after a finished run starts it too)."""
    return await as_device(
        request.app,
        key,
        write=True,
        op=lambda db, device: station_ops.start_run(
            db, station=device.seat, actor=device_actor(device)
        ),
    )
