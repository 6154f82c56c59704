"""The station operations, once: used by the robot's REST routes, the experimenter's
Wizard-of-Oz routes and the station WebSocket, so every client goes through the same path."""

from __future__ import annotations

from sqlalchemy.orm import Session

from app.api.runtime_schemas import (
    AnswerOut,
    AnswerRequest,
    DeviceNotice,
    DeviceOut,
    ExpectedOut,
    LastReplyOut,
    NoticeRequest,
    PresenceRequest,
    PromptOut,
    PromptRequest,
    RoomCategory,
    RoomOut,
    RunOut,
    SessionOut,
    SpeechOut,
    StaffAnswerOut,
    StaffPromptOut,
    StaffStationStateOut,
    StationStateOut,
)
from app.errors import Conflict, NotFound
from app.protocol import Protocol
from app.services.audit import Actor
from app.services.participants import languages
from app.services.privacy import sites
from app.services.sessions import answer_audio, room_presence, runtime, stations
from app.services.sessions.step_store import Seat, Step
from app.services.studies import protocol_of
from app.speech.lines import RECOGNISED_LANGUAGES, spoken_lines
from app.tables import Device, Station, Study

StationRef = str | Seat
"""A station by name (the experimenter's routes), or its seat as a robot's device brings it
(read in the same transaction), which spares the runtime looking it up again."""


def _named(station: StationRef) -> tuple[str, Seat | None]:
    return (station, None) if isinstance(station, str) else (station.station_name, station)


def state(db: Session, *, station: StationRef) -> StationStateOut:
    """The station's state and what is expected next."""
    name, loaded = _named(station)
    return state_out(runtime.station_view(db, station_name=name, seat=loaded))


def _study_run_by(db: Session, station: Seat) -> Study:
    """The seated participant's study, or else the study the station runs (409 when none)."""
    study_id = station.participant.study_id if station.participant else None
    if study_id is None:
        own = db.get(Station, station.station_id)
        study_id = own.study_id if own is not None else None
    study = db.get(Study, study_id) if study_id is not None else None
    if study is None:
        raise Conflict(
            f"station {station.station_name!r} runs no study yet: an experimenter seats a "
            "participant (or chooses the station's study) on its console first"
        )
    return study


def _as_seated_sees_it(study: Study, station: Seat) -> Protocol:
    """The study's protocol in the seated participant's language (the study's first when
    nobody of this study is seated)."""
    seated = station.participant
    language = seated.language if seated is not None and seated.study_id == study.id else None
    return languages.protocol_for(language, protocol_of(study))


def room(db: Session, *, station: Seat) -> RoomOut:
    """The room of the seated participant's study, or else of the study the station runs."""
    study = _study_run_by(db, station)
    protocol = _as_seated_sees_it(study, station)
    return RoomOut(
        study=study.name,
        categories=[RoomCategory(name=c.name, title=c.title) for c in protocol.categories],
        rules=list(protocol.study.rules),
        layout=protocol.room_layout(),
    )


def speech(db: Session, *, station: Seat) -> SpeechOut:
    """How a robot that hears takes answers in the study the station runs (same rule as room)."""
    study = _study_run_by(db, station)
    protocol = _as_seated_sees_it(study, station)
    return SpeechOut(
        study=study.name,
        language=protocol.default_language,
        offline_recognition=protocol.default_language in RECOGNISED_LANGUAGES,
        **protocol.speech.model_dump(),
    )


def check_spoken_line(db: Session, *, station: Seat, text: str) -> str:
    """The language of a line the study the station runs says (the seated participant's
    first); 404 for any other text (same rule as room): the server synthesises its robot's
    lines, not any text a device sends."""
    study = _study_run_by(db, station)
    seated = _as_seated_sees_it(study, station)
    for language in seated.study.languages:
        if text in spoken_lines(protocol_of(study).in_language(language)):
            return language
    raise NotFound(
        f"not a line of study {study.name!r}: the server speaks only its questions, replies, "
        "request to answer again and rules"
    )


def presence(db: Session, *, station: Seat, device_id: int, body: PresenceRequest) -> None:
    """Store where the room client sees the participant (the console's live room panel)."""
    said = body.utterance
    room_presence.record(
        db,
        station_id=station.station_id,
        device_id=device_id,
        x=body.x,
        z=body.z,
        heading=body.heading,
        zone=body.zone,
        said=room_presence.Said(said.kind, said.text) if said is not None else None,
    )


def notice(db: Session, *, station: Seat, device_id: int, body: NoticeRequest) -> None:
    """Show this device's line on the station's console (or clear it)."""
    stations.set_notice(db, device_id=device_id, text=body.text, attention=body.attention)


def _prompt(
    db: Session, station: StationRef, body: PromptRequest, actor: Actor, device_id: int | None
) -> tuple[runtime.PromptResult, PromptOut]:
    name, loaded = _named(station)
    result = runtime.request_prompt(
        db,
        station_name=name,
        category=body.category,
        actor=actor,
        device_id=device_id,
        seat=loaded,
        zone=body.zone,
    )
    out = prompt_out(
        result.prompt,
        session=result.session_number,
        run=result.run_number,
        created=result.created,
        language=result.language,
    )
    return result, out


def prompt(
    db: Session, *, station: StationRef, body: PromptRequest, actor: Actor, device_id: int | None
) -> PromptOut:
    """Choose a question for a category (or hand out its open one again)."""
    return _prompt(db, station, body, actor, device_id)[1]


def wizard_prompt(
    db: Session, *, station: str, body: PromptRequest, actor: Actor
) -> StaffPromptOut:
    """:func:`prompt` for an experimenter (Wizard-of-Oz), as :func:`staff_prompt` shows it."""
    result, out = _prompt(db, station, body, actor, None)
    return staff_prompt(out, shows_learners=result.learners_shown)


def _answer(
    db: Session,
    station: StationRef,
    step_id: int,
    body: AnswerRequest,
    actor: Actor,
    device_id: int | None,
) -> tuple[runtime.AnswerResult, AnswerOut]:
    name, loaded = _named(station)
    result = runtime.record_answer(
        db,
        station_name=name,
        step_id=step_id,
        answer=body.answer == "yes",
        idempotency_key=body.idempotency_key,
        actor=actor,
        device_id=device_id,
        seat=loaded,
        heard=runtime.HowAnswered(
            body.modality, body.transcript, body.transcript_confidence, body.transcript_engine
        ),
    )
    return result, answer_out(result, result.expected)


def answer(
    db: Session,
    *,
    station: StationRef,
    step_id: int,
    body: AnswerRequest,
    actor: Actor,
    device_id: int | None,
) -> AnswerOut:
    """Record an answer exactly once and return the reply."""
    return _answer(db, station, step_id, body, actor, device_id)[1]


def spoken_answer(
    db: Session,
    *,
    station: Seat,
    step_id: int,
    body: AnswerRequest,
    actor: Actor,
    device_id: int,
    recording: bytes | None,
) -> AnswerOut:
    """:func:`answer` for an answer the server recognised from the room's audio; ``recording``:
    the utterance's audio, stored with the answer (only where the study records audio)."""
    result, out = _answer(db, station, step_id, body, actor, device_id)
    if recording is not None:
        answer_audio.store(db, answer_id=result.answer.id, pcm=recording)
    return out


def wizard_answer(
    db: Session, *, station: str, step_id: int, body: AnswerRequest, actor: Actor
) -> StaffAnswerOut:
    """:func:`answer` for an experimenter (Wizard-of-Oz), as :func:`staff_answer` shows it."""
    result, out = _answer(db, station, step_id, body, actor, None)
    return staff_answer(out, shows_learners=result.learners_shown)


def start_run(db: Session, *, station: StationRef, actor: Actor) -> StationStateOut:
    """Start the next run of the running session."""
    name, _ = _named(station)
    return state_out(runtime.start_run(db, station_name=name, actor=actor))


# ------------------------------------------------------------------ service objects → bodies


def expected_out(expected: runtime.Expected) -> ExpectedOut:
    """Serialise an expectation."""
    return ExpectedOut(
        action=expected.action,
        message=expected.message,
        categories=expected.categories,
        step_id=expected.step_id,
        session=expected.session,
    )


def prompt_out(prompt: Step, *, session: int, run: int, created: bool, language: str) -> PromptOut:
    """Serialise a prompt."""
    return PromptOut(
        step_id=prompt.id,
        category=prompt.category,
        action=prompt.action,
        question=prompt.question,
        language=language,
        probabilities=prompt.probabilities,
        adapts=prompt.adapts,
        session=session,
        run=run,
        created=created,
    )


def answer_out(result: runtime.AnswerResult, expected: runtime.Expected) -> AnswerOut:
    """Serialise an answer with what comes next."""
    answer = result.answer
    return AnswerOut(
        step_id=result.prompt.id,
        category=result.prompt.category,
        answer="yes" if answer.answer else "no",
        reply=answer.reply,
        confidence_level=answer.confidence_level,
        confidence=answer.confidence,
        probability=answer.probability,
        probabilities=answer.probabilities_after,
        replayed=result.replayed,
        run_completed=result.run_completed,
        session_completed=result.session_completed,
        expected=expected_out(expected),
    )


def state_out(view: runtime.StationView) -> StationStateOut:
    """Serialise a station view (open prompts always belong to the current run)."""
    session = SessionOut(**view.session) if view.session else None
    run = RunOut(**view.run) if view.run else None
    return StationStateOut(
        station=view.station,
        participant=view.participant,
        study=view.study,
        session=session,
        run=run,
        open_prompts=[
            prompt_out(
                p,
                session=session.number if session else 0,
                run=run.number if run else 0,
                created=False,
                language=view.language or "en",
            )
            for p in view.open_prompts
        ],
        expected=expected_out(view.expected),
        language=view.language,
        last_reply=LastReplyOut(**view.last_reply) if view.last_reply else None,
    )


def device_out(device: Device, station: Station, contact: sites.Contact) -> DeviceOut:
    """Serialise a device (never its key), with what the console shows of it: connected or not,
    and its notice, so that a JSON client sees what the operator sees — as much of its contact as
    the reader may see (``contact``: app.services.privacy.sites.Contact)."""
    notice = (
        DeviceNotice(text=device.notice, attention=device.notice_attention, at=device.notice_at)
        if device.notice is not None and contact.when(device.notice_at) is not None
        else None
    )
    return DeviceOut(
        id=device.id,
        station=station.name,
        label=device.label,
        key_prefix=device.key_prefix,
        created_at=device.created_at,
        revoked_at=device.revoked_at,
        last_seen_at=contact.when(device.last_seen_at),
        connected=contact.connected(device.connected and device.revoked_at is None),
        notice=notice,
    )


# ------------------------------------------------------------- what staff may see of them


def staff_prompt(prompt: PromptOut, *, shows_learners: bool) -> StaffPromptOut:
    """A prompt for the experimenter's routes: without the learner's probabilities while the
    study is blinded (app.services.blinding)."""
    data = prompt.model_dump()
    if not shows_learners:
        data["probabilities"] = None
    return StaffPromptOut.model_validate(data)


def staff_answer(answer: AnswerOut, *, shows_learners: bool) -> StaffAnswerOut:
    """An answer for the experimenter's routes: the reply's words (the robot says them aloud),
    but neither its level nor the probabilities while the study is blinded."""
    data = answer.model_dump()
    if not shows_learners:
        data.update(confidence_level=None, confidence=None, probability=None, probabilities=None)
    return StaffAnswerOut.model_validate(data)


def staff_state(view: runtime.StationView) -> StaffStationStateOut:
    """A station's state for the experimenter's routes (open prompts as :func:`staff_prompt`)."""
    state = state_out(view)
    data = state.model_dump(exclude={"open_prompts", "last_reply"})
    data["open_prompts"] = [
        staff_prompt(p, shows_learners=view.learners_shown) for p in state.open_prompts
    ]
    return StaffStationStateOut.model_validate(data)
