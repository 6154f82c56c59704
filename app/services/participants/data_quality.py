"""Each participant's data-quality measures and flags, computed from what is stored.

Nothing here is stored as a verdict: the answers, each page's timing (``submission``), the room's
time away and the online duplicate flag (``online_participation``) are the facts, and the
protocol's ``[quality]`` rules (app/quality.py) turn them into flags whenever they are read. So a
flag can never disagree with the data it is drawn from, and the exports, the dashboard and the
analysis's exclusions (app.services.analysis_views.study_data) all see the same flags.

A participant's flags take their pages as they were first submitted (the timing of the first
submission; revisions keep it) and their answers as they stand.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass, field

from sqlalchemy import ColumnElement, select
from sqlalchemy.orm import Session

from analysis import dataset as analysis_dataset
from app.protocol import ItemKind, Protocol
from app.quality import Flag, QualitySpec, flag_names
from app.tables import OnlineParticipation, Participant, Response, Submission

QUALITY_COLUMNS = tuple(analysis_dataset.QUALITY_COLUMNS)
"""The participant columns every export carries when the study has data-quality rules (their
labels are the codebook's: analysis.dataset.QUALITY_COLUMNS)."""


@dataclass
class ParticipantQuality:
    """One participant's measures, and the flags the rules draw from them."""

    attention_checks: int = 0
    """Attention-check items they answered."""
    attention_failed: int = 0
    """Of those, answered otherwise than expected."""
    fastest_seconds_per_item: float | None = None
    """The quickest of their timed questionnaire pages, in seconds per item."""
    straightlined_pages: list[str] = field(default_factory=list)
    """The pages (``instrument`` or ``instrument:session``) given one point throughout."""
    seconds_away: float = 0.0
    """Time their questionnaire pages and room were hidden, in all."""
    second_id: bool = False
    """Online: their browser had joined under another recruitment ID."""
    flags: tuple[Flag, ...] = ()

    def columns(self) -> dict[str, object]:
        """The export columns (:data:`QUALITY_COLUMNS`)."""
        return {
            analysis_dataset.QUALITY_FLAGS_COLUMN: flag_names(self.flags),
            "attention_failed": self.attention_failed,
            "fastest_seconds_per_item": self.fastest_seconds_per_item,
            "straightlined_pages": len(self.straightlined_pages),
            "seconds_away": round(self.seconds_away, 1),
        }

    def reasons(self) -> list[str]:
        """Each flag with what raised it, in words for staff pages and the report."""
        said = {
            Flag.ATTENTION: f"failed {self.attention_failed} of {self.attention_checks} "
            "attention checks",
            Flag.SPEEDING: f"a page at {self.fastest_seconds_per_item} s per item",
            Flag.STRAIGHTLINING: "one answer throughout " + ", ".join(self.straightlined_pages),
            Flag.AWAY: f"away from the study for {round(self.seconds_away)} s",
            Flag.SECOND_ID: "their browser had joined under another recruitment ID",
        }
        return [f"{flag.value}: {said[flag]}" for flag in self.flags]


def _page(instrument: str, session: int | None) -> str:
    return instrument if session is None else f"{instrument}:{session}"


def quality_by_participant(
    db: Session, protocol: Protocol, whom: ColumnElement[bool]
) -> dict[int, ParticipantQuality]:
    """The measures and flags of every participant ``whom`` selects (a query that takes the
    reader's scope: app.services.analysis_views.study_data), by participant id. Empty when the
    protocol has no data-quality rules (:meth:`app.protocol.Protocol.quality_rules`)."""
    rules = protocol.quality_rules()
    if rules is None:
        return {}
    ids = list(db.scalars(select(Participant.id).where(whom)))
    found: dict[int, ParticipantQuality] = {pid: ParticipantQuality() for pid in ids}
    if not ids:
        return found
    _answers(db, protocol, rules, whom, found)
    _page_times(db, protocol, whom, found)
    online = (
        select(
            OnlineParticipation.participant_id,
            OnlineParticipation.room_seconds_away,
            OnlineParticipation.flags,
        )
        .join(Participant, Participant.id == OnlineParticipation.participant_id)
        .where(whom)
    )
    for participant_id, away, flags in db.execute(online):
        record = found[participant_id]
        record.seconds_away += away or 0.0
        record.second_id = bool((flags or {}).get(Flag.SECOND_ID.value))
    for record in found.values():
        record.flags = _flags(record, rules)
    return found


def _answers(
    db: Session,
    protocol: Protocol,
    rules: QualitySpec,
    whom: ColumnElement[bool],
    found: dict[int, ParticipantQuality],
) -> None:
    """Attention checks and straight-lining, from the stored answers."""
    expected = {(key, item.key): item for key, item in protocol.attention_checks()}
    likert: dict[str, set[str]] = {
        instrument.key: {
            item.key
            for item in instrument.items
            if item.kind is ItemKind.LIKERT and item.expected is None
        }
        for instrument in protocol.questionnaires.instruments
    }
    rows = db.execute(
        select(
            Response.participant_id,
            Response.instrument,
            Response.session,
            Response.item,
            Response.value,
        )
        .join(Participant, Participant.id == Response.participant_id)
        .where(whom)
    )
    points: dict[tuple[int, str, int | None], list[str]] = defaultdict(list)
    for participant_id, instrument, session, item, value in rows:
        check = expected.get((instrument, item))
        if check is not None:
            record = found[participant_id]
            record.attention_checks += 1
            if not _as_expected(value, check.expected, check.kind):
                record.attention_failed += 1
        elif item in likert.get(instrument, ()):
            points[(participant_id, instrument, session)].append(value)
    for (participant_id, instrument, session), given in sorted(
        points.items(), key=lambda entry: (entry[0][0], entry[0][1], entry[0][2] or 0)
    ):
        if len(given) >= rules.straightlining_min_items and len(set(given)) == 1:
            found[participant_id].straightlined_pages.append(_page(instrument, session))


def _as_expected(value: str, expected: str | None, kind: ItemKind) -> bool:
    if kind is ItemKind.CHOICE or expected is None:
        return value == expected
    try:
        return int(value) == int(expected)
    except ValueError:
        return False


def _page_times(
    db: Session,
    protocol: Protocol,
    whom: ColumnElement[bool],
    found: dict[int, ParticipantQuality],
) -> None:
    """Seconds per item of each timed page, and the time its tab was hidden."""
    items = {i.key: len(i.items) for i in protocol.questionnaires.instruments}
    rows = db.execute(
        select(
            Submission.participant_id,
            Submission.instrument,
            Submission.seconds_on_page,
            Submission.seconds_away,
        )
        .join(Participant, Participant.id == Submission.participant_id)
        .where(whom, Submission.seconds_on_page.is_not(None))
    )
    for participant_id, instrument, seconds, away in rows:
        record = found[participant_id]
        record.seconds_away += away or 0.0
        count = items.get(instrument)
        if not count or seconds is None:  # the consent page, or an instrument since dropped
            continue
        per_item = round(seconds / count, 2)
        if record.fastest_seconds_per_item is None or per_item < record.fastest_seconds_per_item:
            record.fastest_seconds_per_item = per_item


def _flags(record: ParticipantQuality, rules: QualitySpec) -> tuple[Flag, ...]:
    raised = []
    if record.attention_failed > rules.attention_failures_allowed:
        raised.append(Flag.ATTENTION)
    fastest = record.fastest_seconds_per_item
    if fastest is not None and fastest < rules.min_seconds_per_item:
        raised.append(Flag.SPEEDING)
    if record.straightlined_pages:
        raised.append(Flag.STRAIGHTLINING)
    if rules.max_away_seconds is not None and record.seconds_away > rules.max_away_seconds:
        raised.append(Flag.AWAY)
    if record.second_id:
        raised.append(Flag.SECOND_ID)
    return tuple(raised)
