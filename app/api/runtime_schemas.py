"""Bodies of the session-runtime API, shared by the robot routes, the experimenter's
Wizard-of-Oz routes, the station WebSocket (which carries the same JSON) and app/client.py.

Pure pydantic: importing this module pulls in neither the database nor the adaptation engine."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from fastapi import Path
from pydantic import BaseModel, Field

from app.api.schemas import RequestBody
from app.inputs import RowId

StepIdPath = Annotated[RowId, Path(description="The step's id.")]
"""A step id in a route's path: out of range or not plain digits is a 422 (app/inputs.py)."""


class PromptRequest(RequestBody):
    """Ask for the question of one category."""

    category: str = Field(max_length=40, examples=["conation"])


class AnswerRequest(RequestBody):
    """The participant's yes/no answer to a step, with a key that makes retries safe."""

    answer: Literal["yes", "no"]
    idempotency_key: str = Field(
        min_length=1, max_length=100, description="Unique per answer; reuse it when retrying."
    )


class Assignment(RequestBody):
    """Which participant sits at the station."""

    study: str = Field(max_length=64)
    code: str = Field(max_length=32)


class StationCreate(RequestBody):
    """A new station."""

    name: str = Field(max_length=64, examples=["lab-1"])


class DeviceCreate(RequestBody):
    """A new device key for a station."""

    label: str = Field(default="robot", max_length=64, examples=["pepper"])


class ExpectedOut(BaseModel):
    """What the station should do next."""

    action: Literal["assign", "start_session", "wait", "prompt", "answer", "done", "none"]
    message: str
    categories: list[str]
    step_id: int | None
    session: int | None


WITHHELD = " Null for staff while the study is blinded (docs/experimenter-guide.md, Blinding)."


class _PromptFields(BaseModel):
    step_id: int
    category: str
    action: int = Field(description="Index of the chosen question among the category's K.")
    question: str
    adapts: bool = Field(description="False in the familiarisation run: answers are not learned.")
    session: int
    run: int
    created: bool = Field(description="False when this is the category's open prompt again.")


class PromptOut(_PromptFields):
    """A step's question: ask it, then post the yes/no answer to ``step_id``."""

    probabilities: list[float] = Field(description="The learner's probabilities when choosing.")


class StaffPromptOut(_PromptFields):
    """A prompt as the experimenter's Wizard-of-Oz routes return it."""

    probabilities: list[float] | None = Field(
        description="The learner's probabilities when choosing." + WITHHELD
    )


class _AnswerFields(BaseModel):
    step_id: int
    category: str
    answer: Literal["yes", "no"]
    reply: str
    replayed: bool = Field(description="True when this answer had been recorded before.")
    run_completed: bool
    session_completed: bool
    expected: ExpectedOut


class AnswerOut(_AnswerFields):
    """The robot's reply to an answer, and the learner's updated probabilities."""

    confidence_level: int
    confidence: str
    probability: float = Field(description="The probability the reply's confidence comes from.")
    probabilities: list[float] = Field(description="The learner's probabilities after the answer.")


class StaffAnswerOut(_AnswerFields):
    """An answer as the experimenter's Wizard-of-Oz routes return it."""

    confidence_level: int | None = Field(description="The reply's level." + WITHHELD)
    confidence: str | None = Field(description="The reply level's name." + WITHHELD)
    probability: float | None = Field(
        description="The probability the reply's confidence comes from." + WITHHELD
    )
    probabilities: list[float] | None = Field(
        description="The learner's probabilities after the answer." + WITHHELD
    )


class SessionOut(BaseModel):
    """The participant's current session."""

    number: int
    status: str
    runs: int
    familiarisation: bool


class RunOut(BaseModel):
    """The current run."""

    number: int
    status: str
    answered: list[str]
    pending: list[str]


class _StateFields(BaseModel):
    station: str
    participant: str | None
    study: str | None
    session: SessionOut | None
    run: RunOut | None
    expected: ExpectedOut


class StationStateOut(_StateFields):
    """Where a station stands (participant codes only: conditions are never shown to clients)."""

    open_prompts: list[PromptOut]


class StaffStationStateOut(_StateFields):
    """Where a station stands, as the experimenter's routes return it."""

    open_prompts: list[StaffPromptOut]


class DeviceOut(BaseModel):
    """A device key's public facts."""

    id: int
    station: str
    label: str
    key_prefix: str
    created_at: Any
    revoked_at: Any | None
    last_seen_at: Any | None


class IssuedDeviceOut(DeviceOut):
    """A new device and its key, shown this once."""

    key: str


class StationOut(BaseModel):
    """A station, who is assigned and its devices."""

    name: str
    participant: str | None
    study: str | None
    devices: list[DeviceOut]
