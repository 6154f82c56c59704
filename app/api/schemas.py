"""Request and response bodies of the JSON API (unknown fields are refused, not ignored)."""

from __future__ import annotations

from datetime import datetime
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field


class RequestBody(BaseModel):
    """Base for request bodies: a misspelt field is an error, not a silent default."""

    model_config = ConfigDict(extra="forbid")


class StudyCreate(RequestBody):
    """A new study: its name and the protocol as TOML text."""

    name: str = Field(max_length=64, examples=["pilot-2026"])
    protocol_toml: str = Field(max_length=512 * 1024, description="The protocol file's content.")


class StudyStatusChange(RequestBody):
    """Open or close enrolment."""

    status: Literal["open", "closed"]


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
    created_at: datetime
    protocol_sha256: str
    blinded: bool
    enrolment: list[ConditionCount]


class EnrolmentRequest(RequestBody):
    """Enrol one participant; the code is generated (P001, P002…) when omitted."""

    code: str | None = Field(default=None, max_length=32, examples=["P017"])
    strata: dict[str, str] = Field(
        default_factory=dict, description="Values of the study's stratification factors."
    )


class Enrolled(BaseModel):
    """The allocation revealed at enrolment."""

    code: str
    condition: str = Field(description="Condition id, or its neutral label for blinded roles.")
    allocation_index: int | None = Field(
        description="Position in the stratum's sequence (null for a dropout replacement)."
    )
    stratum: str
    replaces: str | None = None


class ParticipantOut(BaseModel):
    """A participant as listed."""

    code: str
    condition: str
    stratum: str
    status: str
    enrolled_at: datetime
    withdrawn_at: datetime | None


class Withdrawal(RequestBody):
    """Why a participant leaves (optional, free text)."""

    reason: str = Field(default="", max_length=2000)


class Health(BaseModel):
    """Whether the service and its database answer."""

    status: Literal["ok", "unavailable"]
    database: str
