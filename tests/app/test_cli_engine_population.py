"""`pretrain --population` and `simulate adaptation --population` (issue 20)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import typer

from analysis.population import Population, read_population, write_population
from app.cli.engine import EXIT_BAD_INPUT
from app.services.sessions.population_fit import fit_population
from models.checkpoints import load_checkpoint
from models.learners.meta_policy import MetaPolicyLearner
from tests.analysis.test_population_file import _steps
from tests.app.test_cli_engine import checkpoints, cli, one_json, run

__all__ = ["checkpoints", "cli"]  # fixtures used by name below

TINY = ("--meta-batches", "1", "--horizon", "3", "--tasks-per-batch", "4")
TINY += ("--validate-every", "1", "--json")


@pytest.fixture
def population_file(tmp_path: Path) -> Path:
    """Thirty pilot participants: conation (K = 4) and cognition (K = 3), most preferring
    question 0, slipping 5 % of the time."""
    path = tmp_path / "pilot.population.json"
    write_population(path, fit_population(_steps(30), {"steps": "pilot.csv"}, replicates=5))
    return path


def test_pretrain_for_a_population_records_it_and_starts_at_its_prior(
    cli: typer.Typer, population_file: Path, tmp_path: Path
) -> None:
    population = read_population(population_file)
    result = run(
        cli,
        "pretrain",
        *TINY,
        "--category",
        "conation",
        "--population",
        str(population_file),
        "--out",
        str(tmp_path / "set"),
    )
    (entry,) = one_json(result)["checkpoints"]
    checkpoint = load_checkpoint(Path(entry["path"]), expected_arms=4)
    recorded = checkpoint.config["population"]
    assert recorded["sha256"] == population.sha256 and recorded["category"] == "conation"
    assert recorded["source"]["steps"] == "pilot.csv" and recorded["participants"] == 30
    expected = population.training_prior("conation", 4)
    assert checkpoint.config["preferred_prior"] == pytest.approx(expected, rel=1e-12)
    start = MetaPolicyLearner(checkpoint).probabilities()
    np.testing.assert_allclose(start, expected, rtol=1e-12)
    assert start[0] > 0.5 and min(start) > 0  # the pilot's favourite, every question possible
    # The pilot changed no minds; the shipped protocol's model assumes a hazard of .02.
    assert "warning: conation: the protocol's hazard 0.02 is outside the fitted" in result.stderr


def test_the_training_prior_is_smoothed_by_the_pilots_size() -> None:
    small = fit_population(_steps(6), {"steps": "a"}, replicates=2)
    large = fit_population(_steps(60), {"steps": "b"}, replicates=2)
    for population, n in ((small, 6), (large, 60)):
        shares = np.asarray(population.prior("conation", 4))
        smoothed = np.asarray(population.training_prior("conation", 4))
        np.testing.assert_allclose(smoothed, (shares * n + 1) / (n + 4))
        assert smoothed.sum() == pytest.approx(1.0) and smoothed.min() > 0
    assert _pull_to_uniform(small) > _pull_to_uniform(large)


def _pull_to_uniform(population: Population) -> float:
    shares = np.asarray(population.prior("conation", 4))
    return float(np.abs(shares - population.training_prior("conation", 4)).sum())


def test_pretrain_population_refusals_are_one_line_and_write_nothing(
    cli: typer.Typer, population_file: Path, tmp_path: Path
) -> None:
    edited = tmp_path / "edited.population.json"
    data = json.loads(population_file.read_text())
    data["content"]["categories"]["conation"]["slip"] = 0.3
    edited.write_text(json.dumps(data))
    asked_otherwise = tmp_path / "other.population.json"
    source = {"studies": ["pilot"], "questions": {"conation": ["a", "b", "c", "d"]}}
    write_population(asked_otherwise, fit_population(_steps(30), source, replicates=2))
    cases = [
        (["--category", "conation", "--preferred-prior", "1,1,1,1"], population_file, "exclude"),
        (["--category", "generic"], population_file, "not generic"),
        (["--category", "conation", "--arms", "3"], population_file, "the questions differ"),
        (["--category", "affection"], population_file, "no category 'affection'"),
        (["--category", "conation"], edited, "does not match its recorded hash"),
        (["--category", "conation"], asked_otherwise, "asks other questions"),
        (["--category", "conation", "--paper-feedback"], population_file, "yes/no feedback"),
    ]
    out = tmp_path / "set"
    for args, path, message in cases:
        result = run(cli, "pretrain", *TINY, *args, "--population", str(path), "--out", str(out))
        assert result.exit_code == EXIT_BAD_INPUT, (args, result.stdout)
        assert result.stderr.startswith("error: ") and message in result.stderr, result.stderr
        assert len(result.stderr.strip().splitlines()) == 1
        assert not out.exists()


def test_simulate_participants_drawn_from_a_population(
    cli: typer.Typer, population_file: Path, checkpoints: Path
) -> None:
    population = read_population(population_file)
    common = ("simulate", "adaptation", "--population", str(population_file))
    common += ("--checkpoint-dir", str(checkpoints), "--iterations", "3", "--json")
    out = one_json(run(cli, *common, "--category", "conation", "--participants", "4000"))
    fitted = population.categories["conation"]
    assert out["arms"] == 4 and f"slip {fitted['slip']:g}" in out["participants_answer"]
    # Before any answer the exact reference's probability of the preferred question is the
    # prior's, averaged over participants drawn by it: the sum of the squared shares.
    prior = np.asarray(fitted["prior"])
    assert out["learners"]["bayes"]["p_correct"][0] == pytest.approx((prior**2).sum(), abs=0.03)
    assert (prior**2).sum() > 0.4  # far from uniform's .25: the population is in play
    cognition = one_json(run(cli, *common, "--category", "cognition", "--arms", "3"))
    assert cognition["arms"] == 3
    for extra, message in (
        (["--category", "conation", "--slip", "0.1"], "only with --preferred-prior"),
        ([], "name one (--category)"),
        (["--category", "conation", "--arms", "3"], "the questions differ"),
    ):
        result = run(cli, *common, *extra)
        assert result.exit_code == EXIT_BAD_INPUT and message in result.stderr, result.stderr


def test_pretrain_all_trains_every_category_of_the_population(
    cli: typer.Typer, tmp_path: Path
) -> None:
    path = tmp_path / "two.population.json"
    steps = _steps(30, categories=(("conation", 4), ("affection", 4)))
    write_population(path, fit_population(steps, {"steps": "two.csv"}, replicates=2))
    out = tmp_path / "set"
    result = run(
        cli, "pretrain", *TINY, "--category", "all", "--population", str(path), "--out", str(out)
    )
    written = [Path(entry["path"]).name for entry in one_json(result)["checkpoints"]]
    assert written == ["affection-k4", "conation-k4"]  # the population's categories, not all three
    recorded = load_checkpoint(out / "affection-k4", 4).config["population"]
    assert recorded["questions"][0].startswith("Be careful with the walls")  # the protocol's
    three = tmp_path / "three.population.json"
    write_population(three, fit_population(_steps(30), {"steps": "x.csv"}, replicates=2))
    refused = run(
        cli,
        "pretrain",
        *TINY,
        "--category",
        "all",
        "--population",
        str(three),
        "--out",
        str(tmp_path / "no"),
    )
    assert refused.exit_code == EXIT_BAD_INPUT
    assert "'cognition' has 4 questions in the shipped protocol, 3 where" in refused.stderr
    assert len(refused.stderr.strip().splitlines()) == 1 and not (tmp_path / "no").exists()
