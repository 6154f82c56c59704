"""A robot bridge's turn-around: from the robot reporting a recognised answer to the bridge asking
it to say the reply.

A trustlab server (a subprocess, as in production) runs the shipped study on SQLite. For each
robot kind, a stand-in robot speaking that robot's own protocol on loopback (tests/robots/
standins/) is driven by the real vendor client inside the bridge (app/robots/), and the console
asks every question of the practice run and session 1 for ``--participants`` participants. The
stand-in timestamps the moment it hands the recogniser's words to the bridge and the moment the
bridge asks it to say the next line (the reply): between the two lie the vendor client, the
bridge's vocabulary check, the answer's round trip over the station WebSocket (the learner's
update, the step committed) and the reply's request to the robot. The robot's own speech time
is not in it (the stand-in says instantly).

Target: p95 ≤ 60 ms with the server on the same machine.

    .venv/bin/python bench/bridge.py
    .venv/bin/python bench/bridge.py --kinds furhat --participants 10 --json
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from app import schema  # noqa: E402
from app.db import Database  # noqa: E402
from app.protocol import default_protocol  # noqa: E402
from app.services import studies  # noqa: E402
from app.services.participants import enrolment  # noqa: E402
from tests.e2e import room_driver as drive  # noqa: E402
from tests.robots.harness import BOUND, RunningBridge  # noqa: E402
from tests.robots.kinds import KINDS  # noqa: E402
from tests.robots.standins.script import Script  # noqa: E402
from tests.servers import ServerProcess  # noqa: E402

STUDY = "default"


def _percentile(samples: list[float], share: float) -> float:
    ordered = sorted(samples)
    return ordered[min(len(ordered) - 1, round(share * (len(ordered) - 1)))]


def _summary(samples: list[float]) -> dict[str, float | int]:
    milliseconds = [1000 * s for s in samples]
    return {
        "n": len(milliseconds),
        "median_ms": round(statistics.median(milliseconds), 1),
        "p95_ms": round(_percentile(milliseconds, 0.95), 1),
        "max_ms": round(max(milliseconds), 1),
    }


def _answer_everything(lab: drive.RoomLab, script: Script) -> list[float]:
    """Ask each question the station expects until it expects none; the turn-around of each."""
    latencies: list[float] = []
    while True:
        expected = lab.experimenter.get(f"/api/v1/stations/{lab.station}/state").json()
        expected = expected["expected"]
        if expected["action"] != "prompt":
            return latencies
        script.add("yes" if len(latencies) % 3 else "no")
        lines = len(script.said)
        lab.wizard_prompt(expected["categories"][0])
        script.wait_said(lines + 2, BOUND)  # the question, then the reply
        latencies.append(script.said_at[-1] - script.heard_at[-1])


def _seat(database: Database, lab: drive.RoomLab, code: str) -> None:
    """Free the station, then enrol ``code``, fill their pre-study questionnaires and seat them."""
    freed = lab.experimenter.delete(f"/api/v1/stations/{lab.station}/participant")
    assert freed.status_code in (200, 204), freed.text
    with database.writing() as db:
        participant = enrolment.enroll_participant(
            db, study_name=STUDY, actor=drive.SYSTEM, code=code
        ).participant
    drive.give_pre_study(database, study=STUDY, participant=participant, actor=drive.SYSTEM)
    seated = lab.experimenter.put(
        f"/api/v1/stations/{lab.station}/participant", json={"study": STUDY, "code": code}
    )
    assert seated.status_code == 200, seated.text


def _run_kind(
    name: str, lab: drive.RoomLab, database: Database, participants: int, transcript: bool
) -> list[float]:
    kind = KINDS[name]()
    samples: list[float] = []
    script = Script()
    with (
        kind.stand_in(script) as stand_in,
        RunningBridge(kind.robot(stand_in), lab.url, lab.station, lab.key) as bridge,
    ):
        for number in range(participants):
            _seat(database, lab, f"{name[:2].upper()}{number:03d}")
            for _session in range(2):  # the practice run, then session 1
                lab.start_session()
                samples += _answer_everything(lab, script)
            print(f"  {name}: participant {number + 1}: {len(samples)} answers", file=sys.stderr)
    if transcript:
        print("\n".join(bridge.lines), file=sys.stderr)
    return samples


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--kinds", default=",".join(KINDS), help="robot kinds, comma-separated")
    parser.add_argument("--participants", type=int, default=5, help="participants per kind")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument(
        "--transcript", action="store_true", help="print what each bridge printed (stderr)"
    )
    args = parser.parse_args(argv)
    kinds = [k for k in args.kinds.split(",") if k]
    unknown = [k for k in kinds if k not in KINDS]
    if unknown:
        parser.error(f"unknown kind(s) {', '.join(unknown)}; known: {', '.join(KINDS)}")

    results: dict[str, Any] = {}
    with tempfile.TemporaryDirectory() as folder:
        url = f"sqlite:///{folder}/bridge.sqlite3"
        database = Database(url)
        schema.upgrade(database)
        with database.writing() as db:
            studies.create_study(db, name=STUDY, loaded=default_protocol(), actor=drive.SYSTEM)
        server = ServerProcess(url, Path(folder) / "var")
        server.start()
        try:
            lab = drive.seat_participant(database, server.url, STUDY, code="WARMUP")
            for name in kinds:
                results[name] = _summary(
                    _run_kind(name, lab, database, args.participants, args.transcript)
                )
        finally:
            server.stop()
            database.dispose()

    if args.json:
        print(json.dumps(results, indent=2))
        return 0
    print("recognised answer -> reply asked for (ms), server on the same machine:")
    for name, row in results.items():
        print(
            f"  {name:>10}: n {row['n']}, median {row['median_ms']}, p95 {row['p95_ms']}, "
            f"max {row['max_ms']}"
        )
    return 0


def _standard_output_for_the_report_alone() -> None:
    """Send what native libraries write to file descriptor 1 (the qi library logs there) to
    stderr, and keep the real standard output for this script's own report: with ``--json`` it
    must hold the JSON alone."""
    sys.stdout.flush()
    report = os.fdopen(os.dup(1), "w", buffering=1)
    os.dup2(2, 1)
    sys.stdout = report


if __name__ == "__main__":
    _standard_output_for_the_report_alone()
    raise SystemExit(main())
