"""Questionnaires: where each participant is in the flow, validation, and all-or-nothing submission.

The participant flow is data (DESIGN.md, after oTree): consent → each pre-study instrument →
"please wait for the experimenter" → after every session its questionnaire → after the last
session the post-study instruments → thank you. :func:`next_page` computes the one page a
participant should see from what is stored, so reloads, back buttons, second tabs and crashed
tablets always land right. When an admin adds a new version of the consent text and the protocol
asks for it (``reconsent_before_next_session``), a participant who accepted an older one is shown
the new one before anything else (app.services.privacy.consent).

A submission is validated as a whole against the protocol's instrument (required items, ranges,
options, lengths, unknown items) and then stored in one transaction: the long-format responses, the
submission record, audit entries for every changed value (with the old value), and a live event.
Nothing partial is ever stored. Submitting a page again revises its answers. Locking a participant
freezes their answers for analysis: every submission (consent, new pages and revisions) is refused
until the experimenter unlocks them. A submission reads the participant again inside its own
transaction (locked on PostgreSQL), so a lock or a withdrawal committed a moment earlier — after
the tablet was identified, say — is always seen.

Where a participant stands (their submitted pages and ended sessions) is one query
(:func:`progress`); a submission computes the page that follows from what it read and wrote, so
its response needs no further query and no second transaction.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from sqlalchemy import CompoundSelect, bindparam, func, insert, literal, null, select, union_all
from sqlalchemy.orm import Session

from app import events
from app.errors import Conflict, InvalidInput, NotFound
from app.i18n.catalogues import Message
from app.protocol import InstrumentSpec, ItemKind, ItemSpec, Protocol
from app.services import audit
from app.services.audit import Actor
from app.services.participants import languages, participant_changes
from app.services.participants.participant_changes import Change
from app.services.privacy import consent, sites
from app.services.sessions.stations import station_topic
from app.services.topics import participant_topic, study_topic
from app.tables import (
    ConsentRecord,
    ConsentVersion,
    Participant,
    ParticipantStatus,
    Response,
    SessionStatus,
    Station,
    Study,
    StudySession,
    Submission,
    utcnow,
)

CONSENT = "consent"
DESCRIPTION_SUFFIX = "_description"
DESCRIPTION_MAX = 200
TIMING_FIELDS = ("page-seconds", "away-seconds")
"""The form fields in which a page reports how long it was open and how long hidden (names no
item key can have: keys are snake case)."""
LONGEST_PAGE_SECONDS = 7 * 24 * 3600.0
"""More than a week on one page is no measurement (a clock changed under the page)."""


@dataclass(frozen=True)
class PageTiming:
    """How long a questionnaire page was open before its first submission and, of that, how
    long its tab was hidden, as the page measured them (static/js/tablet.js): the 'speeding'
    and 'away' flags are computed from them (app/services/participants/data_quality.py)."""

    seconds_on_page: float
    seconds_away: float

    @classmethod
    def from_form(cls, fields: Mapping[str, str]) -> PageTiming | None:
        """The timing a form reported (None: it reported none, e.g. a page without its script);
        InvalidInput for values that are not seconds."""
        page, away = (fields.get(name, "").strip() for name in TIMING_FIELDS)
        if not page and not away:
            return None
        try:
            on_page, hidden = float(page), float(away or "0")
        except ValueError:
            raise InvalidInput("the page's timing is not a number of seconds") from None
        if not (0 <= on_page <= LONGEST_PAGE_SECONDS and 0 <= hidden <= LONGEST_PAGE_SECONDS):
            raise InvalidInput("the page's timing is out of range")
        return cls(round(on_page, 3), round(min(hidden, on_page), 3))


@dataclass(frozen=True)
class Page:
    """The page a participant should see now."""

    kind: str  # language | consent | questionnaire | wait | done | withdrawn
    instrument: InstrumentSpec | None = None
    session: int | None = None

    @property
    def path(self) -> str:
        """Where the tablet shows this page."""
        if self.kind == "questionnaire" and self.instrument is not None:
            suffix = f"/{self.session}" if self.session is not None else ""
            return f"/tablet/q/{self.instrument.key}{suffix}"
        return f"/tablet/{self.kind}"


class QuestionnaireInvalid(InvalidInput):
    """Some items are missing or invalid; ``errors`` maps item keys to messages for the page."""

    def __init__(self, errors: dict[str, str]) -> None:
        first = next(iter(errors.items()))
        super().__init__(
            f"{len(errors)} items need attention, e.g. {first[0]}: {first[1]}"
            if len(errors) > 1
            else f"{first[0]}: {first[1]}"
        )
        self.errors = errors

    @property
    def extra(self) -> dict[str, object]:
        """The per-item messages for API clients, in the shape of every other 422's ``errors``."""
        return {
            "errors": [
                {"loc": ["body", "answers", item], "msg": message, "type": "questionnaire_item"}
                for item, message in self.errors.items()
            ]
        }


@dataclass
class Progress:
    """Where a participant stands: the pages they submitted, the sessions that are over, and the
    version of the consent text they last accepted beside the study's current one."""

    done: set[tuple[str, int | None]]
    closed: list[int]
    consent_accepted: int | None = None
    consent_current: int = 1

    @property
    def consent_outdated(self) -> bool:
        """They accepted an older version of the consent text than the current one."""
        return self.consent_accepted is not None and self.consent_accepted < self.consent_current


_CURRENT_CONSENT = "#consent-current"
_ACCEPTED_CONSENT = "#consent-accepted"
"""Markers of the consent versions' rows in :data:`_PROGRESS` (never an instrument key)."""


_PROGRESS: CompoundSelect[str | None, int | None] = union_all(
    select(Submission.instrument, Submission.session).where(
        Submission.participant_id == bindparam("participant")
    ),
    # The ended sessions, as rows without an instrument: one round trip for both.
    select(null(), StudySession.number).where(
        StudySession.participant_id == bindparam("participant"),
        StudySession.status != SessionStatus.RUNNING,
    ),
    # The study's current consent version and the latest the participant accepted.
    select(literal(_CURRENT_CONSENT), func.max(ConsentVersion.version)).where(
        ConsentVersion.study_id == bindparam("study")
    ),
    select(literal(_ACCEPTED_CONSENT), func.max(ConsentRecord.version)).where(
        ConsentRecord.participant_id == bindparam("participant"),
        ConsentRecord.accepted.is_(True),
    ),
)


def progress(db: Session, participant: Participant) -> Progress:
    """The participant's :class:`Progress` (one query)."""
    done: set[tuple[str, int | None]] = set()
    closed: list[int] = []
    where = Progress(done, closed)
    rows = db.execute(_PROGRESS, {"participant": participant.id, "study": participant.study_id})
    for instrument, session in rows:
        if instrument == _CURRENT_CONSENT:
            where.consent_current = session or 1
        elif instrument == _ACCEPTED_CONSENT:
            where.consent_accepted = session
        elif instrument is not None:
            done.add((instrument, session))
        elif session is not None:
            closed.append(session)
    closed.sort()
    return where


def progress_of_many(db: Session, study: Study, participant_ids: list[int]) -> dict[int, Progress]:
    """:func:`progress` of many participants of ``study`` at once (four queries, however many):
    the online monitor places every participant where their next page is."""
    found = {pid: Progress(set(), []) for pid in participant_ids}
    if not found:
        return found
    current = db.scalar(
        select(func.max(ConsentVersion.version)).where(ConsentVersion.study_id == study.id)
    )
    for where in found.values():
        where.consent_current = current or 1
    submitted = select(Submission.participant_id, Submission.instrument, Submission.session)
    for pid, instrument, session in db.execute(
        submitted.where(Submission.participant_id.in_(participant_ids))
    ):
        found[pid].done.add((instrument, session))
    ended = select(StudySession.participant_id, StudySession.number).where(
        StudySession.participant_id.in_(participant_ids),
        StudySession.status != SessionStatus.RUNNING,
    )
    for pid, number in db.execute(ended):
        found[pid].closed.append(number)
    accepted = (
        select(ConsentRecord.participant_id, func.max(ConsentRecord.version))
        .where(ConsentRecord.participant_id.in_(participant_ids), ConsentRecord.accepted.is_(True))
        .group_by(ConsentRecord.participant_id)
    )
    for pid, version in db.execute(accepted):
        found[pid].consent_accepted = version
    for where in found.values():
        where.closed.sort()
    return found


def page_for(participant: Participant, protocol: Protocol, where: Progress) -> Page:
    """The one page this participant should be on, given where they stand."""
    if participant.status == ParticipantStatus.WITHDRAWN:
        return Page("withdrawn")
    return page_reached(participant, protocol, where)


def page_reached(participant: Participant, protocol: Protocol, where: Progress) -> Page:
    """The page their answers and sessions have brought them to, whatever their status (where
    a withdrawn participant had got to: the online monitor's drop-outs)."""
    done = where.done
    if (CONSENT, None) not in done:
        return (
            Page("language") if languages.needs_choice(participant, protocol) else Page("consent")
        )
    if where.consent_outdated and protocol.questionnaires.consent.reconsent_before_next_session:
        return Page("consent")  # the new version of the text, before anything else
    for instrument in protocol.instruments_at("pre"):
        if (instrument.key, None) not in done:
            return Page("questionnaire", instrument)
    for number in where.closed:
        if number < 1:
            continue
        for instrument in protocol.instruments_at("session"):
            if (instrument.key, number) not in done:
                return Page("questionnaire", instrument, number)
    if protocol.schedule.sessions in where.closed:
        for instrument in protocol.instruments_at("post"):
            if (instrument.key, None) not in done:
                return Page("questionnaire", instrument)
        return Page("done")
    return Page("wait")


def every_page(protocol: Protocol) -> list[Page]:
    """The pages a participant meets, in order: consent, the pre-study questionnaires, one
    session's (the same after every session, ``session`` 1 standing for each), the post-study
    ones. What a preview of the study walks through (app/web/preview.py)."""
    pages = [Page("consent")]
    pages += [Page("questionnaire", i) for i in protocol.instruments_at("pre")]
    pages += [Page("questionnaire", i, 1) for i in protocol.instruments_at("session")]
    pages += [Page("questionnaire", i) for i in protocol.instruments_at("post")]
    return pages


def next_page(db: Session, participant: Participant, protocol: Protocol) -> Page:
    """The one page this participant should be on (one query)."""
    if participant.status == ParticipantStatus.WITHDRAWN:
        return Page("withdrawn")
    return page_for(participant, protocol, progress(db, participant))


def position(protocol: Protocol, page: Page) -> tuple[int, int]:
    """Which page of how many this is, counted within one sitting: consent and the pre-study
    questionnaires, one session's questionnaires, or the post-study ones. A participant told
    "page 2 of 5" knows how long the tablet will keep them; ``(0, 0)`` for pages outside a
    sitting (waiting, done)."""
    if page.kind == "consent":
        return 1, 1 + len(protocol.instruments_at("pre"))
    if page.kind != "questionnaire" or page.instrument is None:
        return 0, 0
    sitting = [i.key for i in protocol.instruments_at(page.instrument.when)]
    offset = 1 if page.instrument.when == "pre" else 0  # consent opens the first sitting
    return offset + sitting.index(page.instrument.key) + 1, offset + len(sitting)


def session_blocker(db: Session, participant: Participant, protocol: Protocol, number: int) -> str:
    """Why session ``number`` cannot start yet ('' when it can); see :func:`blocker_given`,
    and a new consent text the protocol wants accepted first."""
    where = progress(db, participant)
    blocker = blocker_given(where.done, participant.code, protocol, number)
    if blocker or not protocol.questionnaires.consent.reconsent_before_next_session:
        return blocker
    return consent.reconsent_blocker(
        participant.code, where.consent_current, where.consent_accepted
    )


def blocker_given(
    done: set[tuple[str, int | None]], code: str, protocol: Protocol, number: int
) -> str:
    """Why session ``number`` cannot start yet ('' when it can), given the (instrument, session)
    pairs participant ``code`` has submitted.

    Consent always comes first. With ``questionnaire_gates_next_session`` the pre-study
    questionnaires must precede the first session and each session's questionnaire the next one.
    """
    if (CONSENT, None) not in done:
        return f"waiting for {code} to give consent on the tablet"
    if not protocol.schedule.questionnaire_gates_next_session:
        return ""
    first = 0 if protocol.schedule.familiarisation_run else 1
    if number == first:
        missing = [i.title for i in protocol.instruments_at("pre") if (i.key, None) not in done]
        if missing:
            return f"waiting for {code} to fill in on the tablet: {', '.join(missing)}"
    previous = number - 1
    if previous >= 1:
        missing = [
            i.title for i in protocol.instruments_at("session") if (i.key, previous) not in done
        ]
        if missing:
            return (
                f"waiting for {code}'s questionnaire after session {previous}: {', '.join(missing)}"
            )
    return ""


# ---------------------------------------------------------------------------------- validation


def _choose_between(low: int, high: int) -> Message:
    return Message("Choose one of %(low)d–%(high)d.", low=low, high=high)


def _validate_item(
    item: ItemSpec, raw: str, protocol: Protocol, answers: Mapping[str, str]
) -> tuple[dict[str, str], str | None]:
    """(values to store, error) for one given answer: the error is a sentence, shown to the
    participant beside the question as it is."""
    if item.kind is ItemKind.LIKERT:
        assert item.scale is not None
        scale = protocol.scale(item.scale)
        try:
            point = int(raw)
        except ValueError:
            return {}, _choose_between(scale.minimum, scale.maximum)
        if not scale.minimum <= point <= scale.maximum:
            return {}, _choose_between(scale.minimum, scale.maximum)
        return {item.key: str(point)}, None
    if item.kind is ItemKind.NUMBER:
        try:
            number = int(raw)
        except ValueError:
            return {}, Message("Enter a whole number.")
        assert item.minimum is not None and item.maximum is not None
        if not item.minimum <= number <= item.maximum:
            return {}, Message(
                "Enter a number from %(low)d to %(high)d.", low=item.minimum, high=item.maximum
            )
        return {item.key: str(number)}, None
    if item.kind is ItemKind.CHOICE:
        option = next((o for o in item.options if o.value == raw), None)
        if option is None:
            return {}, Message("Choose one of the options.")
        values = {item.key: option.value}
        if option.describe:
            description = answers.get(item.key + DESCRIPTION_SUFFIX, "").strip()
            if len(description) > DESCRIPTION_MAX:
                return {}, Message(
                    "Describe it in at most %(most)d characters.", most=DESCRIPTION_MAX
                )
            if description:
                values[item.key + DESCRIPTION_SUFFIX] = description
        return values, None
    text = raw.strip()
    if len(text) > item.max_length:
        return {}, Message("Write at most %(most)d characters.", most=item.max_length)
    return ({item.key: text} if text else {}), None


def validate_answers(
    instrument: InstrumentSpec, protocol: Protocol, answers: Mapping[str, str]
) -> dict[str, str]:
    """The canonical values to store; raises :class:`QuestionnaireInvalid` with per-item errors
    (missing required items, bad values) and InvalidInput for items the instrument lacks."""
    known = {item.key for item in instrument.items}
    known |= {
        item.key + DESCRIPTION_SUFFIX
        for item in instrument.items
        if any(option.describe for option in item.options)
    }
    unknown = sorted(set(answers) - known)
    if unknown:
        raise InvalidInput(
            f"{instrument.key} has no item {', '.join(repr(u) for u in unknown)}; "
            f"its items are {', '.join(i.key for i in instrument.items)}"
        )
    values: dict[str, str] = {}
    errors: dict[str, str] = {}
    for item in instrument.items:
        raw = answers.get(item.key, "")
        if not str(raw).strip():
            if item.required:
                errors[item.key] = Message("Please answer this question.")
            continue
        stored, error = _validate_item(item, str(raw).strip(), protocol, answers)
        if error:
            errors[item.key] = error
        else:
            values.update(stored)
    if errors:
        raise QuestionnaireInvalid(errors)
    return values


# ---------------------------------------------------------------------------------- submission


def _instrument(protocol: Protocol, key: str) -> InstrumentSpec:
    for instrument in protocol.questionnaires.instruments:
        if instrument.key == key:
            return instrument
    keys = ", ".join(i.key for i in protocol.questionnaires.instruments)
    raise NotFound(f"no questionnaire {key!r} in this study; its questionnaires are {keys}")


def _check_timing(
    participant: Participant,
    protocol: Protocol,
    instrument: InstrumentSpec,
    session: int | None,
    where: Progress,
) -> None:
    if instrument.when == "session":
        if session is None or not 1 <= session <= protocol.schedule.sessions:
            raise InvalidInput(
                f"{instrument.key} is asked after each session: give a session from 1 to "
                f"{protocol.schedule.sessions}"
            )
        if session not in where.closed:
            raise Conflict(
                f"session {session} of {participant.code} has not finished yet; its "
                "questionnaire opens when it ends"
            )
        return
    if session is not None:
        raise InvalidInput(f"{instrument.key} is not asked per session: leave the session out")
    if instrument.when == "post" and protocol.schedule.sessions not in where.closed:
        raise Conflict(f"{instrument.key} opens after {participant.code}'s last session")
    if (CONSENT, None) not in where.done:
        raise Conflict("consent comes first")


@dataclass(frozen=True)
class SubmitResult:
    """What a submission changed (its revision, how many values differ) and the page that follows
    it, computed in its transaction."""

    revision: int
    changed: int
    page: Page


def _store(
    db: Session,
    *,
    participant: Participant,
    instrument: str,
    session: int | None,
    values: Mapping[str, str],
    actor: Actor,
    clear_missing: frozenset[str] = frozenset(),
    revising: bool,
    timing: PageTiming | None = None,
) -> tuple[int, int]:
    """Store a page's values; (its revision, how many stored values changed).

    ``revising``: the page was submitted before (from :func:`progress`, read after the
    participant's row lock). A page's responses are only ever stored with its submission, so a
    first submission has no stored values and no submission row to look up.
    """
    same_page = (
        Response.participant_id == participant.id,
        Response.instrument == instrument,
        Response.session.is_(None) if session is None else Response.session == session,
    )
    existing = (
        {row.item: row for row in db.scalars(select(Response).where(*same_page))}
        if revising
        else {}
    )
    submission = (
        db.scalar(
            select(Submission)
            .where(
                Submission.participant_id == participant.id,
                Submission.instrument == instrument,
                Submission.session.is_(None) if session is None else Submission.session == session,
            )
            .with_for_update()
        )
        if revising
        else None
    )
    now = utcnow()
    changed = 0
    new_rows: list[dict[str, object]] = []
    for item, value in values.items():
        row = existing.get(item)
        if row is None:
            new_rows.append(
                {
                    "participant_id": participant.id,
                    "instrument": instrument,
                    "session": session,
                    "item": item,
                    "value": value,
                    "answered_at": now,
                }
            )
            changed += 1 if submission is not None else 0
        elif row.value != value:
            audit.record(
                db,
                actor=actor,
                action="questionnaire.edited",
                study_id=participant.study_id,
                subject=participant.code,
                details={
                    "instrument": instrument,
                    "session": session,
                    "item": item,
                    "old": row.value,
                    "new": value,
                },
            )
            row.value = value
            row.answered_at = now
            changed += 1
    for item in clear_missing & set(existing) - set(values):
        row = existing[item]
        audit.record(
            db,
            actor=actor,
            action="questionnaire.edited",
            study_id=participant.study_id,
            subject=participant.code,
            details={
                "instrument": instrument,
                "session": session,
                "item": item,
                "old": row.value,
                "new": None,
            },
        )
        db.delete(row)
        changed += 1
    if new_rows:  # one statement for all new values (their ids are not needed)
        db.execute(insert(Response), new_rows)
    if submission is None:
        submission = Submission(
            participant_id=participant.id,
            instrument=instrument,
            session=session,
            submitted_at=now,
            seconds_on_page=None if timing is None else timing.seconds_on_page,
            seconds_away=None if timing is None else timing.seconds_away,
        )
        db.add(submission)
        return 1, changed
    submission.revision += 1
    submission.revised_at = now
    return submission.revision, changed


_AS_NOW = (
    select(Participant, Station)
    .outerjoin(Station, Station.participant_id == Participant.id)
    .where(Participant.id == bindparam("participant"))
    .with_for_update(of=Participant)
    .execution_options(populate_existing=True)
)


def _as_now(db: Session, participant: Participant) -> tuple[Participant, Station | None]:
    """The participant as stored now, in this transaction, and the station where they sit.

    A submission decides on the participant's lock and status, so it reads them inside its own
    transaction, not from whenever the tablet was identified; the row lock (PostgreSQL; SQLite's
    write transactions are exclusive anyway) makes a concurrent lock, unlock or withdrawal wait
    for the submission or the submission for it.
    """
    found = db.execute(_AS_NOW, {"participant": participant.id}).one()
    return found[0], found[1]


def _publish(
    db: Session,
    participant: Participant,
    station: Station | None,
    instrument: str,
    session: int | None,
) -> None:
    topics = [study_topic(participant.study_id), participant_topic(participant.id)]
    if station is not None:
        topics.append(station_topic(station))
    events.publish(
        db,
        topics=topics,
        type="questionnaire_submitted",
        participant=participant.code,
        instrument=instrument,
        session=session,
        site=sites.event_site(participant),
    )


def _refuse_if_locked(participant: Participant) -> None:
    """Refuse any submission (new or a revision) for a locked or withdrawn participant."""
    if participant.locked_at is not None:
        raise Conflict(
            Message(
                "%(code)s's answers are locked; the experimenter can unlock them",
                code=participant.code,
            )
        )
    if participant.status == ParticipantStatus.WITHDRAWN:
        raise Conflict(Message("%(code)s has withdrawn", code=participant.code))


class ConsentChanged(Conflict):
    """The consent text changed while the participant was reading it: show them the new one."""


def check_consent_given(accepted: bool) -> None:
    """Refuse a consent page sent without its box ticked (what the page says beside it)."""
    if not accepted:
        raise QuestionnaireInvalid({"accept": Message("Please tick the box to take part.")})


def accept_consent(
    db: Session,
    *,
    participant: Participant,
    protocol: Protocol,
    accepted: bool,
    actor: Actor,
    version: int | None = None,
) -> SubmitResult:
    """Record consent to the study's current consent text; commits.

    ``protocol`` is the one the participant read (in their language): the record keeps the
    version, its label, the language and the SHA-256 of the exact words accepted, as the
    consent page's answers (the latest acceptance) and as a consent record (every acceptance).
    ``version``: the version number the participant was shown, when the client says; a newer
    one added meanwhile is refused (:class:`ConsentChanged`), so nobody accepts words they did
    not see. Accepting again after a new version was added is a re-consent."""
    participant, station = _as_now(db, participant)
    _refuse_if_locked(participant)
    check_consent_given(accepted)
    text = consent.shown(db, study_id=participant.study_id, protocol=protocol)
    if version is not None and version != text.number:
        raise ConsentChanged(f"the consent text changed (now version {text.number}): read it again")
    record = {
        "accepted": "yes",
        "protocol_version": text.label,
        "consent_version": str(text.number),
        # Named apart from the participant's own `language` column in the wide export.
        "consent_language": text.language,
        "consent_sha256": text.sha256,
    }
    where = progress(db, participant)
    again = where.consent_accepted is not None and where.consent_accepted < text.number
    revision, changed = _store(
        db,
        participant=participant,
        instrument=CONSENT,
        session=None,
        values=record,
        actor=actor,
        revising=(CONSENT, None) in where.done,
    )
    if where.consent_accepted != text.number:  # not a repeat of the same acceptance
        _record_answer(db, participant, text, accepted=True)
    audit.record(
        db,
        actor=actor,
        action="participant.reconsented" if again else "participant.consented",
        study_id=participant.study_id,
        subject=participant.code,
        details={"version": text.label}
        | {k: record[k] for k in ("consent_language", "consent_sha256")}
        | {"consent_version": text.number}
        | ({"previous_version": where.consent_accepted} if again else {}),
    )
    if again:  # a change of the participant's standing: every view of them learns it
        participant_changes.participant_changed(db, participant, Change.RECONSENTED)
    else:
        _publish(db, participant, station, CONSENT, None)
    where.done.add((CONSENT, None))
    where.consent_accepted = where.consent_current = text.number
    page = page_for(participant, protocol, where)
    db.commit()
    return SubmitResult(revision, changed, page)


def decline_consent(
    db: Session,
    *,
    participant: Participant,
    protocol: Protocol,
    actor: Actor,
    version: int | None = None,
) -> Page:
    """Record that a participant asked to consent again declined the new text; commits.

    Nothing else changes: staff see the refusal and may withdraw them (trustlab does not), and
    the participant may still accept later. Only a participant who accepted an earlier version
    can decline a later one; the first consent is given or not given, not declined."""
    participant, _ = _as_now(db, participant)
    _refuse_if_locked(participant)
    where = progress(db, participant)
    if not where.consent_outdated:
        raise Conflict(
            f"{participant.code} has no new consent text to decline"
            if where.consent_accepted is not None
            else "consent comes first: there is no earlier consent to keep"
        )
    text = consent.shown(db, study_id=participant.study_id, protocol=protocol)
    if version is not None and version != text.number:
        raise ConsentChanged(f"the consent text changed (now version {text.number}): read it again")
    _record_answer(db, participant, text, accepted=False)
    audit.record(
        db,
        actor=actor,
        action="participant.consent_declined",
        study_id=participant.study_id,
        subject=participant.code,
        details={
            "consent_version": text.number,
            "version": text.label,
            "consent_language": text.language,
            "consent_sha256": text.sha256,
            "accepted_version": where.consent_accepted,
        },
    )
    participant_changes.participant_changed(db, participant, Change.CONSENT_DECLINED)
    page = page_for(participant, protocol, where)
    db.commit()
    return page


def _record_answer(
    db: Session, participant: Participant, text: consent.Shown, *, accepted: bool
) -> None:
    db.add(
        ConsentRecord(
            participant_id=participant.id,
            version=text.number,
            label=text.label,
            language=text.language,
            sha256=text.sha256,
            accepted=accepted,
        )
    )


def submit(
    db: Session,
    *,
    participant: Participant,
    protocol: Protocol,
    instrument_key: str,
    session: int | None,
    answers: Mapping[str, str],
    actor: Actor,
    timing: PageTiming | None = None,
) -> SubmitResult:
    """Validate and store one questionnaire page all-or-nothing; commits. ``timing``: what the
    page measured, kept with its first submission."""
    participant, station = _as_now(db, participant)
    _refuse_if_locked(participant)
    instrument = _instrument(protocol, instrument_key)
    where = progress(db, participant)
    _check_timing(participant, protocol, instrument, session, where)
    values = validate_answers(instrument, protocol, answers)
    optional = frozenset(
        key for item in instrument.items for key in (item.key, item.key + DESCRIPTION_SUFFIX)
    )
    revision, changed = _store(
        db,
        participant=participant,
        instrument=instrument.key,
        session=session,
        values=values,
        actor=actor,
        clear_missing=optional,
        revising=(instrument.key, session) in where.done,
        timing=timing,
    )
    _publish(db, participant, station, instrument.key, session)
    where.done.add((instrument.key, session))
    page = page_for(participant, protocol, where)
    db.commit()
    return SubmitResult(revision, changed, page)


def set_locked(db: Session, *, participant: Participant, locked: bool, actor: Actor) -> None:
    """Lock a participant's answers (no new submissions, no revisions) or unlock them; commits."""
    if (participant.locked_at is not None) == locked:
        return
    participant.locked_at = utcnow() if locked else None
    audit.record(
        db,
        actor=actor,
        action="participant.locked" if locked else "participant.unlocked",
        study_id=participant.study_id,
        subject=participant.code,
    )
    change = Change.LOCKED if locked else Change.UNLOCKED
    participant_changes.participant_changed(db, participant, change)
    db.commit()


def stored_answers(
    db: Session, participant: Participant, instrument: str, session: int | None
) -> dict[str, str]:
    """A page's stored values (to show them again when a participant edits)."""
    rows = db.scalars(
        select(Response).where(
            Response.participant_id == participant.id,
            Response.instrument == instrument,
            Response.session.is_(None) if session is None else Response.session == session,
        )
    )
    return {row.item: row.value for row in rows}
