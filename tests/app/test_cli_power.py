"""``trustlab power``: the three questions, the JSON contract and one-line errors."""

from __future__ import annotations

import json
from pathlib import Path

import pandas as pd
import pytest
import typer
from typer.testing import CliRunner, Result

from analysis.power_pilot import estimate_pilot
from analysis.study import analyse_study
from app.cli.analysis import EXIT_BAD_INPUT
from app.cli.power import register
from app.db import Database
from app.services import studies
from app.services.analysis_views import study_data
from app.services.privacy.sites import Scope
from bench.seed import seed_study
from tests.conftest import sqlite_only

PAPER = ["--groups", "2", "--sessions", "4"]


@pytest.fixture(scope="module")
def cli() -> typer.Typer:
    app = typer.Typer()

    @app.callback()
    def main() -> None:
        """Stand-in for the trustlab app, which has many commands."""

    register(app)
    return app


def run(cli: typer.Typer, *args: str) -> Result:
    return CliRunner().invoke(cli, ["power", *args])


def test_power_for_n_as_json_carries_outputs_and_inputs(cli: typer.Typer) -> None:
    # The seed paper's interaction, F(3, 66) = 5.629, partial η² = .204, read "as in SPSS".
    result = run(
        cli,
        "--effect",
        "interaction",
        *PAPER,
        "--eta2",
        ".204",
        "--convention",
        "spss",
        "--n",
        "24",
        "--json",
    )
    assert result.exit_code == 0, result.stderr
    payload = json.loads(result.stdout)
    assert payload["question"] == "power"
    assert payload["n_total"] == 24
    assert (payload["df1"], payload["df2"]) == (3, 66)
    assert payload["lambda"] == pytest.approx(16.915, abs=1e-3)
    assert payload["power"] == pytest.approx(0.933, abs=1e-3)
    assert payload["design"]["convention"] == "spss" and payload["design"]["rho_used"] is False


def test_sample_size_and_detectable_effect(cli: typer.Typer) -> None:
    found = run(
        cli,
        "--effect",
        "between",
        *PAPER,
        "--f",
        "0.5",
        "--rho",
        "0.6",
        "--target-power",
        "0.8",
        "--json",
    )
    payload = json.loads(found.stdout)
    assert payload["question"] == "sample size" and payload["n_total"] % 2 == 0
    assert payload["power"] >= 0.8 and payload["target_power"] == 0.8
    smallest = run(
        cli, "--effect", "between", *PAPER, "--rho", "0.6", "--n", "24", "--target-power", "0.8"
    )
    assert smallest.exit_code == 0, smallest.stderr
    assert smallest.stdout.startswith("With N = 24, the smallest between-groups effect")
    assert "power        0.8000" in smallest.stdout


def test_a_means_table_sets_the_design_and_f(cli: typer.Typer) -> None:
    result = run(
        cli,
        "--effect",
        "within",
        "--means",
        "1,2,3;1,2,3",
        "--sd",
        "2",
        "--rho",
        "0.5",
        "--n",
        "20",
        "--json",
    )
    payload = json.loads(result.stdout)
    assert (payload["design"]["groups"], payload["design"]["sessions"]) == (2, 3)
    assert payload["f"] == pytest.approx((2 / 3) ** 0.5 / 2)


@pytest.mark.parametrize(
    ("args", "words"),
    [
        (["--effect", "within", *PAPER, "--f", "0.2", "--rho", "1.2", "--n", "24"], "rho"),
        (
            [
                "--effect",
                "within",
                *PAPER,
                "--f",
                "0.2",
                "--rho",
                ".5",
                "--epsilon",
                "0.2",
                "--n",
                "24",
            ],
            "epsilon",
        ),
        (["--effect", "within", *PAPER, "--f", "-0.2", "--rho", ".5", "--n", "24"], "f must"),
        (
            ["--effect", "within", *PAPER, "--f", "0.2", "--rho", ".5", "--target-power", "1.5"],
            "target power",
        ),
        (["--effect", "sideways", *PAPER, "--f", "0.2", "--rho", ".5", "--n", "24"], "--effect"),
        (["--effect", "within", *PAPER, "--f", "0.2", "--eta2", ".1", "--n", "24"], "one effect"),
        (["--effect", "within", *PAPER, "--f", "0.2", "--rho", ".5"], "exactly one"),
        (["--effect", "within", "--f", "0.2", "--rho", ".5", "--n", "24"], "--groups"),
        (["--effect", "within", "--means", "1,2;3", "--sd", "1", "--n", "9"], "every group"),
    ],
)
def test_bad_input_is_one_line_without_a_traceback(
    cli: typer.Typer, args: list[str], words: str
) -> None:
    result = run(cli, *args)
    assert result.exit_code == EXIT_BAD_INPUT
    assert result.stderr.startswith("error: ") and words in result.stderr
    assert result.stderr.count("\n") == 1 and "Traceback" not in result.stderr


DROPOUTS = Path(__file__).parents[1] / "analysis" / "data" / "mixed_2x4_dropouts.csv"
PILOT = ["--pilot", str(DROPOUTS), "--dv", "trust", "--replicates", "50", "--seed", "7"]


def test_a_pilot_csv_gives_rho_epsilon_and_f_with_intervals(cli: typer.Typer) -> None:
    result = run(cli, "--effect", "interaction", *PILOT, "--n", "40", "--json")
    assert result.exit_code == 0, result.stderr
    payload = json.loads(result.stdout)
    pilot = payload["pilot"]
    assert pilot["n_per_group"] == [9, 13] and pilot["excluded_incomplete"] == 3
    estimates = pilot["estimates"]
    design = payload["design"]
    assert design["rho"] == estimates["rho"]["estimate"]
    assert design["epsilon"] == estimates["epsilon"]["estimate"]
    assert payload["f"] == estimates["f_interaction"]["estimate"]
    assert estimates["rho"]["ci_low"] < estimates["rho"]["estimate"] < estimates["rho"]["ci_high"]
    low, high = payload["pilot_range"]["f_ci_low"], payload["pilot_range"]["f_ci_high"]
    assert low["power"] < payload["power"] < high["power"]
    again = run(cli, "--effect", "interaction", *PILOT, "--n", "40", "--json")
    assert json.loads(again.stdout) == payload  # the seed repeats the intervals


def test_given_values_override_the_pilots(cli: typer.Typer) -> None:
    result = run(
        cli,
        "--effect",
        "within",
        *PILOT,
        "--rho",
        "0.3",
        "--epsilon",
        "1",
        "--f",
        "0.2",
        "--n",
        "30",
        "--json",
    )
    design = json.loads(result.stdout)["design"]
    assert (design["rho"], design["epsilon"]) == (0.3, 1.0)
    text = run(cli, "--effect", "within", *PILOT, "--n", "30")
    assert text.stdout.startswith("Pilot ") and "epsilon (Greenhouse-Geisser)" in text.stdout


def test_a_pilot_too_small_is_refused_in_one_line(cli: typer.Typer, tmp_path: Path) -> None:
    data = pd.read_csv(DROPOUTS)
    keep = data["participant"].isin(data["participant"].unique()[:14])
    small = tmp_path / "small.csv"
    data[keep].to_csv(small, index=False)
    result = run(cli, "--effect", "within", "--pilot", str(small), "--dv", "trust", "--n", "20")
    assert result.exit_code == EXIT_BAD_INPUT
    assert "4 or more participants" in result.stderr and result.stderr.count("\n") == 1
    missing = run(cli, "--effect", "within", "--pilot", str(small), "--n", "20")
    assert "needs --dv" in missing.stderr


def test_simulate_adds_the_mixed_models_power_and_a_curve(cli: typer.Typer, tmp_path: Path) -> None:
    curve = tmp_path / "curve.html"
    args = ["--effect", "between", *PAPER, "--f", "0.4", "--rho", "0.5", "--n", "12"]
    result = run(cli, *args, "--simulate", "6", "--seed", "9", "--curve", str(curve), "--json")
    assert result.exit_code == 0, result.stderr
    payload = json.loads(result.stdout)
    simulation = payload["simulation"]
    assert simulation["n_total"] == 12 and simulation["replicates"] == 6
    assert simulation["ci_low"] <= simulation["power"] <= simulation["ci_high"]
    assert [point["n_total"] for point in payload["curve"]] == sorted(
        point["n_total"] for point in payload["curve"]
    )
    assert "datasets" in result.stderr  # the progress bar
    assert "plotly" in curve.read_text()[:200_000].lower()
    again = run(cli, *args, "--simulate", "6", "--seed", "9", "--json")
    assert json.loads(again.stdout)["simulation"] == simulation
    assert payload["simulated_model"]["kind"] == simulation["kind"] == "lmm"


def test_simulate_the_ordinal_model_of_one_item(cli: typer.Typer) -> None:
    args = ["--effect", "between", *PAPER, "--f", "0.4", "--rho", "0.5", "--n", "12"]
    ordinal = ["--simulate", "4", "--seed", "9", "--model", "ordinal", "--categories", "4"]
    result = run(cli, *args, *ordinal, "--json")
    assert result.exit_code == 0, result.stderr
    payload = json.loads(result.stdout)
    assert payload["simulated_model"]["kind"] == "ordinal"
    population = payload["simulated_model"]["population"]
    assert population["categories"] == 4 and "equally spaced" in population["source"]
    assert population["f_latent"]["between"] == pytest.approx(0.4)
    simulation = payload["simulation"]
    assert simulation["kind"] == "ordinal" and simulation["replicates"] == 4
    assert simulation["mean_df2"] is None  # a χ² test has no denominator df
    assert payload["power"] == json.loads(run(cli, *args, "--json").stdout)["power"]
    text = run(cli, *args, *ordinal).stdout
    assert "Simulated power of the ordinal model" in text and "Ordinal datasets drawn" in text


def test_ordinal_simulation_from_a_likert_pilot(cli: typer.Typer, tmp_path: Path) -> None:
    data = pd.read_csv(DROPOUTS)
    data["trust"] = data["trust"].round().clip(1, 5).astype("Int64")  # one 5-point item
    likert = tmp_path / "likert.csv"
    data.to_csv(likert, index=False)
    pilot = ["--pilot", str(likert), "--dv", "trust", "--replicates", "20"]
    ordinal = ["--n", "24", "--simulate", "3", "--model", "ordinal", "--json"]
    fitted = run(cli, "--effect", "interaction", *pilot, *ordinal)
    assert fitted.exit_code == 0, fitted.stderr
    population = json.loads(fitted.stdout)["simulated_model"]["population"]
    assert "pilot's fitted ordinal model" in population["source"]
    assert population["categories"] == data["trust"].nunique()
    given = run(cli, "--effect", "interaction", *pilot, "--f", "0.3", *ordinal)
    population = json.loads(given.stdout)["simulated_model"]["population"]
    assert "pilot's category proportions" in population["source"]
    shares = data["trust"].value_counts(normalize=True).sort_index().to_numpy()
    assert population["category_proportions"] == pytest.approx(shares, abs=0.02)
    scale_mean = run(cli, "--effect", "interaction", *PILOT, *ordinal)
    assert scale_mean.exit_code == EXIT_BAD_INPUT
    assert "needs one rating item" in scale_mean.stderr and scale_mean.stderr.count("\n") == 1


@pytest.mark.parametrize(
    ("extra", "words"),
    [
        (["--curve", "x.html", "--rho", ".5"], "add --simulate"),
        (["--simulate", "5", "--convention", "spss"], "--convention gpower"),
        (["--simulate", "3", "--rho", ".5", "--model", "ordinal", "--categories", "2"], "3 to 11"),
        (["--rho", ".5", "--model", "ordinal"], "add --simulate R"),
        (["--simulate", "3", "--rho", ".5", "--categories", "5"], "with --model ordinal"),
        (["--simulate", "3", "--rho", ".5", "--model", "probit"], "lmm, ordinal"),
    ],
)
def test_simulation_refusals(cli: typer.Typer, extra: list[str], words: str) -> None:
    result = run(cli, "--effect", "within", *PAPER, "--eta2", ".1", "--n", "12", *extra)
    assert result.exit_code == EXIT_BAD_INPUT and words in result.stderr
    assert result.stderr.count("\n") == 1


def _run_on(database_url: str, *args: str) -> Result:
    """The real ``trustlab`` command line on the test's database."""
    from app.cli import cli as trustlab

    return CliRunner().invoke(
        trustlab, ["power", *args], env={"TRUSTLAB_DATABASE_URL": database_url}
    )


@sqlite_only("the stored study is read once, as `trustlab export` reads it; the maths is the CSV's")
def test_a_stored_study_as_the_pilot(database: Database, database_url: str) -> None:
    seed_study(database, name="pilot", participants=10, seed=4)
    with database.read_session() as db:
        dataset = study_data.load_dataset(
            db, scope=Scope.every_site(), study=studies.get_study(db, "pilot")
        )
    outcome = analyse_study(dataset).outcome("trust_2")
    data = outcome.data.rename(columns={"value": "trust_2"})
    expected = estimate_pilot(
        data,
        dv="trust_2",
        within="session",
        between="condition",
        subject="participant",
        replicates=20,
        seed=3,
    )
    args = ["--effect", "interaction", "--pilot", "pilot", "--replicates", "20", "--seed", "3"]
    result = _run_on(database_url, *args, "--dv", "trust_2", "--n", "40", "--json")
    assert result.exit_code == 0, result.output
    payload = json.loads(result.stdout)
    pilot = payload["pilot"]
    assert pilot["source"] == "pilot" and pilot["dv"] == "trust_2"
    assert pilot["n_per_group"] == list(expected.group_sizes) and sum(expected.group_sizes) == 10
    assert pilot["sessions"] == [1, 2, 3, 4]
    assert payload["f"] == pytest.approx(expected.f("interaction"))
    assert payload["design"]["rho"] == pytest.approx(expected.estimates["rho"])
    assert (payload["design"]["groups"], payload["design"]["sessions"]) == (2, 4)
    default = _run_on(database_url, *args, "--n", "40")
    assert default.exit_code == 0, default.output
    assert default.stdout.startswith("Pilot pilot ('trust_1'): C1 ")  # the first trust item
    for name, dv, words in (("ghost", "trust_1", "ghost"), ("pilot", "trust_9", "trust_9")):
        refused = _run_on(
            database_url, "--effect", "within", "--pilot", name, "--dv", dv, "--n", "40"
        )
        assert refused.exit_code != 0 and refused.stderr.startswith("error: "), refused.output
        assert words in refused.stderr and refused.stderr.count("\n") == 1, refused.stderr
