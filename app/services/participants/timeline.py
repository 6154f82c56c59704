"""One participant's whole record, in order: questionnaires, sessions, runs and steps.

While the study is blinded (app.services.blinding) the steps carry neither the learner's
probabilities nor the replies, their levels and the probabilities behind them: a reply history
would show which condition the participant is in."""

from __future__ import annotations

from dataclasses import dataclass, field
from datetime import datetime

from sqlalchemy import select
from sqlalchemy.orm import Session

from app.protocol import ItemKind, ItemSpec, Protocol
from app.services.blinding import shows_learners
from app.services.participants.languages import gloss
from app.services.studies import protocol_of
from app.tables import Answer, Participant, Prompt, Response, Run, Study, StudySession, Submission


@dataclass(frozen=True)
class Step:
    """A prompt and, once given, its answer and the robot's reply (``probabilities`` empty and
    the reply's fields None while the study is blinded)."""

    step_id: int
    category: str
    question: str
    probabilities: list[float]
    prompted_at: datetime
    actor: str
    answer: bool | None = None
    reply: str | None = None
    confidence: str | None = None
    probability: float | None = None
    answered_at: datetime | None = None
    gloss: str = ""
    """The question in the protocol's own language when it was asked in another ('' if not)."""


@dataclass
class RunRecord:
    """A run and its steps."""

    number: int
    status: str
    steps: list[Step] = field(default_factory=list)


@dataclass(frozen=True)
class ItemAnswer:
    """One stored answer with what it means: the item's text beside its key, and the label of
    the scale point or option chosen, so a record reads without the protocol file at hand."""

    key: str
    text: str
    value: str
    meaning: str = ""
    reverse: bool = False


@dataclass(frozen=True)
class QuestionnaireRecord:
    """A submitted questionnaire with its stored raw answers."""

    instrument: str
    title: str
    session: int | None
    submitted_at: datetime
    revision: int
    answers: list[ItemAnswer]


def _meaning(protocol: Protocol, item: ItemSpec, value: str) -> str:
    """The words for a stored value: the option's label, or the Likert point's own label when
    the scale labels every point (anchors alone label only the ends)."""
    if item.kind == ItemKind.CHOICE:
        return next((o.label for o in item.options if o.value == value), "")
    if item.kind != ItemKind.LIKERT or item.scale is None or not value.lstrip("-").isdigit():
        return ""
    scale, point = protocol.scale(item.scale), int(value)
    if len(scale.labels) == scale.maximum - scale.minimum + 1:
        points = range(scale.minimum, scale.maximum + 1)
        return dict(zip(points, scale.labels, strict=True)).get(point, "")
    if len(scale.labels) == 2:
        return {scale.minimum: scale.labels[0], scale.maximum: scale.labels[1]}.get(point, "")
    return ""


def _item_answer(
    protocol: Protocol, items: dict[str, ItemSpec], key: str, value: str
) -> ItemAnswer:
    item = items.get(key)
    if item is None:  # consent, a self-description, an item a later protocol version dropped
        return ItemAnswer(key, "", value)
    return ItemAnswer(key, item.text, value, _meaning(protocol, item, value), item.reverse)


@dataclass
class SessionRecord:
    """A session, its runs and the questionnaire that followed it."""

    number: int
    status: str
    started_at: datetime
    ended_at: datetime | None
    runs: list[RunRecord] = field(default_factory=list)
    questionnaires: list[QuestionnaireRecord] = field(default_factory=list)


@dataclass
class Timeline:
    """A participant's record."""

    before: list[QuestionnaireRecord]
    sessions: list[SessionRecord]
    after: list[QuestionnaireRecord]


def _questionnaires(
    db: Session, participant: Participant, protocol: Protocol
) -> list[QuestionnaireRecord]:
    titles = {i.key: i.title for i in protocol.questionnaires.instruments} | {"consent": "Consent"}
    order = {i.key: n for n, i in enumerate(protocol.questionnaires.instruments, start=1)}
    items = {
        i.key: {item.key: item for item in i.items} for i in protocol.questionnaires.instruments
    }
    responses: dict[tuple[str, int | None], list[ItemAnswer]] = {}
    for row in db.scalars(
        select(Response).where(Response.participant_id == participant.id).order_by(Response.id)
    ):
        answer = _item_answer(protocol, items.get(row.instrument, {}), row.item, row.value)
        responses.setdefault((row.instrument, row.session), []).append(answer)
    submissions = db.scalars(select(Submission).where(Submission.participant_id == participant.id))
    records = [
        QuestionnaireRecord(
            s.instrument,
            titles.get(s.instrument, s.instrument),
            s.session,
            s.submitted_at,
            s.revision,
            responses.get((s.instrument, s.session), []),
        )
        for s in submissions
    ]
    return sorted(records, key=lambda r: (r.session or 0, order.get(r.instrument, 0)))


def participant_timeline(db: Session, *, study: Study, participant: Participant) -> Timeline:
    """Everything recorded for a participant, oldest first."""
    protocol = protocol_of(study)
    learners = shows_learners(study)
    questionnaires = _questionnaires(db, participant, protocol)
    sessions = {
        s.id: SessionRecord(s.number, s.status, s.started_at, s.ended_at)
        for s in db.scalars(
            select(StudySession)
            .where(StudySession.participant_id == participant.id)
            .order_by(StudySession.number)
        )
    }
    runs: dict[int, RunRecord] = {}
    for run in db.scalars(
        select(Run).where(Run.participant_id == participant.id).order_by(Run.number)
    ):
        runs[run.id] = RunRecord(run.number, run.status)
        sessions[run.session_id].runs.append(runs[run.id])
    for prompt, answer in db.execute(
        select(Prompt, Answer)
        .outerjoin(Answer, Answer.prompt_id == Prompt.id)
        .where(Prompt.participant_id == participant.id)
        .order_by(Prompt.id)
    ):
        shown = answer if learners else None
        runs[prompt.run_id].steps.append(
            Step(
                prompt.id,
                prompt.category,
                prompt.question,
                prompt.probabilities if learners else [],
                prompt.prompted_at,
                prompt.actor,
                answer.answer if answer else None,
                shown.reply if shown else None,
                shown.confidence if shown else None,
                shown.probability if shown else None,
                answer.answered_at if answer else None,
                gloss(
                    protocol, category=prompt.category, action=prompt.action, asked=prompt.question
                ),
            )
        )
    by_number = {s.number: s for s in sessions.values()}
    for record in questionnaires:
        if record.session is not None and record.session in by_number:
            by_number[record.session].questionnaires.append(record)
    post = {i.key for i in protocol.instruments_at("post")}
    return Timeline(
        before=[q for q in questionnaires if q.session is None and q.instrument not in post],
        sessions=list(sessions.values()),
        after=[q for q in questionnaires if q.session is None and q.instrument in post],
    )
