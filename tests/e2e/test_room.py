"""The browser escape room end to end: a participant walks the maze by keyboard in real Chromium,
the zones ask the robot's questions, and every answer reaches the database exactly once."""

from __future__ import annotations

from pathlib import Path

import pytest
from playwright.sync_api import Browser, expect
from sqlalchemy import func, select

from app.db import Database
from app.services import verify
from app.tables import Answer, Prompt
from tests.e2e import room_driver as drive
from tests.servers import ServerProcess

DESKTOP = {"width": 1366, "height": 768}
TABLET = {"width": 768, "height": 1024}


def _steps(database: Database) -> list[tuple[int, str, str | None, str | None, int]]:
    """(prompt id, category, zone, answer modality, answers stored for it) of every step."""
    with database.read_session() as db:
        rows = db.execute(
            select(Prompt.id, Prompt.category, Prompt.zone, Answer.modality)
            .outerjoin(Answer, Answer.prompt_id == Prompt.id)
            .order_by(Prompt.id)
        ).all()
        counts = dict(
            db.execute(select(Answer.prompt_id, func.count()).group_by(Answer.prompt_id)).all()
        )
    return [(pid, category, zone, how, counts.get(pid, 0)) for pid, category, zone, how in rows]


def _verified(database: Database, study: str) -> None:
    with database.read_session() as db:
        report = verify.verify_study(db, study_name=study)
    assert report.ok, report.findings


@pytest.mark.e2e
def test_a_participant_walks_the_practice_run_and_a_session(
    browser: Browser,
    live_server: ServerProcess,
    database: Database,
    study_name: str,
    artifacts: Path,
) -> None:
    lab = drive.seat_participant(database, live_server.url, study_name)
    page = browser.new_page(viewport=DESKTOP)
    drive.open_room(page, lab)
    expect(page.locator("#notice")).to_contain_text("A practice run comes first")
    page.screenshot(path=str(artifacts / "01-waiting.png"))

    lab.start_session()  # the familiarisation run
    expect(page.locator("#run-label")).to_have_text("Practice run (not counted)")
    expect(page.locator("#notice")).to_be_hidden()
    asked = drive.run_through(page, drive.PAPER_ORDER)
    assert asked == ["conation", "affection", "cognition"]
    expect(page.locator("#notice")).to_contain_text("Session 1 comes next")

    lab.start_session()  # session 1: three runs, zones in orders the test chooses
    expect(page.locator("#run-label")).to_have_text("Session 1 · run 1 of 3")
    drive.walk(page, drive.TO_CONATION)
    drive.wait_question(page, "conation")
    drive.face(page, 90)  # towards the robot, past the first wall's end
    page.screenshot(path=str(artifacts / "02-question-desktop.png"))
    page.set_viewport_size(TABLET)
    page.screenshot(path=str(artifacts / "03-question-tablet.png"))
    page.set_viewport_size(DESKTOP)
    question = page.evaluate("() => window.trustlabRoom.question.question")
    drive.answer_by_rules(page, "conation", question, how="button")
    for category, waypoints in drive.PAPER_ORDER[1:]:
        drive.walk(page, waypoints)
        drive.answer_by_rules(page, category, drive.wait_question(page, category))
    drive.walk_out(page)
    expect(page.locator("#run-label")).to_have_text("Session 1 · run 1 of 3")
    assert drive.run_through(page, drive.AFFECTION_FIRST) == ["affection", "conation", "cognition"]
    drive.run_through(page, drive.PAPER_ORDER)
    expect(page.locator("#notice")).to_contain_text("Please use the tablet")  # the gate holds
    page.screenshot(path=str(artifacts / "04-session-done.png"))

    steps = _steps(database)
    assert len(steps) == 12  # 3 categories × (1 practice run + 3 runs)
    assert all(count == 1 for *_, count in steps), steps  # every answer stored once
    assert all(zone == category for _, category, zone, _, _ in steps)  # with the zone walked into
    assert {how for *_, how, _ in steps} == {"key", "button"}
    _verified(database, study_name)
