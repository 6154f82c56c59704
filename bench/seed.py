"""Bulk-generated studies for benchmarks: N participants with complete, plausible records.

Going through the services would take ~40 transactions per participant; benchmarks need a thousand
participants in seconds, so this writes the same rows with bulk inserts. Learners are simulated
with the real Exp3 (both conditions) so probabilities and ``p_preferred`` look like a study's;
questionnaire answers follow a simple condition effect. The data is for timing pages, not for
``trustlab verify`` (learner states are not stored step by step).
"""

from __future__ import annotations

import random
import secrets
from datetime import timedelta
from typing import Any

from sqlalchemy import insert, text

from app.db import Database
from app.protocol import LearnerKind, default_protocol, parse_protocol
from app.randomisation import entry_at
from app.services import studies
from app.services.audit import Actor
from app.services.sessions import stations
from app.services.sessions.learners import LearnerSpec
from app.services.sessions.replies import choose_reply
from app.tables import (
    Allocation,
    Answer,
    LearnerState,
    Participant,
    Prompt,
    Response,
    Run,
    Study,
    StudySession,
    Submission,
    utcnow,
)
from models.learners.exp3 import Exp3

SYSTEM = Actor.system("bench")


def _exp3_protocol() -> str:
    return default_protocol().source_text.replace('learner = "meta"', 'learner = "exp3"')


def seed_study(
    database: Database, *, name: str, participants: int, seed: int = 1, title: str | None = None
) -> None:
    """Create study ``name`` with ``participants`` fully completed participants (``title``: the
    study's own, else the protocol's)."""
    rng = random.Random(seed)
    loaded = parse_protocol(_exp3_protocol())
    protocol = loaded.protocol
    with database.writing() as db:
        study = studies.create_study(db, name=name, loaded=loaded, actor=SYSTEM, title=title)
        # The concealed sequence follows ``seed`` too (a created study draws a secret one): the
        # same call seeds the same conditions, so a test or bench reads the same data every run.
        study.allocation_seed = rng.randbytes(32).hex()
        study_id = study.id
        study_seed = bytes.fromhex(study.allocation_seed)
    with database.writing() as db:
        station_id = stations.create_station(db, name=f"{name}-seed", actor=SYSTEM).id
    assert all(c.learner is LearnerKind.EXP3 for c in protocol.conditions)
    start = utcnow() - timedelta(days=30)
    rows: dict[type, list[dict[str, Any]]] = {
        t: []
        for t in (
            Participant,
            Allocation,
            LearnerState,
            StudySession,
            Run,
            Prompt,
            Answer,
            Response,
            Submission,
        )
    }
    ids = {"participant": 0, "session": 0, "run": 0, "prompt": 0}
    with database.read_session() as db:
        ids = {
            "participant": int(db.query(Participant).count()),
            "session": int(db.query(StudySession).count()),
            "run": int(db.query(Run).count()),
            "prompt": int(db.query(Prompt).count()),
        }
    scales = {s.name: s for s in protocol.questionnaires.scales}
    for number in range(participants):
        ids["participant"] += 1
        pid = ids["participant"]
        entry = entry_at(
            study_seed,
            "",
            [c.id for c in protocol.conditions],
            protocol.allocation.block_sizes,
            number,
        )
        at = start + timedelta(minutes=number)
        rows[Participant].append(
            {
                "id": pid,
                "study_id": study_id,
                "code": f"P{number + 1:04d}",
                "stratum": "",
                "strata": {},
                "status": "completed",
                "enrolled_at": at,
                "enrolled_by": "bench",
                "withdrawal_reason": "",
                "token_generation": 0,
            }
        )
        rows[Allocation].append(
            {
                "study_id": study_id,
                "participant_id": pid,
                "stratum": "",
                "sequence_index": number,
                "block_number": entry.block_number,
                "block_size": entry.block_size,
                "condition": entry.condition,
                "revealed_at": at,
            }
        )
        boost = 0.7 if entry.condition == "C2" else 0.0
        for instrument in protocol.questionnaires.instruments:
            if instrument.when == "session":
                continue
            rows[Submission].append(
                {
                    "participant_id": pid,
                    "instrument": instrument.key,
                    "session": None,
                    "submitted_at": at,
                    "revision": 1,
                }
            )
            for item in instrument.items:
                if item.kind.value == "likert" and item.scale:
                    scale = scales[item.scale]
                    value = str(rng.randint(scale.minimum, scale.maximum))
                elif item.kind.value == "number":
                    value = str(rng.randint(18, 60))
                elif item.kind.value == "choice":
                    value = item.options[0].value
                else:
                    continue
                rows[Response].append(
                    {
                        "participant_id": pid,
                        "instrument": instrument.key,
                        "session": None,
                        "item": item.key,
                        "value": value,
                        "answered_at": at,
                    }
                )
        learners = {
            c.name: Exp3(len(c.questions), protocol.learners.exp3.gamma)
            for c in protocol.categories
        }
        initial = {k: v.state_dict() for k, v in learners.items()}
        numbers = range(
            0 if protocol.schedule.familiarisation_run else 1, protocol.schedule.sessions + 1
        )
        for session_number in numbers:
            ids["session"] += 1
            session_id = ids["session"]
            rows[StudySession].append(
                {
                    "id": session_id,
                    "participant_id": pid,
                    "station_id": station_id,
                    "number": session_number,
                    "status": "completed",
                    "started_at": at,
                    "started_by": "bench",
                    "ended_at": at,
                    "ended_by": "bench",
                }
            )
            runs = 1 if session_number == 0 else protocol.schedule.runs_per_session
            for run_number in range(1, runs + 1):
                ids["run"] += 1
                rows[Run].append(
                    {
                        "id": ids["run"],
                        "session_id": session_id,
                        "participant_id": pid,
                        "number": run_number,
                        "status": "completed",
                        "started_at": at,
                        "ended_at": at,
                    }
                )
                for category in protocol.categories:
                    learner = learners[category.name]
                    before = [float(p) for p in learner.probabilities()]
                    action = rng.choices(range(len(before)), before)[0]
                    adapts = session_number > 0
                    version = learner.updates
                    said = action == category.preferred
                    if adapts:
                        learner.update(action, 1.0 if said else 0.0)
                    after = [float(p) for p in learner.probabilities()]
                    ids["prompt"] += 1
                    preferred = category.preferred or 0
                    rows[Prompt].append(
                        {
                            "id": ids["prompt"],
                            "participant_id": pid,
                            "run_id": ids["run"],
                            "category": category.name,
                            "action": action,
                            "question": category.questions[action],
                            "probabilities": before,
                            "p_preferred": before[preferred],
                            "learner_version": version,
                            "adapts": adapts,
                            "prompted_at": at,
                            "actor": "bench",
                        }
                    )
                    reply = choose_reply(
                        protocol,
                        LearnerSpec("exp3", len(before), {"gamma": learner.gamma}, None),
                        before=before,
                        action=action,
                        after=after,
                        said_yes=said,
                    )
                    rows[Answer].append(
                        {
                            "prompt_id": ids["prompt"],
                            "participant_id": pid,
                            "answer": said,
                            "reward": 1.0 if said else 0.0,
                            "probabilities_after": after,
                            "p_preferred": after[preferred],
                            "probability": reply.probability,
                            "confidence_level": reply.level,
                            "confidence": reply.name,
                            "reply": reply.text,
                            "learner_version": learner.updates,
                            "idempotency_key": secrets.token_hex(8),
                            "answered_at": at,
                            "processing_ms": 1.0,
                            "actor": "bench",
                        }
                    )
            if session_number >= 1:
                for instrument in protocol.instruments_at("session"):
                    rows[Submission].append(
                        {
                            "participant_id": pid,
                            "instrument": instrument.key,
                            "session": session_number,
                            "submitted_at": at,
                            "revision": 1,
                        }
                    )
                    for item in instrument.items:
                        centre = 2.8 + boost + (0.2 if boost else 0.0) * (session_number - 1)
                        point = min(5, max(1, round(rng.gauss(centre, 1.0))))
                        rows[Response].append(
                            {
                                "participant_id": pid,
                                "instrument": instrument.key,
                                "session": session_number,
                                "item": item.key,
                                "value": str(point),
                                "answered_at": at,
                            }
                        )
        for name_, learner in learners.items():
            rows[LearnerState].append(
                {
                    "participant_id": pid,
                    "category": name_,
                    "kind": "exp3",
                    "n_arms": learner.n_arms,
                    "config": {"gamma": protocol.learners.exp3.gamma},
                    "checkpoint_sha256": None,
                    "initial_state": initial[name_],
                    "state": learner.state_dict(),
                    "version": learner.updates,
                    "updated_at": at,
                }
            )
    with database.writing() as db:
        for table, values in rows.items():
            for chunk in range(0, len(values), 5000):
                db.execute(insert(table), values[chunk : chunk + 5000])
        if not database.is_sqlite:  # explicit ids do not advance PostgreSQL's sequences
            for serial in ("participant", "study_session", "run", "prompt"):
                db.execute(
                    text(
                        f"SELECT setval(pg_get_serial_sequence('{serial}', 'id'), "
                        f"(SELECT max(id) FROM {serial}))"
                    )
                )
        db.commit()


def study_exists(database: Database, name: str) -> bool:
    """Whether a study of that name exists."""
    with database.read_session() as db:
        return db.query(Study).filter(Study.name == name).count() > 0
