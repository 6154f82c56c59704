"""``trustlab bots --online``: simulated participants come through an online study's public link
to a real server, as people sent by a recruitment platform would."""

from __future__ import annotations

import asyncio
import json
from collections import Counter
from collections.abc import Iterator
from pathlib import Path

import pytest
from sqlalchemy import func, select
from typer.testing import CliRunner

from app.bots import BotConfig
from app.bots_online import OnlineStudyClosed, run_online_bots
from app.cli import cli
from app.db import Database
from app.services.analysis_views import study_data
from app.services.privacy.sites import Scope
from app.services.sessions import verify
from app.services.studies import get_study
from app.tables import Answer, OnlineParticipation, OnlineStatus, Prompt, Role, Submission
from tests.app.test_data_quality import QUALITY, WITH_CHECK
from tests.app.test_online_join import create_online_study
from tests.app.test_online_pages import SHORT
from tests.conftest import PASSWORD, make_user, sqlite_only
from tests.servers import ServerProcess


@pytest.fixture
def server(database: Database, database_url: str, tmp_path: Path) -> Iterator[ServerProcess]:
    make_user(database, "botmaster", Role.ADMIN)
    process = ServerProcess(database_url, tmp_path / "var")
    process.start()
    yield process
    process.stop()


def _config(server: ServerProcess, study: str, participants: int) -> BotConfig:
    return BotConfig(
        url=server.url,
        study=study,
        participants=participants,
        username="botmaster",
        password=PASSWORD,
        concurrency=2,
        noise=0.1,
        seed=3,
    )


@pytest.mark.slow
def test_online_bots_go_from_the_link_to_the_completion_page(
    server: ServerProcess, database: Database
) -> None:
    study = create_online_study(database, extra=QUALITY, **WITH_CHECK, **SHORT)
    kinds: Counter[str] = Counter()
    ticks: list[int] = []
    summary = asyncio.run(
        run_online_bots(
            _config(server, study, 3),
            tick=lambda: ticks.append(1),
            record=lambda kind, _seconds: kinds.update([kind]),
        )
    )
    assert summary.errors == []
    # a practice run and two sessions of one run each (three questions a run), per participant
    assert (summary.participants, summary.completed, summary.sessions) == (3, 3, 9)
    assert summary.steps == len(ticks) == 3 * 9 == kinds["answer"] == kinds["prompt"]
    assert kinds["start"] == 9 and kinds["join"] == 3 and kinds["online"] > 0
    assert kinds["page"] == kinds["form"] - 3 > 0  # each page loaded and submitted; the joins
    with database.read_session() as db:
        statuses = db.scalars(select(OnlineParticipation.status)).all()
        assert sorted(statuses) == [OnlineStatus.COMPLETED] * 3
        # every answer the bots were told of is stored, once
        assert db.scalar(select(func.count()).select_from(Answer)) == summary.steps
        assert db.scalar(select(func.count(func.distinct(Prompt.id)))) == summary.steps
        # each of the 7 questionnaire pages reported its time, as the page's script does
        pages = select(Submission.seconds_on_page).where(Submission.instrument != "consent")
        timed = db.scalars(pages).all()
        assert len(timed) == 3 * 7 and all(seconds is not None for seconds in timed)
        report = verify.verify_study(db, study_name=study)
        dataset = study_data.load_dataset(db, study=get_study(db, study), scope=Scope.every_site())
    assert report.ok, report.findings
    # attentive bots: nobody failed the attention check
    assert dataset.participants["attention_failed"].tolist() == [0, 0, 0]


@pytest.mark.slow
@sqlite_only("the refusal's wording, not the database")
def test_online_bots_refuse_a_lab_study_in_one_line(
    server: ServerProcess, exp3_study: str, database_url: str
) -> None:
    with pytest.raises(OnlineStudyClosed, match="is not run online"):
        asyncio.run(run_online_bots(_config(server, exp3_study, 1)))
    result = CliRunner().invoke(
        cli,
        [
            *("bots", "--online", "--url", server.url, "--study", exp3_study),
            *("--participants", "1", "--username", "botmaster", "--password-stdin", "--json"),
        ],
        input=PASSWORD + "\n",
        env={"TRUSTLAB_DATABASE_URL": database_url},
    )
    assert result.exit_code != 0
    assert f"study '{exp3_study}' is not run online" in result.output
    assert "Traceback" not in result.output
    with pytest.raises(json.JSONDecodeError):
        json.loads(result.stdout or "x")
