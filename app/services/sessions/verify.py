"""Integrity checks for a study: replay every learner and audit the timeline and allocations.

``trustlab verify`` trusts nothing it can recompute:

- **learners**: each is rebuilt from its stored initial state and fed its answers in version order;
  the learner version of every answer must match the replay exactly, and the probabilities
  recorded with every prompt and answer and the final stored state to within
  :data:`FLOAT_TOLERANCE` (see there why not bit for bit);
- **timeline**: sessions numbered without gaps, at most one running and only the last; runs
  likewise within a session and never more than the protocol allows; completed runs have every
  category answered; familiarisation prompts never adapt; each prompt's question is the protocol's
  text for its action; rewards and replies follow the protocol;
- **orphans**: answers, runs and learners that point at another participant, categories the
  protocol does not know, participants without learners or allocation;
- **allocation**: every sequence allocation is the seed's entry at its index, indices have no gaps,
  replacements replace a withdrawn participant of the same stratum and take their condition, and
  the groups stay within half the largest block of each other per stratum (an erased
  participant's slot counts: it stays, as a withdrawal); the pilot's sequence (its own seed,
  app.randomisation.pilot_seed) is checked the same way, apart from the live one;
- **erasures**: nothing but the allocation slot remains of an erased participant;
- **consent**: every version of the consent text matches its SHA-256, and every participant's
  consent record names a version and that version's hash in the record's language.
"""

from __future__ import annotations

from collections import Counter, defaultdict
from dataclasses import asdict, dataclass, field
from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session

from app.protocol import Protocol, parse_protocol
from app.randomisation import entry_at, sequence_seed
from app.services.participants import languages
from app.services.privacy import consent
from app.services.sessions import learners, replies
from app.services.sessions.runtime import (
    FAMILIARISATION,
    first_session_number,
    runs_in,
    session_label,
)
from app.services.studies import get_study, protocol_of
from app.tables import (
    Allocation,
    Answer,
    ConsentRecord,
    LearnerState,
    Participant,
    ParticipantStatus,
    Prompt,
    ProtocolVersion,
    Run,
    RunStatus,
    SessionStatus,
    Study,
    StudySession,
)
from app.wording import counted
from models.replies import confidence_level


def _run_label(session_number: int, run_number: int) -> str:
    """How people call a run: the familiarisation run has one, so it is not numbered."""
    if session_number != FAMILIARISATION:
        return f"{session_label(session_number)} run {run_number}"
    if run_number == 1:
        return session_label(session_number)
    return f"run {run_number} of {session_label(session_number)}"


@dataclass(frozen=True)
class Finding:
    """One inconsistency: which check, about whom, what exactly."""

    check: str
    participant: str | None
    detail: str


@dataclass
class VerifyReport:
    """What was checked and what was found."""

    study: str
    participants: int = 0
    learners: int = 0
    steps: int = 0
    answers: int = 0
    findings: list[Finding] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        """Whether nothing was found."""
        return not self.findings

    def to_json(self) -> dict[str, Any]:
        """The report as one JSON object."""
        value = asdict(self)
        value["ok"] = self.ok
        return value


FLOAT_TOLERANCE = 1e-9
"""How far a replayed number may be from the stored one (absolute, plus as much relative).

Not zero because the C2 learner's arithmetic is not bit-identical across environments: numpy's
BLAS chooses its kernels by CPU (AVX2 or AVX-512, or as ``OPENBLAS_CORETYPE`` says), and they
sum in different orders, so a server and a ``trustlab verify`` run elsewhere (another machine,
or only another environment) differ in the last bit or two (measured: 1e-16). Anything a real
fault causes — an answer lost, applied twice or out of order, a wrong reward or checkpoint —
moves the probabilities by many orders of magnitude more."""


def _close(replayed: Any, stored: Any) -> bool:
    """Equal structure, strings, integers and booleans; floats within :data:`FLOAT_TOLERANCE`."""
    if isinstance(replayed, dict) and isinstance(stored, dict):
        return replayed.keys() == stored.keys() and all(
            _close(replayed[key], stored[key]) for key in replayed
        )
    if isinstance(replayed, list | tuple) and isinstance(stored, list | tuple):
        return len(replayed) == len(stored) and all(map(_close, replayed, stored))
    if replayed == stored:
        return type(replayed) is type(stored) or not (
            isinstance(replayed, bool) or isinstance(stored, bool)
        )
    if isinstance(replayed, float) and isinstance(stored, float):
        return abs(replayed - stored) <= FLOAT_TOLERANCE * (1.0 + abs(stored))
    return False


class _Study:
    """Everything of one study loaded once, indexed for the checks."""

    def __init__(self, db: Session, study: Study) -> None:
        self.study = study
        self.protocol: Protocol = protocol_of(study)
        pid_query = select(Participant.id).where(Participant.study_id == study.id)
        self.participants = {
            p.id: p for p in db.scalars(select(Participant).where(Participant.study_id == study.id))
        }
        self.allocations = list(
            db.scalars(select(Allocation).where(Allocation.study_id == study.id))
        )
        self.learners = list(
            db.scalars(select(LearnerState).where(LearnerState.participant_id.in_(pid_query)))
        )
        self.sessions = list(
            db.scalars(
                select(StudySession)
                .where(StudySession.participant_id.in_(pid_query))
                .order_by(StudySession.participant_id, StudySession.number)
            )
        )
        session_ids = [s.id for s in self.sessions]
        self.runs = (
            list(db.scalars(select(Run).where(Run.session_id.in_(session_ids)).order_by(Run.id)))
            if session_ids
            else []
        )
        self.prompts = list(
            db.scalars(
                select(Prompt).where(Prompt.participant_id.in_(pid_query)).order_by(Prompt.id)
            )
        )
        self.answers = {
            a.prompt_id: a
            for a in db.scalars(select(Answer).where(Answer.participant_id.in_(pid_query)))
        }
        self.sessions_by_id = {s.id: s for s in self.sessions}
        self.runs_by_id = {r.id: r for r in self.runs}
        # Every version a session ran under (a live study's amendments: app.services.design).
        used = {s.protocol_version for s in self.sessions if s.protocol_version is not None}
        self.versions: dict[int, Protocol] = {
            row.number: parse_protocol(row.source, source=f"version {row.number}").protocol
            for row in db.scalars(
                select(ProtocolVersion).where(
                    ProtocolVersion.study_id == study.id, ProtocolVersion.number.in_(used)
                )
            )
        }

    def protocol_of_session(self, session: StudySession) -> Protocol:
        """The protocol version the session ran under (the study's, for an older row)."""
        if session.protocol_version is None:
            return self.protocol
        return self.versions.get(session.protocol_version, self.protocol)

    def code(self, participant_id: int) -> str | None:
        participant = self.participants.get(participant_id)
        return participant.code if participant else None

    def protocol_asked_in(self, prompt: Prompt, protocol: Protocol) -> Protocol:
        """``protocol`` (its session's version) in the language this prompt was asked in: the
        participant's, or another of the study's when its question is that language's (an
        admin may have changed the language after a session, with a recorded reason). The
        participant's when no language's text matches, so the check reports the mismatch."""
        participant = self.participants.get(prompt.participant_id)
        own = languages.protocol_for(participant.language if participant else None, protocol)
        for language in (own.default_language, *protocol.study.languages):
            candidate = protocol.in_language(language)
            category = next((c for c in candidate.categories if c.name == prompt.category), None)
            questions = category.questions if category is not None else []
            if 0 <= prompt.action < len(questions) and questions[prompt.action] == prompt.question:
                return candidate
        return own


def _check_learners(data: _Study, report: VerifyReport) -> None:
    protocol = data.protocol
    categories = {c.name: c for c in protocol.categories}
    allocation_of = {a.participant_id: a for a in data.allocations}
    prompts_by_learner: dict[tuple[int, str], list[Prompt]] = defaultdict(list)
    for prompt in data.prompts:
        if prompt.adapts and prompt.id in data.answers:
            prompts_by_learner[(prompt.participant_id, prompt.category)].append(prompt)
    seen: set[tuple[int, str]] = set()
    for row in data.learners:
        code = data.code(row.participant_id)
        seen.add((row.participant_id, row.category))
        report.learners += 1
        if row.category not in categories:
            report.findings.append(
                Finding("orphan", code, f"learner for unknown category {row.category!r}")
            )
            continue
        allocation = allocation_of.get(row.participant_id)
        if allocation is not None:
            expected_kind = protocol.condition(allocation.condition).learner
            if row.kind != expected_kind:
                report.findings.append(
                    Finding(
                        "learner",
                        code,
                        f"{row.category}: kind {row.kind} but condition "
                        f"{allocation.condition} uses {expected_kind}",
                    )
                )
        _replay(data, row, prompts_by_learner[(row.participant_id, row.category)], report)
    for participant in data.participants.values():
        if participant.erased_at is not None:
            continue  # _check_erased: nothing of theirs may remain
        for category in categories:
            if (participant.id, category) not in seen:
                report.findings.append(
                    Finding("orphan", participant.code, f"no learner for {category}")
                )


def _replay(data: _Study, row: LearnerState, prompts: list[Prompt], report: VerifyReport) -> None:
    code = data.code(row.participant_id)
    where = f"{row.category} learner"
    try:
        learner = learners.restore(row, initial=True)
    except (ValueError, KeyError) as exc:
        report.findings.append(Finding("learner", code, f"{where}: cannot rebuild: {exc}"))
        return
    answers = sorted(
        ((data.answers[p.id], p) for p in prompts), key=lambda pair: pair[0].learner_version
    )
    for version, (answer, prompt) in enumerate(answers, start=1):
        if prompt.learner_version != version - 1:
            report.findings.append(
                Finding(
                    "replay",
                    code,
                    f"{where}: step {prompt.id} was prompted at version "
                    f"{prompt.learner_version}, replay expects {version - 1}",
                )
            )
            return
        if not _close(learners.probabilities_list(learner), prompt.probabilities):
            report.findings.append(
                Finding("replay", code, f"{where}: step {prompt.id} probabilities differ")
            )
            return
        learner.update(prompt.action, answer.reward)
        if answer.learner_version != version:
            report.findings.append(
                Finding(
                    "replay",
                    code,
                    f"{where}: step {prompt.id} answer has version "
                    f"{answer.learner_version}, replay gives {version}",
                )
            )
            return
        if not _close(learners.probabilities_list(learner), answer.probabilities_after):
            report.findings.append(
                Finding("replay", code, f"{where}: step {prompt.id} updated probabilities differ")
            )
            return
    if row.version != len(answers):
        report.findings.append(
            Finding(
                "replay",
                code,
                f"{where}: stored version {row.version} but {counted(len(answers), 'answer')}",
            )
        )
    elif not _states_close(learner.state_dict(), row.state):
        report.findings.append(
            Finding("replay", code, f"{where}: stored state differs from the replayed one")
        )


def _states_close(replayed: dict[str, Any], stored: dict[str, Any]) -> bool:
    """Whether two learner states hold the same numbers (within :data:`FLOAT_TOLERANCE`),
    whichever state format version each was written in."""
    try:
        return _close(learners.plain_state(replayed), learners.plain_state(stored))
    except ValueError:  # stored weights that are not numbers at all
        return False


def _check_steps(data: _Study, report: VerifyReport) -> None:
    specs = {(row.participant_id, row.category): learners.spec_of(row) for row in data.learners}
    for prompt in data.prompts:
        report.steps += 1
        code = data.code(prompt.participant_id)
        run = data.runs_by_id.get(prompt.run_id)
        if run is None or run.participant_id != prompt.participant_id:
            report.findings.append(
                Finding("orphan", code, f"step {prompt.id}: run of another participant")
            )
            continue
        session = data.sessions_by_id[run.session_id]
        protocol = data.protocol_of_session(session)
        categories = {c.name: c for c in protocol.categories}
        if prompt.adapts != (session.number != FAMILIARISATION):
            report.findings.append(
                Finding(
                    "timeline",
                    code,
                    f"step {prompt.id}: adapts={prompt.adapts} in {session_label(session.number)}",
                )
            )
        category = categories.get(prompt.category)
        if category is None or not 0 <= prompt.action < len(category.questions):
            report.findings.append(Finding("step", code, f"step {prompt.id}: unknown question"))
            continue
        asked_in = data.protocol_asked_in(prompt, protocol)
        if prompt.question != asked_in.category(prompt.category).questions[prompt.action]:
            report.findings.append(
                Finding("step", code, f"step {prompt.id}: question text is not the protocol's")
            )
        answer = data.answers.get(prompt.id)
        if answer is None:
            continue
        report.answers += 1
        if answer.participant_id != prompt.participant_id:
            report.findings.append(
                Finding("orphan", code, f"answer to step {prompt.id} of another participant")
            )
        expected_reward = protocol.reward.yes if answer.answer else protocol.reward.no
        if answer.reward != expected_reward:
            report.findings.append(
                Finding(
                    "step",
                    code,
                    f"step {prompt.id}: reward {answer.reward}, protocol says {expected_reward}",
                )
            )
        level = confidence_level(answer.probability, protocol.replies.thresholds)
        line = asked_in.replies.levels[level].line(answer.answer)
        if level != answer.confidence_level or answer.reply != line:
            report.findings.append(
                Finding("step", code, f"step {prompt.id}: reply does not follow the thresholds")
            )
        spec = specs.get((prompt.participant_id, prompt.category))
        if spec is not None and not _reply_follows_basis(protocol, spec, prompt, answer):
            report.findings.append(
                Finding(
                    "step",
                    code,
                    f"step {prompt.id}: reply probability does not follow replies.basis "
                    f"{protocol.replies.basis!r}",
                )
            )


def _reply_follows_basis(
    protocol: Protocol, spec: learners.LearnerSpec, prompt: Prompt, answer: Answer
) -> bool:
    """Whether the stored reply probability is the one the protocol's basis gives for the
    stored probabilities and answer (the same floats, so the same bits)."""
    expected = replies.choose_reply(
        protocol,
        spec,
        before=prompt.probabilities,
        action=prompt.action,
        after=answer.probabilities_after,
        said_yes=answer.answer,
    )
    return _close(expected.probability, answer.probability)


def _check_timeline(data: _Study, report: VerifyReport) -> None:
    protocol = data.protocol
    sessions_of: dict[int, list[StudySession]] = defaultdict(list)
    for session in data.sessions:
        sessions_of[session.participant_id].append(session)
    runs_of: dict[int, list[Run]] = defaultdict(list)
    for run in data.runs:
        runs_of[run.session_id].append(run)
    answered_in: dict[int, set[str]] = defaultdict(set)
    for prompt in data.prompts:
        if prompt.id in data.answers:
            answered_in[prompt.run_id].add(prompt.category)
    all_categories = {c.name for c in protocol.categories}
    first = first_session_number(protocol)
    for participant_id, sessions in sessions_of.items():
        code = data.code(participant_id)
        numbers = [s.number for s in sessions]
        if numbers != list(range(first, first + len(numbers))):
            report.findings.append(Finding("timeline", code, f"sessions out of order: {numbers}"))
        if numbers and numbers[-1] > protocol.schedule.sessions:
            report.findings.append(Finding("timeline", code, "more sessions than the protocol has"))
        for index, session in enumerate(sessions):
            if session.status == SessionStatus.RUNNING and index != len(sessions) - 1:
                report.findings.append(
                    Finding(
                        "timeline",
                        code,
                        f"{session_label(session.number)} still running after a later one",
                    )
                )
            if (session.status == SessionStatus.RUNNING) == (session.ended_at is not None):
                report.findings.append(
                    Finding(
                        "timeline",
                        code,
                        f"{session_label(session.number)}: status and end time disagree",
                    )
                )
            runs = runs_of.get(session.id, [])
            run_numbers = [r.number for r in runs]
            if run_numbers != list(range(1, len(runs) + 1)):
                report.findings.append(
                    Finding(
                        "timeline",
                        code,
                        f"{session_label(session.number)}: runs out of order {run_numbers}",
                    )
                )
            if len(runs) > runs_in(protocol, session.number):
                report.findings.append(
                    Finding("timeline", code, f"{session_label(session.number)}: too many runs")
                )
            for position, run in enumerate(runs):
                if run.participant_id != participant_id:
                    report.findings.append(
                        Finding("orphan", code, f"run {run.id} of another participant")
                    )
                if run.status == RunStatus.RUNNING and (
                    position != len(runs) - 1 or session.status != SessionStatus.RUNNING
                ):
                    report.findings.append(
                        Finding(
                            "timeline",
                            code,
                            f"{_run_label(session.number, run.number)} is running out of turn",
                        )
                    )
                if run.status == RunStatus.COMPLETED and answered_in[run.id] != all_categories:
                    missing = sorted(all_categories - answered_in[run.id])
                    report.findings.append(
                        Finding(
                            "timeline",
                            code,
                            f"{_run_label(session.number, run.number)} "
                            f"completed without {', '.join(missing)}",
                        )
                    )


def _check_allocation(data: _Study, report: VerifyReport) -> None:
    protocol = data.protocol
    conditions = [c.id for c in protocol.conditions]
    sizes = protocol.allocation.block_sizes
    allocated = {a.participant_id for a in data.allocations}
    for participant in data.participants.values():
        if participant.id not in allocated:
            report.findings.append(Finding("allocation", participant.code, "no allocation"))
    # The live sequence and the pilot's (its own seed) are checked apart, slot by slot.
    by_stratum: dict[tuple[bool, str], list[Allocation]] = defaultdict(list)
    for allocation in data.allocations:
        code = data.code(allocation.participant_id)
        owner = data.participants.get(allocation.participant_id)
        if owner is not None and owner.pilot != allocation.pilot:
            report.findings.append(
                Finding("allocation", code, "pilot participant and allocation slot disagree")
            )
        if allocation.sequence_index is None:
            replaced = data.participants.get(allocation.replaces_participant_id or -1)
            original = next(
                (a for a in data.allocations if a.participant_id == getattr(replaced, "id", None)),
                None,
            )
            if (
                replaced is None
                or replaced.status != ParticipantStatus.WITHDRAWN
                or replaced.stratum != allocation.stratum
                or replaced.pilot != allocation.pilot
                or original is None
                or original.condition != allocation.condition
            ):
                report.findings.append(
                    Finding(
                        "allocation", code, "replacement does not match a withdrawn participant"
                    )
                )
            continue
        by_stratum[(allocation.pilot, allocation.stratum)].append(allocation)
        seed = sequence_seed(data.study.allocation_seed, pilot=allocation.pilot)
        entry = entry_at(seed, allocation.stratum, conditions, sizes, allocation.sequence_index)
        if entry.condition != allocation.condition:
            report.findings.append(
                Finding(
                    "allocation",
                    code,
                    f"allocation {allocation.sequence_index} is "
                    f"{allocation.condition} but the seed gives {entry.condition}",
                )
            )
    for (pilot, stratum), allocations in by_stratum.items():
        name = ("pilot " if pilot else "") + f"stratum {stratum or '(all)'}"
        indices = sorted(a.sequence_index or 0 for a in allocations)
        if indices != list(range(len(indices))):
            report.findings.append(Finding("allocation", None, f"{name}: indices have gaps"))
        counts = Counter(a.condition for a in allocations)
        spread = max(counts.get(c, 0) for c in conditions) - min(
            counts.get(c, 0) for c in conditions
        )
        if spread > max(sizes) // len(conditions):
            report.findings.append(
                Finding("allocation", None, f"{name}: groups differ by {spread}")
            )


def _check_erased(data: _Study, report: VerifyReport) -> None:
    """An erased participant keeps only their allocation slot: no learner, session, prompt or
    answer may still point at them (app.services.privacy.erasure)."""
    erased = {p.id for p in data.participants.values() if p.erased_at is not None}
    if not erased:
        return
    left = Counter(
        [("learner", row.participant_id) for row in data.learners]
        + [("session", row.participant_id) for row in data.sessions]
        + [("prompt", row.participant_id) for row in data.prompts]
        + [("answer", row.participant_id) for row in data.answers.values()]
    )
    for (kind, participant_id), n in sorted(left.items()):
        if participant_id in erased:
            report.findings.append(
                Finding(
                    "erasure", data.code(participant_id), f"erased, yet {n} {kind} row(s) remain"
                )
            )


def _check_consent(db: Session, data: _Study, report: VerifyReport) -> None:
    """Every version of the consent text hashes to its stored SHA-256, and every consent
    record names a version and the hash of that version's words in its language (a record
    from before hashes were kept has none to compare)."""
    versions = {v.number: v for v in consent.versions(db, data.study)}
    for each in versions.values():
        for language, text in each.texts.items():
            if consent.digest(text) != each.sha256.get(language):
                report.findings.append(
                    Finding(
                        "consent",
                        None,
                        f"version {each.number}'s {language} text does not match its SHA-256",
                    )
                )
    records = db.scalars(
        select(ConsentRecord)
        .where(ConsentRecord.participant_id.in_(list(data.participants)))
        .order_by(ConsentRecord.id)
    )
    for record in records:
        version = versions.get(record.version)
        code = data.code(record.participant_id)
        if version is None:
            report.findings.append(
                Finding("consent", code, f"answered version {record.version}, which is unknown")
            )
        elif record.sha256 and version.sha256.get(record.language) != record.sha256:
            report.findings.append(
                Finding(
                    "consent",
                    code,
                    f"the words of version {record.version} answered in {record.language} are "
                    "not the version's",
                )
            )


def verify_study(db: Session, *, study_name: str) -> VerifyReport:
    """Run every check on one study."""
    study = get_study(db, study_name)
    data = _Study(db, study)
    report = VerifyReport(study=study.name, participants=len(data.participants))
    _check_allocation(data, report)
    _check_consent(db, data, report)
    _check_timeline(data, report)
    _check_steps(data, report)
    _check_learners(data, report)
    _check_erased(data, report)
    return report
