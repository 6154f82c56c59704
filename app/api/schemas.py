"""Request and response bodies of the JSON API (unknown fields are refused, not ignored)."""

from __future__ import annotations

from datetime import datetime
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from app.protocol import MAX_PROTOCOL_BYTES


class RequestBody(BaseModel):
    """Base for request bodies: a misspelt field is an error, not a silent default."""

    model_config = ConfigDict(extra="forbid")


class StudyCreate(RequestBody):
    """A new study: its name and what it starts from, exactly one of the protocol as TOML text,
    a shipped protocol (``GET /api/v1/protocols``) or a copy of a study's protocol."""

    name: str = Field(max_length=64, examples=["pilot-2026"])
    title: str | None = Field(
        default=None,
        max_length=200,
        description="Shown on every page; the protocol's title when left out.",
        examples=["Pilot, spring 2026"],
    )
    protocol_toml: str | None = Field(
        default=None, max_length=MAX_PROTOCOL_BYTES, description="The protocol file's content."
    )
    shipped: str | None = Field(
        default=None,
        max_length=200,
        description="A shipped protocol's file name.",
        examples=["fast_adaptation_trust_sv.toml"],
    )
    copy_of: str | None = Field(
        default=None, max_length=64, description="The name of a study whose protocol to copy."
    )
    phase: Literal["draft", "pilot", "live"] = Field(
        default="live",
        description="live: enrols real participants now; pilot: enrolments are pilot "
        "participants; draft: nobody enrols while the protocol is edited and previewed.",
    )


class ShippedProtocol(BaseModel):
    """A protocol trustlab ships, to start a study from."""

    file: str
    title: str
    description: str
    languages: list[str]
    sha256: str


class StudyStatusChange(RequestBody):
    """Open or close enrolment."""

    status: Literal["open", "closed"]


class StudyPhaseChange(RequestBody):
    """Move a study between draft, pilot and live (live is final: the protocol is frozen)."""

    phase: Literal["draft", "pilot", "live"]


class PilotResetOut(BaseModel):
    """What a pilot reset deleted."""

    participants: list[str] = Field(description="The pilot participants' codes, now deleted.")
    removed: dict[str, int] = Field(description="Rows deleted per table.")


class ConditionCount(BaseModel):
    """Participants of one condition (or neutral group, for blinded roles) by status."""

    label: str
    active: int
    withdrawn: int
    completed: int


class StudySummary(BaseModel):
    """A study as listed."""

    name: str
    title: str
    status: str
    phase: str = Field(description="draft, pilot or live.")
    live_at: datetime | None = Field(description="When it went live, its protocol frozen.")
    pilots: int = Field(description="Pilot participants, not counted in ``enrolment``.")
    created_at: datetime
    protocol_sha256: str
    blinded: bool = Field(description="Whether the protocol blinds the study.")
    unblinded_at: datetime | None = Field(
        description="When an admin lifted the blinding; until then staff see no learner data."
    )
    enrolment: list[ConditionCount]


class EnrolmentRequest(RequestBody):
    """Enrol one participant; the code is generated (P001, P002…) when omitted."""

    code: str | None = Field(default=None, max_length=32, examples=["P017"])
    strata: dict[str, str] = Field(
        default_factory=dict, description="Values of the study's stratification factors."
    )
    language: str | None = Field(
        default=None,
        max_length=16,
        examples=["sv"],
        description="One of the study's languages; omitted: the study's first, or the "
        "participant chooses on the tablet when the protocol lets them.",
    )
    site: str | None = Field(
        default=None,
        max_length=40,
        examples=["uppsala"],
        description="One of the study's sites: required when it declares any, refused otherwise.",
    )


class Enrolled(BaseModel):
    """The allocation revealed at enrolment."""

    code: str
    condition: str = Field(description="Condition id, or its neutral label for blinded roles.")
    stratum: str
    replaces: str | None = None
    language: str | None = Field(
        default=None, description="The participant's language (None: chosen on the tablet)."
    )
    site: str | None = Field(default=None, description="The participant's site, if any.")


class ConsentStandingOut(BaseModel):
    """Where a participant stands with the study's consent text (docs/data-protection.md)."""

    current_version: int = Field(description="The study's current consent version.")
    accepted_version: int | None = Field(
        description="The latest version they accepted (None: they have not consented yet)."
    )
    declined_version: int | None = Field(
        description="The latest version they declined, when later than the one they accepted."
    )
    reconsent_needed: bool = Field(
        description="They accepted an older version than the current one."
    )
    before_next_session: bool = Field(
        description=(
            "The protocol has them consent again before their next session "
            "(`reconsent_before_next_session`): until they do, no session starts for them."
        )
    )


class ParticipantOut(BaseModel):
    """A participant as listed."""

    code: str
    condition: str
    stratum: str
    status: str
    enrolled_at: datetime
    withdrawn_at: datetime | None
    locked: bool = False
    language: str | None = Field(
        default=None, description="The participant's language (None: not chosen yet)."
    )
    site: str | None = Field(
        default=None, description="The participant's site (None in a study without sites)."
    )
    pilot: bool = Field(
        default=False, description="A pilot participant: left out of every analysis."
    )
    consent: ConsentStandingOut | None = Field(
        default=None, description="Where they stand with the consent text (None: erased)."
    )


class Withdrawal(RequestBody):
    """Why a participant leaves (optional, free text)."""

    reason: str = Field(default="", max_length=2000)


class ErasureRequest(RequestBody):
    """Erase everything a participant gave the study; ``confirm`` repeats their code."""

    confirm: str = Field(
        max_length=64, description="The participant's code again: erasure cannot be undone."
    )
    reason: str = Field(default="", max_length=2000, description="Not stored with the data.")


class EarlierCopyOut(BaseModel):
    """A backup or export made before the erasure that may still hold the participant."""

    kind: str
    made_at: datetime
    where: str
    exists: bool | None = Field(
        description="Whether the file is still on the server (null: unknown)."
    )


class ErasureOut(BaseModel):
    """What an erasure removed (rows per table) and the earlier copies the audit log knows of."""

    code: str
    study: str
    erased_at: datetime
    removed: dict[str, int]
    earlier_copies: list[EarlierCopyOut]


class Health(BaseModel):
    """Whether the service and its database answer."""

    status: Literal["ok", "unavailable"]
    database: str


class TabletLink(BaseModel):
    """A tablet link: open ``url`` on the tablet (or scan its QR code)."""

    token: str | None
    url: str | None


class ErrorOut(BaseModel):
    """Every refusal: one sentence saying what is wrong and what is expected instead."""

    detail: str


class FieldError(BaseModel):
    """Where a request did not validate, and why."""

    loc: list[str | int]
    msg: str
    type: str


class ValidationErrorOut(BaseModel):
    """A request that did not validate: the first problems in one sentence, then all of them."""

    detail: str
    errors: list[FieldError] = Field(default_factory=list)


ERROR_RESPONSES: dict[int | str, dict[str, object]] = {
    400: {"model": ErrorOut, "description": "Malformed request"},
    401: {"model": ErrorOut, "description": "Not signed in, or no valid key or token"},
    403: {"model": ErrorOut, "description": "Not allowed for this role, or a missing CSRF token"},
    404: {"model": ErrorOut, "description": "No such study, participant, station or step"},
    409: {"model": ErrorOut, "description": "Not possible in the current state"},
    413: {"model": ErrorOut, "description": "Request body too large"},
    422: {"model": ValidationErrorOut, "description": "Invalid content"},
    429: {"model": ErrorOut, "description": "Too many attempts; retry later"},
    503: {"model": ErrorOut, "description": "Database unavailable; retry"},
}
"""Documented on every API route, so clients (and schemathesis) know every error's shape."""
