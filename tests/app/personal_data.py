"""A study with personal data to erase or anonymise: a free-text answer, spoken transcripts, a
stratification value; and a scan of the whole database and of files for what must be gone."""

from __future__ import annotations

import re
import subprocess
import time
from pathlib import Path

from sqlalchemy.engine import make_url
from typer.testing import CliRunner, Result

from app.cli import cli
from app.db import Database, WalCheckpointer
from app.protocol import parse_protocol
from app.services import studies
from app.services.audit import Actor
from tests.conftest import EXP3_ONLY, PRE_STUDY_ANSWERS, Lab, protocol_text, tablet_client

FREE_TEXT = "Quagmire-Xylophone remembers the orange lighthouse"
TRANSCRIPT = "yes zebrafish certainly"
STRATUM = "lefthanded"
AGE_ITEM = (
    '{ key = "age", text = "How old are you (in years)?", kind = "number", minimum = 18, '
    "maximum = 99 },"
)
NOTE_ITEM = (
    '{ key = "note", text = "Anything else?", kind = "text", required = false, max_length = 400 },'
)


def personal_data_study(database: Database, name: str = "erasable", **replacements: str) -> str:
    """Exp3 in both conditions, a free-text pre-study item, stratified by handedness."""
    text = protocol_text(
        **EXP3_ONLY,
        **{AGE_ITEM: AGE_ITEM + "\n    " + NOTE_ITEM},
        **{"stratify_by = []": 'stratify_by = ["hand"]'},
        **replacements,
    )
    with database.writing() as db:
        studies.create_study(db, name=name, loaded=parse_protocol(text), actor=Actor.system())
    return name


def note_of(code: str) -> str:
    """The participant's free-text answer (distinct per participant)."""
    return f"{FREE_TEXT} for {code.lower()}"


def enrol_with_data(lab: Lab, code: str) -> None:
    """Enrol, consent, pre-study with free text, the practice run answered by voice."""
    enrolled = lab.experimenter.post(
        f"/api/v1/studies/{lab.study}/participants",
        json={"code": code, "strata": {"hand": STRATUM}},
    )
    assert enrolled.status_code == 201, enrolled.text
    seated = lab.experimenter.put(
        f"/api/v1/stations/{lab.station}/participant", json={"study": lab.study, "code": code}
    )
    assert seated.status_code == 200, seated.text
    tablet = lab.tablets[code] = tablet_client(lab.app, lab, code)
    assert tablet.post("/api/v1/tablet/consent", json={"accept": True}).status_code == 200
    for instrument, answers in PRE_STUDY_ANSWERS.items():
        extra = {"note": note_of(code)} if instrument == "demographics" else {}
        sent = tablet.post(
            f"/api/v1/tablet/questionnaires/{instrument}", json={"answers": answers | extra}
        )
        assert sent.status_code == 200, sent.text
    lab.start_session()
    expected = lab.robot.get("/api/v1/station").json()["expected"]
    for category in expected["categories"]:
        step = lab.prompt(category)
        answered = lab.robot.post(
            f"/api/v1/station/steps/{step['step_id']}/answer",
            json={
                "answer": "yes",
                "idempotency_key": f"{code}-{category}",
                "modality": "speech",
                "transcript": f"{TRANSCRIPT} {code.lower()}",
                "transcript_confidence": 0.9,
            },
        )
        assert answered.status_code == 200, answered.text


def heard_in_the_room_then_unseated(lab: Lab, code: str) -> None:
    """The room client reports the seated participant's words (the recogniser's), then the
    station is freed: their presence must go with them all the same."""
    said = {"kind": "participant", "text": f"{TRANSCRIPT} {code.lower()}"}
    reported = lab.robot.put(
        "/api/v1/station/presence", json={"x": 1.0, "z": 2.0, "heading": 0, "utterance": said}
    )
    assert reported.status_code == 204, reported.text
    freed = lab.experimenter.delete(f"/api/v1/stations/{lab.station}/participant")
    assert freed.status_code in (200, 204), freed.text


def run_cli(database_url: str, *args: str) -> Result:
    return CliRunner().invoke(cli, list(args), env={"TRUSTLAB_DATABASE_URL": database_url})


def dump_database(database: Database, *others: Database) -> bytes:
    """Everything the database holds: pg_dump's SQL, or the SQLite file and its WAL byte for
    byte (deleted content included, were it not zeroed). ``others``: further engines on the
    same database (the served app's), closed first so that, as docs/data-protection.md says, a
    checkpoint once no reader holds an old snapshot leaves no earlier page in the WAL."""
    url = make_url(database.url)
    if url.get_backend_name() == "sqlite":
        for engine in (database, *others):
            engine.dispose()
        path = Path(str(url.database))
        # The served app's own threads (its activity flusher, its background checkpoints) may
        # be mid-transaction at this moment: wait for them to let go, however long that takes
        # on a loaded machine, rather than read a dump with an earlier page still in the WAL.
        checkpointer = WalCheckpointer(str(path))
        for _attempt in range(600):
            if checkpointer.truncate():
                break
            time.sleep(0.05)
        else:
            raise AssertionError("a reader still holds an old snapshot after 30 s")
        return b"".join(
            p.read_bytes() for p in (path, path.with_name(path.name + "-wal")) if p.exists()
        )
    conninfo = url.set(drivername="postgresql").render_as_string(hide_password=False)
    return subprocess.run(
        ["pg_dump", "--data-only", conninfo], capture_output=True, check=True
    ).stdout


def mentions(content: bytes, code: str) -> list[str]:
    found = []
    # Not the stratum: it stays with the allocation slot, shared with others of the stratum.
    for secret in (code, note_of(code), f"{TRANSCRIPT} {code.lower()}"):
        if re.search(rb"(?<![A-Za-z0-9_-])" + re.escape(secret.encode()), content):
            found.append(secret)
    return found
