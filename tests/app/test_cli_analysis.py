"""``trustlab anova``: the JSON contract, the readable table and one-line errors."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import typer
from typer.testing import CliRunner, Result

from app.cli.analysis import EXIT_BAD_INPUT, register

DATA = Path(__file__).parents[1] / "analysis" / "data"
REFERENCE = DATA / "reference_anova"
REF_ARGS = ["--dv", "dv", "--within", "within", "--between", "between", "--subject", "subject"]
DROP_ARGS = ["--dv", "trust", "--within", "session", "--between", "condition"]
DROP_ARGS += ["--subject", "participant"]


@pytest.fixture(scope="module")
def cli() -> typer.Typer:
    app = typer.Typer()

    @app.callback()
    def main() -> None:
        """Stand-in for the trustlab app, which has many commands."""

    register(app)
    return app


def run(cli: typer.Typer, *args: str) -> Result:
    return CliRunner().invoke(cli, ["anova", *args])


def one_json(result: Result) -> dict:  # type: ignore[type-arg]
    assert result.exit_code == 0, result.stderr
    assert result.stderr == ""
    lines = result.stdout.splitlines()
    assert len(lines) == 1  # exactly one JSON object, nothing else
    return json.loads(lines[0])


@pytest.mark.parametrize("ss_type", [2, 3])
def test_json_matches_r_afex(cli: typer.Typer, ss_type: int) -> None:
    # Expected: R 4.2.2, afex 1.2-1 / car 3.1-1 (reference r/pingouin_mixed_anova_unbalanced.json)
    ref = json.loads((REFERENCE / "r" / "pingouin_mixed_anova_unbalanced.json").read_text())
    ref = ref[f"type{ss_type}"]
    csv = str(REFERENCE / "pingouin_mixed_anova_unbalanced.csv")
    out = one_json(run(cli, csv, *REF_ARGS, "--ss-type", str(ss_type), "--json"))
    assert out["ss_type"] == ss_type
    assert out["n_subjects_used"] == 26
    assert out["excluded_subjects"] == []
    for i, name in enumerate(["between", "within", "interaction"]):
        effect = out["effects"][name]
        assert effect["df1"] == ref["num_df"][i]
        assert effect["df2"] == ref["den_df"][i]
        assert effect["F"] == pytest.approx(ref["F"][i], rel=1e-6)
        assert effect["p"] == pytest.approx(ref["p"][i], rel=1e-6)
        assert effect["np2"] == pytest.approx(ref["pes"][i], rel=1e-6)
        assert effect["ng2"] == pytest.approx(ref["ges"][i], rel=1e-6)
        if name == "between":
            assert "p_gg" not in effect
        else:
            assert effect["p_gg"] == pytest.approx(ref["p_GG"][i], rel=1e-6)
    assert out["sphericity"]["W"] == pytest.approx(ref["mauchly"]["Test statistic"][0], rel=1e-6)
    assert out["sphericity"]["p"] == pytest.approx(ref["mauchly"]["p-value"][0], rel=1e-6)
    assert out["sphericity"]["eps_gg"] == pytest.approx(ref["pval_adj"]["GG eps"][0], rel=1e-6)


def test_json_default_is_type_3_with_exclusions(cli: typer.Typer) -> None:
    out = one_json(run(cli, str(DATA / "mixed_2x4_dropouts.csv"), *DROP_ARGS, "--json"))
    assert set(out) == {"ss_type", "n_subjects_used", "excluded_subjects", "effects", "sphericity"}
    assert out["ss_type"] == 3
    assert out["n_subjects_used"] == 22
    assert [e["subject"] for e in out["excluded_subjects"]] == ["P103", "P110", "P120"]
    assert "session 3, 4" in out["excluded_subjects"][0]["reason"]
    # statsmodels 0.15.0 OLS type III (tests/analysis/data/derive_mixed_2x4_dropouts.py)
    assert out["effects"]["within"]["F"] == pytest.approx(0.11969754413491146, rel=1e-9)


def test_integer_subjects_stay_integers(cli: typer.Typer, tmp_path: Path) -> None:
    data = pd.read_csv(REFERENCE / "pingouin_mixed_anova_unbalanced.csv")
    data = data[~((data["subject"] == 5) & (data["within"] == "T3"))]
    path = tmp_path / "drop.csv"
    data.to_csv(path, index=False)
    out = one_json(run(cli, str(path), *REF_ARGS, "--json"))
    assert out["excluded_subjects"][0]["subject"] == 5
    assert out["n_subjects_used"] == 25


def test_undefined_mauchly_is_null(cli: typer.Typer, tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    rows = [(s, "A" if s < 2 else "B", t, rng.normal()) for s in range(4) for t in range(4)]
    path = tmp_path / "tiny.csv"
    pd.DataFrame(rows, columns=["subject", "between", "within", "dv"]).to_csv(path, index=False)
    out = one_json(run(cli, str(path), *REF_ARGS, "--json"))
    assert out["sphericity"]["p"] is None
    assert out["sphericity"]["W"] == 0.0


def test_readable_table(cli: typer.Typer) -> None:
    result = run(cli, str(DATA / "mixed_2x4_dropouts.csv"), *DROP_ARGS)
    assert result.exit_code == 0
    text = result.stdout
    assert "type III sums of squares" in text
    assert "22 participants used, 3 excluded" in text
    assert "condition × session: F(3, 60) = 6.52, p < .001, ηp² = .25" in text
    assert "P103: incomplete" in text
    with pytest.raises(json.JSONDecodeError):
        json.loads(text)


def _bad(result: Result, fragment: str) -> None:
    assert result.exit_code == EXIT_BAD_INPUT
    assert result.stdout == ""
    lines = result.stderr.splitlines()
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith("error: ")
    assert fragment in lines[0]
    assert "Traceback" not in result.stderr


def test_missing_file(cli: typer.Typer, tmp_path: Path) -> None:
    _bad(run(cli, str(tmp_path / "nope.csv"), *REF_ARGS, "--json"), "no such file")
    _bad(run(cli, str(tmp_path), *REF_ARGS, "--json"), "is a directory")
    empty = tmp_path / "empty.csv"
    empty.write_text("")
    _bad(run(cli, str(empty), *REF_ARGS, "--json"), "is empty")


def test_missing_column(cli: typer.Typer) -> None:
    csv = str(REFERENCE / "pingouin_mixed_anova.csv")
    args = ["--dv", "score", "--within", "within", "--between", "between", "--subject", "subject"]
    _bad(run(cli, csv, *args, "--json"), "no column 'score'")


def test_duplicates(cli: typer.Typer, tmp_path: Path) -> None:
    data = pd.read_csv(REFERENCE / "pingouin_mixed_anova.csv")
    path = tmp_path / "dup.csv"
    pd.concat([data, data.iloc[[3]]]).to_csv(path, index=False)
    _bad(run(cli, str(path), *REF_ARGS, "--json"), "more than one row per subject × within")


def test_degenerate(cli: typer.Typer, tmp_path: Path) -> None:
    data = pd.read_csv(REFERENCE / "pingouin_mixed_anova.csv").assign(dv=3.0)
    path = tmp_path / "flat.csv"
    data.to_csv(path, index=False)
    _bad(run(cli, str(path), *REF_ARGS, "--json"), "cannot be computed because all")
    one_group = pd.read_csv(REFERENCE / "pingouin_mixed_anova.csv").assign(between="X")
    one_group.to_csv(path, index=False)
    _bad(run(cli, str(path), *REF_ARGS), "cannot be computed because only one level")


def test_bad_ss_type(cli: typer.Typer) -> None:
    csv = str(REFERENCE / "pingouin_mixed_anova.csv")
    _bad(run(cli, csv, *REF_ARGS, "--ss-type", "1", "--json"), "--ss-type must be 2 or 3")
