"""The browser escape room in headless Chromium: its frame rate, and how soon a question's caption
follows walking into a trigger zone.

A trustlab server (a subprocess, as in production) runs the shipped study on SQLite; Debian's
Chromium, driven by Playwright, opens /stations/room-1/room (static/js/room.js) as a lab machine
would. Two figures (issue 22's targets):

- **frames per second** at each ``--viewports`` size, standing still and while walking (the arrow
  keys held, turning in circles), counted by the page's own animation loop over ``--seconds``;
  also the render scale the room settled on (below 1: it draws fewer pixels to keep the rate up;
  ``--scale 1`` pins full resolution, to see what the adapting buys);
- **zone → caption**: the ``trustlab:zone-to-caption`` performance measure the room records from
  the frame in which the participant stepped into a zone to the frame that draws the question's
  caption, i.e. the prompt's round trip over the station WebSocket (the learner choosing the
  question, the step committed) plus the page's own work. One sample per prompt: the practice run
  and ``--sessions`` sessions of three runs (the tablet questionnaires between sessions are
  filled in directly in the database).

Targets: ≥ 30 frames/s; zone → caption p95 ≤ 150 ms (server on the same machine).

    .venv/bin/python bench/room.py
    .venv/bin/python bench/room.py --sessions 4 --json
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from playwright.sync_api import Page, sync_playwright  # noqa: E402

from app import schema  # noqa: E402
from app.db import Database  # noqa: E402
from app.protocol import default_protocol  # noqa: E402
from app.services import studies  # noqa: E402
from app.services.audit import Actor  # noqa: E402
from app.services.participants import enrolment, questionnaires  # noqa: E402
from tests.conftest import TRUST_ANSWERS  # noqa: E402
from tests.e2e import room_driver as drive  # noqa: E402
from tests.servers import ServerProcess  # noqa: E402

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking"]
STUDY = "default"

FRAMES = "() => [window.trustlabRoom.frames, performance.now()]"
LATENCIES = """() => {
  const found = performance.getEntriesByName("trustlab:zone-to-caption").map((m) => m.duration);
  performance.clearMeasures("trustlab:zone-to-caption");
  return found;
}"""


def _frame_rate(page: Page, seconds: float, *, walking: bool) -> float:
    """Frames the room drew per second over ``seconds``, walking in circles or standing."""
    if walking:
        page.keyboard.down("ArrowUp")
        page.keyboard.down("ArrowLeft")
    try:
        first = page.evaluate(FRAMES)
        time.sleep(seconds)
        last = page.evaluate(FRAMES)
    finally:
        if walking:
            page.keyboard.up("ArrowLeft")
            page.keyboard.up("ArrowUp")
    return float((last[0] - first[0]) / ((last[1] - first[1]) / 1000.0))


def _fill_session_questionnaire(database: Database, code: str, session: int) -> None:
    with database.writing() as db:
        study = studies.get_study(db, STUDY)
        participant = enrolment.get_participant(db, study, code, actor=Actor.system())
        questionnaires.submit(
            db,
            participant=participant,
            protocol=studies.protocol_of(study),
            instrument_key="trust",
            session=session,
            answers=TRUST_ANSWERS,
            actor=drive.SYSTEM,
        )


def _summary(samples: list[float]) -> dict[str, float | int]:
    ordered = sorted(samples)
    p95 = ordered[min(len(ordered) - 1, max(0, round(0.95 * len(ordered)) - 1))]
    return {
        "n": len(ordered),
        "median_ms": round(statistics.median(ordered), 1),
        "p95_ms": round(p95, 1),
        "max_ms": round(ordered[-1], 1),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--viewports", default="1366x768,768x1024", help="WIDTHxHEIGHT,…")
    parser.add_argument("--seconds", type=float, default=5.0, help="each frame-rate window")
    parser.add_argument("--sessions", type=int, default=1, help="sessions walked after practice")
    parser.add_argument(
        "--scale", type=float, help="pin the render scale (?scale=, e.g. 1: full resolution)"
    )
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    args = parser.parse_args(argv)
    sizes = [tuple(int(n) for n in size.split("x")) for size in args.viewports.split(",")]

    results: dict[str, Any] = {"frame_rate": [], "zone_to_caption": None}
    with tempfile.TemporaryDirectory() as folder:
        url = f"sqlite:///{folder}/room.sqlite3"
        database = Database(url)
        schema.upgrade(database)
        with database.writing() as db:
            studies.create_study(db, name=STUDY, loaded=default_protocol(), actor=drive.SYSTEM)
        server = ServerProcess(url, Path(folder) / "var")
        server.start()
        try:
            lab = drive.seat_participant(database, server.url, STUDY)
            with sync_playwright() as playwright:
                browser = playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
                lab.start_session()  # the practice run: the room can be walked
                for width, height in sizes:
                    page = browser.new_page(viewport={"width": width, "height": height})
                    drive.open_room(page, lab, query=f"?scale={args.scale}" if args.scale else "")
                    _frame_rate(page, 1.0, walking=False)  # let the render scale settle
                    standing = _frame_rate(page, args.seconds, walking=False)
                    walking = _frame_rate(page, args.seconds, walking=True)
                    scale = page.evaluate("() => window.trustlabRoom.renderScale")
                    results["frame_rate"].append(
                        {
                            "viewport": f"{width}x{height}",
                            "standing_fps": round(standing, 1),
                            "walking_fps": round(walking, 1),
                            "render_scale": round(scale, 2),
                        }
                    )
                    print(
                        f"  {width}x{height}: {standing:.1f} / {walking:.1f} fps", file=sys.stderr
                    )
                    page.close()

                page = browser.new_page(viewport={"width": sizes[0][0], "height": sizes[0][1]})
                drive.open_room(page, lab)
                drive.walk_to(page, *drive.START)  # the frame-rate walk left them somewhere
                samples: list[float] = []
                for session in range(args.sessions + 1):
                    if session > 0:
                        if session > 1:
                            _fill_session_questionnaire(database, lab.code, session - 1)
                        lab.start_session()
                    runs = 1 if session == 0 else 3
                    for run in range(runs):
                        drive.run_through(page, drive.PAPER_ORDER)
                        samples += page.evaluate(LATENCIES)
                        print(f"  session {session} run {run + 1}: {len(samples)}", file=sys.stderr)
                results["zone_to_caption"] = _summary(samples)
                browser.close()
        finally:
            server.stop()
            database.dispose()

    if args.json:
        print(json.dumps(results, indent=2))
        return 0
    print("frame rate (headless Chromium, software WebGL):")
    for row in results["frame_rate"]:
        print(
            f"  {row['viewport']:>10}: standing {row['standing_fps']:5.1f} fps, walking "
            f"{row['walking_fps']:5.1f} fps (render scale {row['render_scale']})"
        )
    latency = results["zone_to_caption"]
    print(
        f"zone → caption over {latency['n']} prompts: median {latency['median_ms']} ms, "
        f"p95 {latency['p95_ms']} ms, max {latency['max_ms']} ms"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
