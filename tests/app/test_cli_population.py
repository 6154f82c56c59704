"""``trustlab population fit``: from a stored study or a steps CSV, one-line refusals."""

from __future__ import annotations

import json
from pathlib import Path

from analysis.population import read_population
from app.services import studies
from app.services.audit import Actor
from app.tables import StudyStatus
from tests.analysis.test_population_file import _steps
from tests.app.test_cli import run
from tests.conftest import Lab, sqlite_only


@sqlite_only("fitted from a CSV file; the stored study's fit runs on both")
def test_fit_from_a_steps_csv_writes_a_verified_file(database_url: str, tmp_path: Path) -> None:
    csv = tmp_path / "adaptation_steps.csv"
    _steps(30).to_csv(csv, index=False)
    out = tmp_path / "pilot.population.json"
    fit = ("population", "fit", "--steps", str(csv), "--out", str(out), "--replicates", "5")
    code, stdout, _ = run(database_url, *fit)
    assert code == 0, stdout
    assert f"population fitted from {csv}" in stdout
    assert "conation: 30 participants, 270 answers" in stdout and "question 3" in stdout
    population = read_population(out)
    figure = tmp_path / "pilot.population.prior.html"
    html = figure.read_text()
    assert f"figure of the fitted prior: {figure}" in stdout
    assert "Fitted prior over the preferred question" in html and '<script src="http' not in html
    assert html.count('"legendgroup":"prior"') == 2  # one panel per category
    code, stdout, _ = run(database_url, *fit, "--json")
    assert code == 0
    printed = json.loads(stdout)
    assert printed["sha256"] == population.sha256  # same data, same seed: the same file
    assert printed["source"]["steps"] == str(csv)


def test_unusable_input_is_one_line_and_writes_nothing(database_url: str, tmp_path: Path) -> None:
    out = tmp_path / "p.json"
    csv = tmp_path / "steps.csv"
    _steps(30).drop(columns=["answer"]).to_csv(csv, index=False)
    cases = [
        (["--steps", str(csv)], "lacks the column(s) answer"),
        ([], "give either --study NAME"),
        (["--steps", str(tmp_path / "missing.csv")], "cannot read the steps CSV"),
        (["--study", "nope"], "nope"),
    ]
    odd = tmp_path / "odd.csv"
    frame = _steps(30)
    frame.loc[frame.index[0], "answer"] = 2
    frame.to_csv(odd, index=False)
    cases.append((["--steps", str(odd)], "every answer must be 0 (no) or 1 (yes)"))
    small = tmp_path / "small.csv"
    _steps(4).to_csv(small, index=False)
    cases.append((["--steps", str(small)], "4 participant(s) answered here"))
    good = tmp_path / "good.csv"
    _steps(30).to_csv(good, index=False)
    code, _, err = run(
        database_url, "population", "fit", "--steps", str(good), "--out", str(tmp_path)
    )
    assert code == 2 and "is a directory" in err
    for args, message in cases:
        code, _, err = run(database_url, "population", "fit", "--out", str(out), *args)
        assert code in (1, 2) and err.startswith("error: ") and message in err, err
        assert len(err.strip().splitlines()) == 1, err
        assert not out.exists() and not list(tmp_path.glob("*.html"))


def test_fit_from_a_stored_study(lab: Lab, database_url: str, tmp_path: Path) -> None:
    for _ in range(6):
        lab.enrol_and_assign()
        for _session in ("familiarisation", "session 1"):
            lab.start_session()
            lab.run_session(preferred=0)
    out = tmp_path / "rt.population.json"
    fit = ("population", "fit", "--study", lab.study, "--out", str(out), "--replicates", "3")
    code, _, err = run(database_url, *fit)
    assert code == 2 and "rt is still enrolling" in err and "--enrolling-reason" in err, err
    assert not out.exists()
    code, _, err = run(database_url, *fit, "--enrolling-reason", "a pilot fit, for the bench")
    assert code == 0, err
    population = read_population(out)
    source = population.content["source"]
    assert source["studies"] == [lab.study] and source["status_when_fitted"][lab.study] == "open"
    assert source["enrolling_reason"] == "a pilot fit, for the bench"
    conation = population.categories["conation"]
    assert conation["participants"] == 6 and conation["prior"][0] > 0.9  # everyone said yes to 0
    assert conation["slip"] < 0.05
    assert population.prior("conation", 4, source["questions"]["conation"])
    with lab.database.writing() as db:
        studies.set_study_status(
            db, name=lab.study, status=StudyStatus.CLOSED, actor=Actor.system()
        )
    code, _, err = run(database_url, *fit)  # closed: no reason needed, none recorded
    assert code == 0, err
    source = read_population(out).content["source"]
    assert source["status_when_fitted"][lab.study] == "closed" and "enrolling_reason" not in source
