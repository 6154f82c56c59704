"""Figures and their JSON payloads."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import plotly.graph_objects as go
import pytest

from analysis.adaptation import adaptation_curves
from analysis.dataset import empty_steps
from analysis.descriptives import cell_descriptives
from analysis.errors import InvalidInputError
from analysis.figures import (
    BOX_POINTS_LIMIT,
    PALETTE,
    adaptation_figure,
    adaptation_payload,
    adaptation_payload_from_curves,
    condition_colors,
    mean_ci_figure,
    mean_ci_payload,
    mean_ci_payload_from_cells,
    score_distribution_figure,
    score_distribution_payload,
    trajectories_figure,
    trajectories_payload,
)
from tests.analysis.test_adaptation import PREFERRED, _step

DKW = {"dv": "trust", "within": "session", "between": "condition"}


def test_mean_ci_payload_is_json_and_matches_descriptives(dropouts: pd.DataFrame) -> None:
    payload = mean_ci_payload(dropouts, **DKW, y_range=(1, 5))
    text = json.dumps(payload, allow_nan=False)
    assert json.loads(text)["kind"] == "mean_ci"
    cells = cell_descriptives(dropouts, **DKW)
    assert len(payload["cells"]) == len(cells) == 8
    c2 = next(t for t in payload["data"] if t["name"] == "C2")
    expected = cells[cells.condition == "C2"]
    np.testing.assert_allclose(c2["y"], expected["mean"])
    np.testing.assert_allclose(c2["error_y"]["array"], expected["ci_high"] - expected["mean"])
    np.testing.assert_allclose(c2["error_y"]["arrayminus"], expected["mean"] - expected["ci_low"])
    assert c2["type"] == "bar"
    assert c2["x"] == ["session 1", "session 2", "session 3", "session 4"]
    assert payload["layout"]["barmode"] == "group"
    assert payload["layout"]["yaxis"]["range"] == [1, 5]
    assert c2["marker"]["color"] == PALETTE[1]


def test_point_style_dodges_conditions(dropouts: pd.DataFrame) -> None:
    payload = mean_ci_payload(dropouts, **DKW, style="point", within_label="Session")
    c1, c2 = payload["data"]
    assert c1["type"] == "scatter"
    assert all(a < b for a, b in zip(c1["x"], c2["x"], strict=True))
    assert payload["layout"]["xaxis"]["ticktext"][0] == "Session 1"
    with pytest.raises(InvalidInputError, match="style"):
        mean_ci_payload(dropouts, **DKW, style="violin")  # type: ignore[arg-type]


def test_nan_cells_become_null(dropouts: pd.DataFrame) -> None:
    one = dropouts[dropouts.participant.isin(["P101", "P112", "P113"])]
    payload = mean_ci_payload(one, **DKW)  # C1 has one participant: no CI
    c1 = payload["data"][0]
    assert c1["error_y"]["array"] == [None] * 4
    json.dumps(payload, allow_nan=False)


def test_figures_are_plotly_figures(dropouts: pd.DataFrame) -> None:
    fig = mean_ci_figure(dropouts, **DKW, title="Trust towards the robot")
    assert isinstance(fig, go.Figure)
    assert fig.layout.title.text == "Trust towards the robot"
    assert len(fig.data) == 2
    traj = trajectories_figure(dropouts, **DKW, subject="participant")
    assert isinstance(traj, go.Figure)
    assert len(traj.data) == 4


def test_trajectories_one_trace_per_condition_with_gaps(dropouts: pd.DataFrame) -> None:
    payload = trajectories_payload(dropouts, **DKW, subject="participant")
    lines = [t for t in payload["data"] if t["name"].endswith("participants")]
    assert [t["name"] for t in lines] == ["C1 participants", "C2 participants"]
    assert lines[0]["x"].count(None) == 11  # one gap after each C1 participant
    assert payload["total"] == {"C1": 11, "C2": 14}
    capped = trajectories_payload(dropouts, **DKW, subject="participant", max_per_condition=3)
    assert capped["shown"] == {"C1": 3, "C2": 3}
    json.dumps(capped, allow_nan=False)


def test_adaptation_payload_panels_and_band() -> None:
    rows = [
        _step("P1", "C1", "conation", 1, 1, 0.25, 0.4),
        _step("P2", "C2", "cognition", 1, 2, 0.25, 0.6),
    ]
    steps = pd.DataFrame(rows)
    payload = adaptation_payload(steps, PREFERRED)
    json.dumps(payload, allow_nan=False)
    assert payload["categories"] == ["conation", "cognition"]
    assert "xaxis2" in payload["layout"]
    assert payload["layout"]["yaxis"]["range"] == [0, 1]
    means = [t for t in payload["data"] if t.get("mode") == "lines+markers"]
    assert [(t["name"], t["xaxis"]) for t in means] == [("C1", "x"), ("C2", "x2")]
    assert means[0]["y"] == [0.25, 0.4]
    bands = [t for t in payload["data"] if t.get("fill") == "toself"]
    assert len(bands) == 2
    assert len(payload["curves"]) == 4
    assert isinstance(adaptation_figure(steps, PREFERRED), go.Figure)


def _scores(n: int) -> pd.DataFrame:
    rng = np.random.default_rng(1)
    return pd.DataFrame(
        {
            "participant": np.arange(2 * n),
            "condition": ["C1"] * n + ["C2"] * n,
            "scale": "tipi_openness",
            "score": rng.uniform(1, 7, 2 * n),
        }
    )


def test_score_distribution_small_ships_points() -> None:
    payload = score_distribution_payload(_scores(10), scale_labels={"tipi_openness": "Openness"})
    assert payload["data"][0]["boxpoints"] == "all"
    assert payload["data"][0]["x"] == ["Openness"] * 10
    assert isinstance(score_distribution_figure(_scores(10)), go.Figure)


def test_score_distribution_large_ships_quartiles() -> None:
    scores = _scores(BOX_POINTS_LIMIT + 100)
    payload = score_distribution_payload(scores)
    trace = payload["data"][0]
    assert "y" not in trace
    c1 = scores[scores.condition == "C1"]["score"]
    assert trace["median"] == [pytest.approx(float(np.median(c1)))]
    assert trace["q1"] == [pytest.approx(float(np.quantile(c1, 0.25)))]
    assert len(json.dumps(payload)) < 5000


def test_condition_colors() -> None:
    assert condition_colors(["C1", "C2"], {"C2": "#123456"}) == {"C1": PALETTE[0], "C2": "#123456"}


def test_payloads_for_a_study_that_has_not_started() -> None:
    empty = pd.DataFrame({"trust": [], "session": [], "condition": []})
    payload = mean_ci_payload(empty, **DKW, y_range=(1, 5))
    assert payload["cells"] == []
    assert payload["data"] == []
    assert payload["layout"]["yaxis"]["range"] == [1, 5]
    json.dumps(payload, allow_nan=False)
    with pytest.raises(InvalidInputError, match="no column 'trust'"):
        mean_ci_payload(pd.DataFrame({"session": []}), **DKW)
    adaptation = adaptation_payload(empty_steps(), PREFERRED)
    assert adaptation["data"] == []
    assert adaptation["curves"] == []
    assert adaptation["categories"] == ["conation", "cognition"]
    json.dumps(adaptation, allow_nan=False)


def _columns(frame: pd.DataFrame) -> dict[str, list[object]]:
    return {column: frame[column].tolist() for column in frame.columns}


def test_plain_columns_give_the_frames_payload(dropouts: pd.DataFrame) -> None:
    # The live dashboard passes plain columns, the report frames: one builder, one payload.
    one = dropouts[dropouts.participant.isin(["P101", "P112", "P113"])]  # NaN SDs in C1
    for data in (dropouts, one):
        cells = cell_descriptives(data, **DKW).sample(frac=1.0, random_state=3)  # any row order
        for style in ("bar", "point"):
            kw = {**DKW, "style": style, "y_range": (1, 5), "within_label": "Session"}
            framed = mean_ci_payload_from_cells(cells, **kw)  # type: ignore[arg-type]
            plain = mean_ci_payload_from_cells(_columns(cells), **kw)  # type: ignore[arg-type]
            assert json.dumps(plain) == json.dumps(framed)
    steps = pd.DataFrame(
        [
            _step("P1", "C1", "conation", 1, 1, 0.25, 0.4),
            _step("P2", "C1", "conation", 1, 1, 0.25, 0.7),
            _step("P3", "C2", "cognition", 1, 2, 0.25, 0.6),
        ]
    )
    curves = adaptation_curves(steps, PREFERRED)
    framed = adaptation_payload_from_curves(curves, list(PREFERRED))
    assert json.dumps(adaptation_payload_from_curves(_columns(curves), list(PREFERRED))) == (
        json.dumps(framed)
    )
    empty = {column: [] for column in curves.columns}
    assert adaptation_payload_from_curves(empty, list(PREFERRED))["data"] == []
    with pytest.raises(InvalidInputError, match="no column 'iteration', 'mean'"):
        adaptation_payload_from_curves({"condition": [], "category": []}, ["conation"])
    with pytest.raises(InvalidInputError, match="different lengths"):
        mean_ci_payload_from_cells({**_columns(cells), "n": [1]}, **DKW)


def test_a_categorical_condition_keeps_its_declared_order(dropouts: pd.DataFrame) -> None:
    cells = cell_descriptives(dropouts, **DKW)
    cells["condition"] = pd.Categorical(cells["condition"], categories=["C2", "C1"])
    names = [t["name"] for t in mean_ci_payload_from_cells(cells, **DKW)["data"]]
    assert names == ["C2", "C1"]
