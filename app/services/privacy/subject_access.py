"""Everything stored about one participant, for their subject-access request.

Data-protection law (the GDPR's article 15 and its equivalents) gives participants the right to
a copy of what is held about them. :func:`participant_record` gathers it from every table that
holds it, in the sections the personal data registry names (app.services.privacy.personal_data): the
enrolment, every answer to a version of the consent text (which version, its SHA-256, when),
every questionnaire answer, every question the robot asked with the answer and what was heard,
audio recordings (described, and included when asked), where the room last saw them and what
was said there, and the audit entries about them. ``trustlab participant export`` writes it as
JSON (complete, for a machine) and HTML (readable, for the participant).

In a blinded study that has not been unblinded, the condition is left out and marked sealed: the
lab may tell the participant after the study, as its protocol says.
"""

from __future__ import annotations

import base64
from datetime import datetime
from typing import Any

from sqlalchemy import or_, select
from sqlalchemy.orm import Session

from app.services import blinding, studies
from app.services.audit import Actor
from app.services.participants import enrolment
from app.services.privacy import consent, personal_data
from app.tables import (
    Answer,
    AnswerAudio,
    AuditEvent,
    OnlineParticipation,
    Prompt,
    Response,
    RoomPresence,
    Run,
    Station,
    StudySession,
    Submission,
)

SEALED = "sealed until the study is unblinded"


def _when(value: datetime | None) -> str | None:
    return value.isoformat(timespec="seconds") if value is not None else None


def _unsealed(details: dict[str, Any], sealed: bool) -> dict[str, Any]:
    """An audit entry's details, without the condition while the study is blinded."""
    if not sealed:
        return dict(details)
    return {k: (SEALED if k == "condition" else v) for k, v in details.items()}


def participant_record(
    db: Session, *, study_name: str, code: str, with_audio: bool = False
) -> dict[str, Any]:
    """What is stored about participant ``code`` of ``study_name``, as plain JSON-able data."""
    study = studies.get_study(db, study_name)
    # The command line's (whoever holds the server sees every site: app.services.privacy.sites).
    participant = enrolment.get_participant(db, study, code, actor=Actor.command_line())
    pid = participant.id
    sealed = blinding.is_sealed(study)
    sessions = {
        s.id: s for s in db.scalars(select(StudySession).where(StudySession.participant_id == pid))
    }
    runs = {r.id: r for r in db.scalars(select(Run).where(Run.participant_id == pid))}
    answers = {
        a.prompt_id: a for a in db.scalars(select(Answer).where(Answer.participant_id == pid))
    }
    audio = {
        a.answer_id: a
        for a in db.scalars(select(AnswerAudio).where(AnswerAudio.participant_id == pid))
    }
    steps = []
    for prompt in db.scalars(
        select(Prompt).where(Prompt.participant_id == pid).order_by(Prompt.id)
    ):
        run = runs.get(prompt.run_id)
        session = sessions.get(run.session_id) if run is not None else None
        answer = answers.get(prompt.id)
        recording = audio.get(answer.id) if answer is not None else None
        steps.append(
            {
                "session": session.number if session is not None else None,
                "run": run.number if run is not None else None,
                "category": prompt.category,
                "question": prompt.question,
                "asked_at": _when(prompt.prompted_at),
                "answer": None if answer is None else ("yes" if answer.answer else "no"),
                "answered_at": _when(answer.answered_at) if answer else None,
                "how": answer.modality if answer else None,
                "heard": answer.transcript if answer else None,
                "heard_confidence": answer.transcript_confidence if answer else None,
                "recogniser": answer.transcript_engine if answer else None,
                "reply": answer.reply if answer else None,
                "recording": None
                if recording is None
                else {
                    "seconds": recording.seconds,
                    "recorded_at": _when(recording.recorded_at),
                    **(
                        {"wav_base64": base64.b64encode(recording.wav).decode()}
                        if with_audio
                        else {}
                    ),
                },
            }
        )
    submitted = {
        (s.instrument, s.session): s
        for s in db.scalars(select(Submission).where(Submission.participant_id == pid))
    }
    questionnaires: dict[tuple[str, int | None], dict[str, Any]] = {}
    for response in db.scalars(
        select(Response).where(Response.participant_id == pid).order_by(Response.id)
    ):
        key = (response.instrument, response.session)
        page = questionnaires.setdefault(
            key,
            {
                "instrument": response.instrument,
                "session": response.session,
                "submitted_at": _when(submitted[key].submitted_at) if key in submitted else None,
                "answers": {},
            },
        )
        page["answers"][response.item] = response.value
    audit = db.scalars(
        select(AuditEvent)
        .where(
            AuditEvent.study_id == study.id,
            or_(AuditEvent.subject == code, AuditEvent.actor.startswith(f"{code} (")),
        )
        .order_by(AuditEvent.id)
    )
    station = db.scalar(select(Station.name).where(Station.participant_id == pid))
    online = db.scalar(select(OnlineParticipation).where(OnlineParticipation.participant_id == pid))
    sections: dict[str, Any] = {
        "enrolment": {
            "enrolled_at": _when(participant.enrolled_at),
            "status": participant.status,
            "condition": SEALED if sealed else participant.allocation.condition,
            "stratification": dict(participant.strata or {}),
            "language": participant.language,
            "withdrawn_at": _when(participant.withdrawn_at),
            "withdrawal_reason": participant.withdrawal_reason or None,
            "station": station,
            "online": None if online is None else _online(online),
        },
        "consent": [
            {
                "version": record.version,
                "label": record.label,
                "answer": "accepted" if record.accepted else "declined",
                "language": record.language,
                "sha256": record.sha256,
                "at": _when(record.answered_at),
            }
            for record in consent.records(db, participant)
        ],
        "questionnaires": list(questionnaires.values()),
        "robot_steps": steps,
        "audit_log": [
            {
                "at": _when(entry.occurred_at),
                "action": entry.action,
                "by": entry.actor,
                "details": _unsealed(entry.details, sealed),
            }
            for entry in audit
        ],
        "room": _room(db, pid, sealed),
    }
    # Every section the personal data registry names, in its order (a KeyError here is a
    # table registered with a section nobody builds).
    return {
        "study": study.name,
        "study_title": study.title,
        "participant": participant.code,
        "exported_at": _when(datetime.now().astimezone()),
        **{section: sections[section] for section in personal_data.SUBJECT_ACCESS_SECTIONS},
    }


def _online(online: OnlineParticipation) -> dict[str, Any]:
    """An online participation as their copy shows it (the recruitment ID is stored only as a
    keyed hash, which tells them nothing: its presence is said, not the hash)."""
    return {
        "recruitment_id": "stored as a keyed hash" if online.recruitment_hash else None,
        "platform_parameters": dict(online.parameters or {}),
        "joined_at": _when(online.joined_at),
        "status": online.status,
        "step": online.step,
        "device": online.device,
        "finished_at": _when(online.finished_at),
        "data_quality_flags": dict(online.flags),
    }


def _room(db: Session, participant_id: int, sealed: bool) -> dict[str, Any] | None:
    """Where the room client last saw them and the last line said there (a robot's reply
    sealed while the study is: its level would show the condition)."""
    presence = db.scalar(select(RoomPresence).where(RoomPresence.participant_id == participant_id))
    if presence is None:
        return None
    said = presence.utterance
    if sealed and presence.utterance_kind == "reply":
        said = SEALED
    return {
        "seen_at": _when(presence.updated_at),
        "x": presence.x,
        "z": presence.z,
        "heading": presence.heading,
        "zone": presence.zone,
        "last_said": None
        if said is None
        else {"by": presence.utterance_kind, "words": said, "at": _when(presence.utterance_at)},
    }
