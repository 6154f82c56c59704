"""Fitted analyses are computed once per data version and settings, kept in memory and in the
database, and fitted in the background while the pages say so (issue 49).

The fits are counted, and held back, by a fitter injected into the app's runner
(app.services.analysis_views.fit_runner): no test waits for a time."""

from __future__ import annotations

import json
import threading
from collections import Counter
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient
from sqlalchemy import func, select, update
from typer.testing import CliRunner

import analysis.exports.files
import analysis.mixed_models
import analysis.report
from analysis.dataset import StudyDataset
from app.cli import cli
from app.db import Database
from app.main import create_app
from app.services.analysis_views import fitted, study_data
from app.services.analysis_views.fit_runner import FitRunner, run_fit
from app.services.audit import Actor
from app.services.privacy import erasure
from app.services.privacy.sites import Scope
from app.settings import Settings
from app.tables import FittedAnalysis, Participant, Response, Role, Study
from bench.seed import seed_study
from tests.conftest import UserClientFactory, make_user, sign_in_api

STUDY = "fits"


class CountingFitter:
    """The real fits, counted by kind; ``hold`` makes the fits of one kind wait for ``release``
    (and sets ``entered`` when one has begun)."""

    def __init__(self, hold: str | None = None) -> None:
        self.counts: Counter[str] = Counter()
        self.hold = hold
        self.entered = threading.Event()
        self.release = threading.Event()

    def __call__(
        self, kind: fitted.Kind, dataset: StudyDataset, settings: Mapping[str, Any]
    ) -> bytes:
        self.counts[kind] += 1
        if kind == self.hold:
            self.entered.set()
            assert self.release.wait(60), "the test never released the fit"
        return run_fit(kind, dataset, settings)


def runner_of(
    app: FastAPI,
    fitter: CountingFitter,
    *,
    wait: float = 120.0,
    clock: Callable[[], float] | None = None,
) -> FitRunner:
    """A runner with ``fitter`` in place of the app's (fits in its threads)."""
    options: dict[str, Any] = {} if clock is None else {"clock": clock}
    runner = FitRunner(app.state.database, processes=0, wait=wait, fitter=fitter, **options)
    app.state.analysis_fits = runner
    return runner


@pytest.fixture
def seeded(database: Database) -> str:
    seed_study(database, name=STUDY, participants=24, seed=3)
    return STUDY


def stored_rows(database: Database) -> int:
    with database.read_session() as db:
        return int(db.scalar(select(func.count()).select_from(FittedAnalysis)) or 0)


def test_a_second_request_with_the_same_data_does_not_refit(
    seeded: str, app: FastAPI, user_client: UserClientFactory, database: Database
) -> None:
    fitter = CountingFitter()
    runner_of(app, fitter)
    analyst = user_client(Role.ANALYST)
    first = analyst.get(f"/studies/{seeded}/analysis")
    assert first.status_code == 200
    assert "24 participants analysed" in first.text
    assert fitter.counts == {"study": 1, "pilot": 1}
    again = analyst.get(f"/studies/{seeded}/analysis")
    power = analyst.get(f"/studies/{seeded}/analysis/power")
    assert fitter.counts == {"study": 1, "pilot": 1}  # both pages from the kept fits
    assert again.text.count('class="card outcome"') == first.text.count('class="card outcome"') == 5
    assert "own data: 24 complete participants" in power.text
    # Other settings are another result: type II sums of squares are fitted once more.
    assert "type 2 sums of squares" in analyst.get(f"/studies/{seeded}/analysis?ss=2").text
    assert fitter.counts == {"study": 2, "pilot": 1}
    assert stored_rows(database) == 3


def test_an_answer_after_a_cached_fit_changes_the_page(
    seeded: str, app: FastAPI, user_client: UserClientFactory, database: Database
) -> None:
    fitter = CountingFitter()
    runner_of(app, fitter)
    analyst = user_client(Role.ANALYST)
    before = analyst.get(f"/studies/{seeded}/analysis").text
    assert "24 participants analysed" in before
    with database.writing() as db:  # one participant answers every trust item with a 1
        first = db.scalar(select(Participant.id).order_by(Participant.id).limit(1))
        db.execute(
            update(Response)
            .where(Response.participant_id == first, Response.instrument == "trust")
            .values(value="1")
        )
        db.commit()
    after = analyst.get(f"/studies/{seeded}/analysis").text
    assert fitter.counts == {"study": 2, "pilot": 2}
    assert after != before
    # And an exclusion: a participant who withdrew leaves the analysis.
    with database.writing() as db:
        db.execute(update(Participant).where(Participant.id == first).values(status="withdrawn"))
        db.commit()
    excluded = analyst.get(f"/studies/{seeded}/analysis").text
    assert "23 participants analysed" in excluded
    assert fitter.counts == {"study": 3, "pilot": 3}


def test_a_slow_fit_never_delays_another_request(
    seeded: str, app: FastAPI, user_client: UserClientFactory
) -> None:
    """The mixed models' fit is held: the page says "fitting… started N s ago" at once (again on
    the next poll, with the same single fit), every other page answers meanwhile, and the
    result swaps in once the fit is done."""
    now = [100.0]
    fitter = CountingFitter(hold="mixed")
    runner = runner_of(app, fitter, wait=0.0, clock=lambda: now[0])
    analyst = user_client(Role.ANALYST)
    url = f"/studies/{seeded}/analysis/mixed?measure=trust_2"
    pages: dict[str, Any] = {}

    def ask(name: str) -> None:
        pages[name] = analyst.get(url, headers={"HX-Request": "true"})

    # The study's ANOVA (which the mixed page reads first) is fitted and kept beforehand.
    assert analyst.get(f"/studies/{seeded}/analysis").status_code == 200
    runner.settle(60)
    first = threading.Thread(target=ask, args=("first",))
    first.start()
    assert fitter.entered.wait(60), pages
    first.join(60)  # an upper bound: with the fit held, it ends only if the page did not wait
    assert not first.is_alive(), "the page waited for the fit"
    assert fitter.release.is_set() is False
    page = pages["first"]
    assert page.status_code == 200
    assert 'id="mixed-models"' in page.text and 'aria-busy="true"' in page.text
    assert "Fitting the mixed models of trust_2… started just now." in page.text
    assert f'hx-get="{url}" hx-trigger="load delay:1s" hx-target="#mixed-models"' in page.text
    now[0] += 7
    polled = analyst.get(url, headers={"HX-Request": "true"})
    assert "Fitting the mixed models of trust_2… started 7 s ago." in polled.text
    other = analyst.get(f"/studies/{seeded}/analysis/power")  # another page, meanwhile
    assert other.status_code == 200 and "Plan the next study" in other.text
    assert fitter.counts["mixed"] == 1  # the poll joined the running fit
    fitter.release.set()
    runner.settle(60)
    done = analyst.get(url, headers={"HX-Request": "true"})
    assert "Fitting the mixed models" not in done.text and 'aria-busy="false"' in done.text
    assert "Type III F tests (Satterthwaite df)" in done.text
    assert '<option value="trust_2" selected>' in done.text
    assert fitter.counts["mixed"] == 1


def test_the_stored_fit_serves_a_new_app(
    seeded: str,
    app: FastAPI,
    user_client: UserClientFactory,
    settings: Settings,
    database: Database,
) -> None:
    """A restart (or another worker): the results come from the database, fitted by nobody."""
    runner_of(app, CountingFitter())
    analyst = user_client(Role.ANALYST)
    url = f"/studies/{seeded}/analysis/mixed?measure=trust_1"
    htmx = {"HX-Request": "true"}
    before = analyst.get(url, headers=htmx).text
    assert "Type III F tests (Satterthwaite df)" in before
    restarted = create_app(settings)
    fitter = CountingFitter()
    runner = runner_of(restarted, fitter)
    with TestClient(restarted) as other:
        make_user(database, "second", Role.ANALYST)
        sign_in_api(other, "second")
        after = other.get(url, headers=htmx).text
    assert fitter.counts == {}
    assert runner.cache.loaded == 2  # the ANOVAs and the measure's mixed models
    assert after == before


def test_erasure_removes_the_fits_that_include_the_participant(
    seeded: str, app: FastAPI, user_client: UserClientFactory, database: Database
) -> None:
    fitter = CountingFitter()
    runner_of(app, fitter)
    analyst = user_client(Role.ANALYST)
    assert "24 participants analysed" in analyst.get(f"/studies/{seeded}/analysis").text
    assert stored_rows(database) == 2
    with database.writing() as db:
        erasure.erase_participant(
            db, study_name=seeded, code="P0001", actor=Actor.system("tests"), secret=b"k" * 32
        )
    assert stored_rows(database) == 0
    # The copy in this process's memory went with its row: the page is fitted again.
    assert "23 participants analysed" in analyst.get(f"/studies/{seeded}/analysis").text
    assert fitter.counts == {"study": 2, "pilot": 2}


def test_a_result_fitted_before_an_erasure_is_not_stored(
    seeded: str, app: FastAPI, database: Database
) -> None:
    """The fit read the participant's data; the erasure committed while it ran."""
    fitter = CountingFitter(hold="study")
    runner = runner_of(app, fitter, wait=0.0)
    with database.read_session() as db:
        study = db.scalars(select(Study).where(Study.name == seeded)).one()
        dataset = study_data.load_dataset(db, study=study, scope=Scope.every_site())
        runner.for_study(db, study_id=study.id, dataset=dataset).start("study")
    assert fitter.entered.wait(60)
    with database.writing() as writer:  # no snapshot left open: the erasure empties the WAL
        erasure.erase_participant(
            writer, study_name=seeded, code="P0002", actor=Actor.system("tests"), secret=b"k" * 32
        )
    fitter.release.set()
    with database.read_session() as db:  # the request that asked, waiting for its result
        result = runner.for_study(db, study_id=study.id, dataset=dataset).result("study")
    assert len(result.participants) == 24  # the request that asked gets what it asked for
    assert stored_rows(database) == 0


def test_fits_run_in_worker_processes(seeded: str, database: Database) -> None:
    """The default runner: the result comes back from another process (patsy's design
    descriptions left out), and is stored."""
    runner = FitRunner(database, processes=1, wait=0.0)
    try:
        with database.read_session() as db:
            study = db.scalars(select(Study).where(Study.name == seeded)).one()
            dataset = study_data.load_dataset(db, study=study, scope=Scope.every_site())
            fits = runner.for_study(db, study_id=study.id, dataset=dataset)
            models = fits.result("mixed", measure="trust_1", slope=False)
    finally:
        runner.close()
    (fit,) = models.outcomes[0].lmm.models
    assert fit.converged and fit.design_info is None and len(fit.tests) == 3
    assert stored_rows(database) == 1


# ------------------------------------------------------------------ exports from the command line


def count_mixed_fits(monkeypatch: pytest.MonkeyPatch) -> list[object]:
    """Every fit of mixed models from now on, by whatever path (a page's fit, an export's own,
    the report's), each recorded as it starts: the function counted wherever it is named."""
    calls: list[object] = []
    original = analysis.mixed_models.analyse_mixed_models

    def counting(*args: Any, **kwargs: Any) -> Any:
        calls.append(kwargs.get("keys"))
        return original(*args, **kwargs)

    for module in (analysis.mixed_models, analysis.report, fitted, analysis.exports.files):
        monkeypatch.setattr(module, "analyse_mixed_models", counting, raising=False)
    return calls


def export_from_the_command_line(database_url: str, study: str, kind: str, out: Path) -> None:
    env = {"TRUSTLAB_DATABASE_URL": database_url, "TRUSTLAB_VAR_DIR": str(out.parent / "var")}
    args = ["export", "--study", study, "--format", kind, "--out", str(out)]
    result = CliRunner().invoke(cli, args, env=env)
    assert result.exit_code == 0, result.output


def test_an_export_after_the_page_fits_nothing_again(
    seeded: str,
    app: FastAPI,
    user_client: UserClientFactory,
    database_url: str,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The report downloaded from the page fits each measure's mixed models once; the report and
    mixed_models.json exported from the command line after it take them from the database."""
    runner_of(app, CountingFitter())
    calls = count_mixed_fits(monkeypatch)
    analyst = user_client(Role.ANALYST)
    assert analyst.get(f"/studies/{seeded}/exports/html").status_code == 200
    measures = len(calls)
    assert measures == 5  # trust_1 … trust_5, each once
    export_from_the_command_line(database_url, seeded, "html", tmp_path / "report.html")
    export_from_the_command_line(database_url, seeded, "mixed-json", tmp_path / "mixed.json")
    assert len(calls) == measures
    exported = json.loads((tmp_path / "mixed.json").read_text(encoding="utf-8"))
    downloaded = analyst.get(f"/studies/{seeded}/exports/mixed-json").json()
    assert exported.pop("manifest")["data_sha256"] == downloaded.pop("manifest")["data_sha256"]
    assert exported == downloaded
    assert len(calls) == measures


def test_what_the_command_line_fits_is_kept_for_the_pages(
    seeded: str,
    app: FastAPI,
    user_client: UserClientFactory,
    database: Database,
    database_url: str,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    calls = count_mixed_fits(monkeypatch)
    export_from_the_command_line(database_url, seeded, "mixed-json", tmp_path / "mixed.json")
    assert len(calls) == 5
    assert stored_rows(database) == 1 + 5  # the ANOVAs and each measure's mixed models
    fitter = CountingFitter()
    runner_of(app, fitter)
    assert user_client(Role.ANALYST).get(f"/studies/{seeded}/exports/html").status_code == 200
    assert not fitter.counts and len(calls) == 5
    export_from_the_command_line(database_url, seeded, "html", tmp_path / "report.html")
    assert len(calls) == 5 and stored_rows(database) == 1 + 5
