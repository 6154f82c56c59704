"""``trustlab mixed``: the JSON contract, the readable summary, progress and one-line errors."""

from __future__ import annotations

import json
from pathlib import Path

import pandas as pd
import pytest
import typer
from typer.testing import CliRunner, Result

from analysis import lmm
from app.cli.analysis import EXIT_BAD_INPUT
from app.cli.mixed import register

DATA = Path(__file__).parents[1] / "analysis" / "data"
DROPOUTS = DATA / "mixed_2x4_dropouts.csv"
ARGS = ["--dv", "trust", "--within", "session", "--between", "condition"]
ARGS += ["--subject", "participant"]


@pytest.fixture(scope="module")
def cli() -> typer.Typer:
    app = typer.Typer()

    @app.callback()
    def main() -> None:
        """Stand-in for the trustlab app, which has many commands."""

    register(app)
    return app


def run(cli: typer.Typer, *args: str) -> Result:
    return CliRunner().invoke(cli, ["mixed", *args])


def test_json_has_both_models_the_comparison_and_the_kept_participants(
    cli: typer.Typer,
) -> None:
    result = run(cli, str(DROPOUTS), *ARGS, "--random-slope", "--json")
    assert result.exit_code == 0, result.stderr
    payload = json.loads(result.stdout)
    lmm_part = payload["lmm"]
    assert [m["name"] for m in lmm_part["models"]] == ["random intercept", "random slope"]
    assert lmm_part["comparison"]["df"] == 2
    assert {r["subject"] for r in lmm_part["kept_by_mixed_model"]} == {"P103", "P110", "P120"}
    tests = {t["effect"]: t for t in lmm_part["models"][0]["tests"]}
    assert set(tests) == {"between", "within", "interaction"}
    assert 60 < tests["within"]["df2"] < 70  # Satterthwaite, not ∞
    assert payload["ordinal"] is None
    assert "whole-number" in payload["ordinal_skipped"]
    assert "models" in result.stderr  # the progress bar is on stderr, not in the JSON


def test_whole_number_ratings_also_get_the_ordinal_model(cli: typer.Typer, tmp_path: Path) -> None:
    data = pd.read_csv(DROPOUTS)
    data["trust"] = data["trust"].round().clip(1, 5).astype("Int64")
    path = tmp_path / "items.csv"
    data.to_csv(path, index=False)
    result = run(cli, str(path), *ARGS, "--json")
    assert result.exit_code == 0, result.stderr
    payload = json.loads(result.stdout)
    assert payload["ordinal"]["converged"] is True
    assert payload["ordinal"]["se_type"] == "cluster-robust (25 clusters)"
    assert [m["name"] for m in payload["lmm"]["models"]] == ["random intercept"]
    text = run(cli, str(path), *ARGS)
    assert "proportional-odds (cumulative logit) model" in text.stdout


def test_the_text_summary_names_what_the_anova_dropped(cli: typer.Typer) -> None:
    result = run(cli, str(DROPOUTS), *ARGS, "--random-slope")
    assert result.exit_code == 0, result.stderr
    assert "Kept by the mixed model, excluded by the ANOVA:" in result.stdout
    assert "P110: incomplete: no trust value for session 4" in result.stdout
    assert "Satterthwaite df" in result.stdout
    assert "did not improve the fit enough to keep it, χ²(2) = " in result.stdout


def test_a_model_that_does_not_converge_is_one_line(
    cli: typer.Typer, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(lmm, "_GRADIENT_TOL", -1.0)  # no fit is ever close enough
    result = run(cli, str(DROPOUTS), *ARGS)
    assert result.exit_code == 0
    problem = [line for line in result.stdout.splitlines() if "did not converge" in line]
    assert problem and all("no estimates" in line for line in problem)
    assert "F(" not in result.stdout


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["missing.csv", *ARGS], "error: no such file: missing.csv"),
        ([str(DROPOUTS), *ARGS[:1], "nope", *ARGS[2:]], "error: data has no column 'nope'"),
    ],
)
def test_bad_input_is_one_line(cli: typer.Typer, args: list[str], message: str) -> None:
    result = run(cli, *args)
    assert result.exit_code == EXIT_BAD_INPUT
    assert result.stderr.strip().splitlines()[-1].startswith(message)
    assert "Traceback" not in result.stderr


def test_declared_text_levels_set_the_slope_steps(cli: typer.Typer, tmp_path: Path) -> None:
    data = pd.read_csv(DROPOUTS)
    data = data[data["session"] <= 3].assign(
        session=lambda d: d["session"].map({1: "pre", 2: "mid", 3: "post"})
    )
    path = tmp_path / "prepost.csv"
    data.to_csv(path, index=False)
    default = run(cli, str(path), *ARGS, "--random-slope")
    assert "session levels in order (slope steps): mid = 0, post = 1, pre = 2" in default.stdout
    declared = run(cli, str(path), *ARGS, "--random-slope", "--within-levels", "pre,mid,post")
    assert declared.exit_code == 0, declared.stderr
    assert "session levels in order (slope steps): pre = 0, mid = 1, post = 2" in declared.stdout
    assert "Estimated marginal means (random intercept model, 95 % CI):" in declared.stdout
    numeric = run(cli, str(DROPOUTS), *ARGS, "--within-levels", "one,two")
    assert numeric.exit_code == EXIT_BAD_INPUT
    assert "--within-levels: 'session' holds numbers" in numeric.stderr


def test_data_without_residual_variation_are_refused_in_one_line(
    cli: typer.Typer, tmp_path: Path
) -> None:
    # every rating = its condition × session cell + the participant's own level, exactly
    data = pd.read_csv(DROPOUTS).dropna()
    level = data["participant"].str[1:].astype(int) / 10
    data["trust"] = 3 + data["session"] * (data["condition"] == "C2") * 0.25 + level
    path = tmp_path / "noiseless.csv"
    data.to_csv(path, index=False)
    result = run(cli, str(path), *ARGS)
    assert result.exit_code == EXIT_BAD_INPUT
    assert "Traceback" not in result.stderr and "converged" not in result.stdout
    assert result.stderr.strip().splitlines()[-1] == (
        "error: the mixed model trust ~ condition * session + (1 | participant) cannot be "
        "computed because its fixed and random effects reproduce every value to rounding error (no "
        "residual variation), so its variances and tests are undefined"
    )
