"""`simulate adaptation --population` with a declared true population (issue 36, item 4).

C2 here is a small checkpoint anchored at the fitted population's training prior and recording
that population, as `trustlab pretrain --population` writes one: before any answer its
probability of a participant's preferred question is the anchor's, averaged over the participants
drawn, so where they are drawn from shows in the first figure exactly (up to sampling).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import typer

from analysis.population import Population, read_population, write_population
from app.cli.engine import EXIT_BAD_INPUT
from tests.app.test_cli_engine import checkpoints, cli, one_json, run
from tests.app.test_cli_engine_population import population_file
from tests.models.conftest import make_checkpoint

__all__ = ["checkpoints", "cli", "population_file"]  # fixtures used by name below

PARTICIPANTS = ("--participants", "300", "--seed", "3")
CAUTION = "warning: the participants are drawn from the fitted population"


@pytest.fixture
def trained(population_file: Path, tmp_path: Path) -> Path:
    """A conation K = 4 checkpoint meta-trained (in miniature) for the fitted population."""
    population = read_population(population_file)
    directory = tmp_path / "pilot" / "conation-k4"
    make_checkpoint(
        directory,
        prior=population.training_prior("conation", 4),
        config={"population": population.record("conation")},
    )
    return directory


def _population(path: Path, prior: list[float], *, arms: int = 4, name: str = "conation") -> Path:
    """A population file written by hand (hashed as a fit's): one category with this prior."""
    figures: dict[str, Any] = {
        "arms": arms,
        "participants": 40,
        "prior": prior,
        "prior_ci": [[max(v - 0.1, 0.0), min(v + 0.1, 1.0)] for v in prior],
        "slip": 0.05,
        "slip_ci": [0.03, 0.07],
        "hazard": 0.02,
        "hazard_ci": [0.0, 0.05],
    }
    content = {"source": {"steps": "held-out.csv"}, "categories": {name: figures}}
    write_population(path, Population.of(content))
    return path


def _simulate(cli: typer.Typer, *args: str) -> Any:
    return run(cli, "simulate", "adaptation", "--category", "conation", *PARTICIPANTS, *args)


def _first(out: dict[str, Any], learner: str) -> float:
    return float(out["learners"][learner]["p_correct"][0])


def test_participants_come_from_the_population_the_lab_declares(
    cli: typer.Typer, population_file: Path, trained: Path, tmp_path: Path
) -> None:
    fitted = read_population(population_file)
    anchor = np.asarray(fitted.training_prior("conation", 4))
    common = ("--population", str(population_file), "--checkpoint", str(trained), "--json")

    optimistic = _simulate(cli, *common)
    out = one_json(optimistic)
    drawn = out["population"]["participants"]
    assert drawn["drawn_from"] == "fitted" and drawn["declared_by"] is None
    assert drawn["sha256"] == fitted.sha256 and out["population"]["c2_trained_for_fitted"]
    assert (
        drawn["prior_from"] == "shares" and drawn["prior"] == fitted.categories["conation"]["prior"]
    )
    summary = out["population"]["summary"]
    assert f"drawn from the fitted population {population_file}" in summary
    assert "the one C2 was trained for" in summary and summary.endswith("optimistic")
    prior = np.asarray(fitted.prior("conation", 4))
    assert _first(out, "meta") == pytest.approx(float(prior @ anchor), abs=0.03)
    assert CAUTION in optimistic.stderr

    # By hand: the lab believes every question equally likely (slip and hazard as fitted).
    by_hand = _simulate(cli, *common, "--preferred-prior", "1,1,1,1")
    declared = one_json(by_hand)
    drawn = declared["population"]["participants"]
    assert (drawn["drawn_from"], drawn["declared_by"]) == ("declared", "--preferred-prior")
    assert drawn["prior"] == [0.25] * 4 and drawn["file"] is None
    assert (drawn["slip_from"], drawn["hazard_from"]) == ("fitted", "fitted")
    assert drawn["slip"] == pytest.approx(fitted.categories["conation"]["slip"])
    assert declared["population"]["summary"].startswith(
        "participants: drawn from the declared true population: prior 0.25/0.25/0.25/0.25"
    )
    assert CAUTION not in by_hand.stderr
    # C2 starts where it was trained, and the declared participants are not the fitted ones:
    # its first belief in their preferred question falls to the uniform .25, as the exact
    # reference's does (which knows the declared truth).
    assert _first(declared, "meta") == pytest.approx(0.25, abs=0.03)
    assert _first(declared, "bayes") == pytest.approx(0.25, abs=1e-9)
    assert _first(out, "meta") > 0.4 and _first(out, "bayes") > 0.4
    # A flatter truth makes every learner slower, the reference included.
    for learner in ("meta", "bayes"):
        slower = declared["learners"][learner]["iterations_to_95"]
        assert slower > out["learners"][learner]["iterations_to_95"], learner

    # A file: held-out participants who mostly prefer question 1, not the pilot's question 0.
    held_out = _population(tmp_path / "held-out.population.json", [0.1, 0.7, 0.1, 0.1])
    truth = one_json(_simulate(cli, *common, "--true-population", str(held_out)))
    drawn = truth["population"]["participants"]
    assert (drawn["drawn_from"], drawn["declared_by"]) == ("declared", "--true-population")
    assert drawn["file"] == str(held_out) and drawn["sha256"] == read_population(held_out).sha256
    assert (drawn["slip"], drawn["hazard"]) == (0.05, 0.02)
    # A new participant's predictive prior given the file's 40: the shares smoothed.
    smoothed = (np.asarray([0.1, 0.7, 0.1, 0.1]) * 40 + 1) / 44
    assert drawn["prior_from"] == "smoothed shares"
    np.testing.assert_allclose(drawn["prior"], smoothed)
    assert truth["population"]["fitted"]["sha256"] == fitted.sha256
    assert f"drawn from the declared true population {held_out}" in truth["population"]["summary"]
    expected = float(smoothed @ anchor)
    assert _first(truth, "meta") == pytest.approx(expected, abs=0.03)
    assert _first(truth, "meta") < _first(out, "meta") - 0.2


def test_the_table_and_the_figure_say_where_the_participants_came_from(
    cli: typer.Typer, population_file: Path, checkpoints: Path, tmp_path: Path
) -> None:
    common = ("--population", str(population_file), "--checkpoint-dir", str(checkpoints))
    table = _simulate(cli, *common, "--iterations", "4")
    assert table.exit_code == 0, table.stderr
    lines = table.stdout.splitlines()
    assert f"participants: drawn from the fitted population {population_file}" in lines[2]
    assert lines[2].endswith("not one declared true: optimistic")
    # The fixture's set records no population: the table says C2 was not trained for it.
    assert lines[3].startswith("C2: trained on its own prior, not for the fitted population")
    (warning,) = table.stderr.strip().splitlines()  # the caution is one line
    assert warning.startswith(CAUTION) and "--true-population FILE" in warning
    assert "--preferred-prior P1,P2,…" in warning

    # The same file declared true is still the fitted population: optimistic, and said so.
    same = _simulate(cli, *common, "--true-population", str(population_file), "--json")
    assert one_json(same)["population"]["participants"]["drawn_from"] == "fitted"
    assert CAUTION in same.stderr

    out = tmp_path / "figures"
    held_out = _population(tmp_path / "held-out.population.json", [0.4, 0.2, 0.2, 0.2])
    written = _simulate(
        cli, *common, "--true-population", str(held_out), "--iterations", "4", "--out", str(out)
    )
    assert written.exit_code == 0, written.stderr
    assert f"drawn from the declared true population {held_out}" in written.stdout
    html = (out / "simulation.html").read_text()  # plotly writes "/" as \u002f in its JSON
    assert f"drawn from the declared true population {held_out}" in html.replace("\\u002f", "/")


def test_contradictory_declarations_are_refused_in_one_line(
    cli: typer.Typer, population_file: Path, trained: Path, tmp_path: Path
) -> None:
    held_out = _population(tmp_path / "held.population.json", [0.1, 0.7, 0.1, 0.1])
    other_k = _population(tmp_path / "k3.population.json", [0.5, 0.3, 0.2], arms=3)
    other_name = _population(tmp_path / "aff.population.json", [0.7, 0.1, 0.1, 0.1], name="x")
    retrained = tmp_path / "other" / "conation-k4"
    make_checkpoint(retrained, config={"population": {"sha256": "f" * 64, "category": "x"}})
    fitted = ("--population", str(population_file))
    truth = ("--true-population", str(held_out))
    cases = [
        ((*fitted, *truth, "--preferred-prior", "1,1,1,1"), "give one declaration"),
        ((*fitted, *truth, "--hazard", "0.1"), "so does --hazard"),
        ((*fitted, "--slip", "0.1"), "--slip with --population declares the true participants"),
        ((*fitted, "--feedback", "gaussian"), "participants answer yes/no"),
        ((*fitted, "--acceptable", "2"), "prefer one question"),
        (truth, "name that one with --population FILE"),
        ((*fitted, "--true-population", str(other_k)), "the questions differ"),
        ((*fitted, "--true-population", str(other_name)), "has no category 'conation'"),
        ((*fitted, "--preferred-prior", "1,-1,1,1"), "--preferred-prior: preferred prior"),
        ((*fitted, "--checkpoint", str(retrained)), "was trained for population ffffffffffff"),
    ]
    for args, message in cases:
        own = () if "--checkpoint" in args else ("--checkpoint", str(trained))
        result = _simulate(cli, *args, *own, "--json")
        assert result.exit_code == EXIT_BAD_INPUT, (args, result.stdout)
        assert result.stdout == "" and result.stderr.startswith("error: "), args
        assert message in result.stderr, (args, result.stderr)
        assert len(result.stderr.strip().splitlines()) == 1, result.stderr
    # --feedback binary is what a population's participants give anyway: accepted.
    accepted = _simulate(cli, *fitted, "--feedback", "binary", "--checkpoint", str(trained))
    assert accepted.exit_code == 0, accepted.stderr
