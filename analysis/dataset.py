"""What the app hands to the analysis: one :class:`StudyDataset` per study.

The web layer loads the study from its database into three plain frames plus the protocol
summary, the instrument specifications and a manifest, and passes them here. Everything the
report and the exports need is in this one object, so analysis never touches the database.

Frames
------
participants
    One row per enrolled participant. Required columns: ``participant`` (str, the code),
    ``condition`` (str, e.g. ``"C1"``; neutral labels if the viewer is blinded), ``status``
    (str, e.g. ``"completed"``, ``"active"``, ``"withdrawn"``). Any further column (e.g. the
    randomisation strata ``gender``, ``site``) is kept and exported as a participant attribute.
responses
    Long raw answers, one row per participant × instrument × session × item: ``participant``
    (str), ``instrument`` (str), ``session`` (nullable ``Int64``; NA for once-only
    instruments), ``item`` (str), ``value`` (number; categorical items may be codes or
    strings, free text is a string). See :mod:`analysis.scoring`.
steps
    The adaptation step log (see :mod:`analysis.adaptation` for the columns); may be empty.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, NotRequired, TypedDict

import pandas as pd

from analysis._checks import describe_keys, require_columns
from analysis.adaptation import STEP_COLUMNS
from analysis.errors import InvalidInputError
from analysis.instruments import DEFAULT_INSTRUMENTS, InstrumentSpec
from analysis.scoring import DEFAULT_SCALES, RESPONSE_COLUMNS, ScaleSpec

__all__ = [
    "DEFAULT_EXCLUDED_STATUSES",
    "PARTICIPANT_COLUMNS",
    "QUALITY_COLUMNS",
    "QUALITY_FLAGS_COLUMN",
    "ConditionSummary",
    "ProtocolSummary",
    "StudyDataset",
    "empty_steps",
    "validate_protocol",
]

PARTICIPANT_COLUMNS = ("participant", "condition", "status")
"""Required columns of the participants frame; extra columns are participant attributes."""

DEFAULT_EXCLUDED_STATUSES = frozenset({"withdrawn"})
"""Participant statuses left out of the statistics (listed as exclusions in the report)."""

QUALITY_FLAGS_COLUMN = "quality_flags"
"""The participant column naming each participant's data-quality flags, ``;``-separated (empty:
none). A study's ``excluded_flags`` leave the participants who have them out of the analysis."""
QUALITY_COLUMNS: dict[str, tuple[str, str]] = {
    QUALITY_FLAGS_COLUMN: (
        "Data-quality flags raised, separated by ';' (attention, speeding, straightlining, "
        "away, second_id_same_browser)",
        "string",
    ),
    "attention_failed": ("Attention checks answered otherwise than expected", "numeric"),
    "fastest_seconds_per_item": (
        "Quickest timed questionnaire page, in seconds per item",
        "numeric",
    ),
    "straightlined_pages": (
        "Questionnaire pages with the same answer to every Likert item",
        "numeric",
    ),
    "seconds_away": (
        "Seconds the study's page was hidden (another tab or window in front)",
        "numeric",
    ),
}
"""The data-quality participant columns a study with data-quality rules carries, with their
codebook label and type (the app computes them: app/services/participants/data_quality.py)."""


class ConditionSummary(TypedDict):
    """One experimental condition as the methods paragraph names it."""

    code: str
    """Stored condition code, e.g. ``"C1"``."""
    label: str
    """Short name, e.g. ``"Exp3 bandit"``."""
    description: NotRequired[str]
    """One sentence on what the robot does in this condition."""


class ProtocolSummary(TypedDict):
    """The parts of a study protocol the report describes (a plain JSON-able dict)."""

    study: str
    """The study's own title (as the lab named it; not the protocol's, which studies share)."""
    conditions: list[ConditionSummary]
    """Conditions in allocation order."""
    categories: dict[str, list[str]]
    """Category key → question texts in arm order (arm index = list position)."""
    preferred_arms: dict[str, int]
    """Category key → 0-based index of the question participants are told to prefer."""
    sessions: int
    """Number of sessions (the within-subject factor)."""
    runs_per_session: int
    """Runs per session; each run prompts every category once."""
    quality: NotRequired[dict[str, Any]]
    """The data-quality rules (the protocol's ``[quality]``: ``min_seconds_per_item``,
    ``straightlining_min_items``, ``max_away_seconds``, ``attention_failures_allowed`` and the
    flags it ``exclude``s), when the study has them."""
    familiarisation_runs: NotRequired[int]
    """Runs before session 1 that are not used for adaptation (default 1)."""
    allocation: NotRequired[str]
    """How participants were allocated, e.g. "permuted blocks of 2 and 4, stratified by gender"."""
    feedback: NotRequired[str]
    """How answers become rewards, e.g. "yes → 1, no → 0"."""
    version: NotRequired[str]
    """Protocol version or file hash."""
    reply_levels: NotRequired[list[str]]
    """Names of the robot's reply levels, least to most confident (the step log's
    ``reply_level`` indexes them)."""
    languages: NotRequired[list[str]]
    """The study's languages, its protocol's own first; with two or more the linear mixed models
    adjust for language (:mod:`analysis.specification`) and the report names each translation."""
    translations: NotRequired[dict[str, dict[str, Any]]]
    """Per further language: ``source`` (where the translation comes from; '' when not given)
    and ``instruments``: instrument key → ``title``, ``citation`` and ``items`` (item key → its
    wording) in that language. The codebook lists the wordings, the report cites the sources."""
    record_audio: NotRequired[bool]
    """Whether the participants' spoken answers were recorded as audio (``[speech]
    record_audio``; the codebook lists the recordings)."""
    sites: NotRequired[list[str]]
    """The sites of a multi-site study; with two or more the linear mixed models adjust for
    site (:mod:`analysis.specification`)."""
    population: NotRequired[dict[str, Any]]
    """The population C2 was meta-trained for (issue 20): ``sha256``, ``source`` (in words),
    ``enrolling_reason`` and per category ``participants``, ``prior``, ``prior_ci``, ``slip``,
    ``slip_ci``, ``hazard``; absent when C2 was trained on the uniform prior."""


def validate_protocol(protocol: Mapping[str, Any]) -> None:
    """Refuse a protocol summary that lacks a required key or has a wrong type, naming it."""
    if not isinstance(protocol, Mapping):
        raise InvalidInputError("protocol must be a dict")
    required: dict[str, type | tuple[type, ...]] = {
        "study": str,
        "conditions": list,
        "categories": dict,
        "preferred_arms": dict,
        "sessions": int,
        "runs_per_session": int,
    }
    for key, kind in required.items():
        if key not in protocol:
            raise InvalidInputError(f"protocol: missing key {key!r}")
        if not isinstance(protocol[key], kind) or isinstance(protocol[key], bool):
            raise InvalidInputError(f"protocol.{key}: expected {getattr(kind, '__name__', kind)}")
    for i, condition in enumerate(protocol["conditions"]):
        if not isinstance(condition, Mapping) or not {"code", "label"} <= set(condition):
            raise InvalidInputError(f"protocol.conditions[{i}]: needs 'code' and 'label'")
    if protocol["sessions"] < 1 or protocol["runs_per_session"] < 1:
        raise InvalidInputError("protocol: sessions and runs_per_session must be at least 1")
    for category, arm in protocol["preferred_arms"].items():
        questions = protocol["categories"].get(category)
        if questions is None:
            raise InvalidInputError(f"protocol.preferred_arms.{category}: unknown category")
        if not isinstance(arm, int) or not 0 <= arm < len(questions):
            raise InvalidInputError(
                f"protocol.preferred_arms.{category}: {arm!r} is not an arm index "
                f"(0–{len(questions) - 1})"
            )
    missing = sorted(set(protocol["categories"]) - set(protocol["preferred_arms"]))
    if missing:
        raise InvalidInputError(f"protocol.preferred_arms: no preferred arm for {missing}")


def empty_steps() -> pd.DataFrame:
    """A step log with the right columns and no rows (a study that has not started)."""
    return pd.DataFrame({column: pd.Series(dtype=object) for column in STEP_COLUMNS})


@dataclass(frozen=True)
class StudyDataset:
    """Everything the analysis, the exports and the report need about one study.

    Attributes
    ----------
    participants : pandas.DataFrame
        See the module docstring (``participant``, ``condition``, ``status`` + attributes).
    responses : pandas.DataFrame
        Long raw answers (``participant``, ``instrument``, ``session``, ``item``, ``value``).
    protocol : ProtocolSummary
        Conditions, categories, preferred arms, sessions, runs.
    steps : pandas.DataFrame
        Adaptation step log; default empty.
    manifest : mapping
        Provenance shown verbatim in the report: e.g. ``data_sha256``, ``software``
        (name → version), ``protocol_sha256``, ``checkpoints`` (name → sha256), ``seeds``,
        ``exported_at``. JSON-serialisable values.
    instruments : tuple of InstrumentSpec
        Specifications of every instrument present in ``responses`` (default: the seed paper's).
    scales : tuple of ScaleSpec
        Scores to compute (default: TIPI and NARS).
    excluded_statuses : frozenset of str
        Participants with these statuses are left out of the statistics and listed as excluded.
    excluded_flags : frozenset of str
        Participants with any of these data-quality flags (:data:`QUALITY_FLAGS_COLUMN`) are
        left out of the statistics and listed as excluded: the protocol's pre-registered rules.
    steps_withheld : str
        Why ``steps`` is left empty although steps were recorded (a blinded study that has not
        been unblinded); shown where the adaptation results would be. Empty: nothing withheld.
    registration : mapping or None
        The study's pre-registration (``prereg.json``, :mod:`analysis.prereg`), when it has one:
        the report then says whether its analyses are those registered, or lists each deviation.
    registration_source : str
        Where the registration came from (a file and its SHA-256, or the audit log), for the
        report.

    Raises
    ------
    InvalidInputError
        Missing columns, duplicate participant codes, a participant without a condition, or
        answers/steps of participants that are not in ``participants``.
    """

    participants: pd.DataFrame
    responses: pd.DataFrame
    protocol: ProtocolSummary
    steps: pd.DataFrame = field(default_factory=empty_steps)
    manifest: Mapping[str, Any] = field(default_factory=dict)
    instruments: tuple[InstrumentSpec, ...] = DEFAULT_INSTRUMENTS
    scales: tuple[ScaleSpec, ...] = DEFAULT_SCALES
    excluded_statuses: frozenset[str] = DEFAULT_EXCLUDED_STATUSES
    excluded_flags: frozenset[str] = frozenset()
    steps_withheld: str = ""
    registration: Mapping[str, Any] | None = None
    registration_source: str = ""

    def __post_init__(self) -> None:
        for name in ("participants", "responses", "steps"):
            if not isinstance(getattr(self, name), pd.DataFrame):
                raise InvalidInputError(f"StudyDataset.{name} must be a pandas DataFrame")
        require_columns(self.participants, PARTICIPANT_COLUMNS, "participants")
        require_columns(self.responses, RESPONSE_COLUMNS, "responses")
        require_columns(self.steps, STEP_COLUMNS, "steps")
        validate_protocol(self.protocol)
        codes = self.participants["participant"]
        if codes.isna().any() or self.participants["condition"].isna().any():
            raise InvalidInputError(
                "participants: every row needs a participant code and condition"
            )
        duplicated = codes[codes.duplicated()]
        if len(duplicated):
            raise InvalidInputError(
                f"participants: code(s) {describe_keys(list(duplicated))} appear twice"
            )
        known = set(codes)
        for name in ("responses", "steps"):
            frame: pd.DataFrame = getattr(self, name)
            strangers = sorted(set(frame["participant"].dropna().unique()) - known, key=str)
            if strangers:
                raise InvalidInputError(
                    f"{name} mention participant(s) {describe_keys(strangers)} that are not in "
                    "participants"
                )
        if self.excluded_flags and QUALITY_FLAGS_COLUMN not in self.participants.columns:
            raise InvalidInputError(
                f"participants: excluding by data-quality flags needs a {QUALITY_FLAGS_COLUMN!r} "
                "column"
            )
        declared = {c["code"] for c in self.protocol["conditions"]}
        undeclared = sorted(set(self.participants["condition"]) - declared, key=str)
        if undeclared:
            raise InvalidInputError(
                f"participants: condition(s) {describe_keys(undeclared)} are not in the protocol"
            )

    @property
    def attribute_columns(self) -> list[str]:
        """Participant columns beyond code, condition and status (e.g. strata)."""
        return [c for c in self.participants.columns if c not in PARTICIPANT_COLUMNS]

    @property
    def condition_labels(self) -> dict[str, str]:
        """Condition code → label, from the protocol."""
        return {c["code"]: c["label"] for c in self.protocol["conditions"]}

    def flagged(self) -> pd.Series:
        """Per participant row: the excluding data-quality flags they have, ``;``-separated
        (empty: none, or the study excludes by none)."""
        if not self.excluded_flags:
            return pd.Series("", index=self.participants.index, dtype=object)
        cells = self.participants[QUALITY_FLAGS_COLUMN].fillna("").astype(str)
        return cells.map(
            lambda cell: ";".join(f for f in cell.split(";") if f in self.excluded_flags)
        )

    def instrument(self, name: str) -> InstrumentSpec:
        """The specification of instrument ``name``."""
        for spec in self.instruments:
            if spec.name == name:
                return spec
        raise InvalidInputError(f"no instrument {name!r} in this dataset")
