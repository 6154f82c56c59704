"""Figures (a) and (b) of the objective measures, and the files ``--out`` writes."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pandas as pd
import pytest

from analysis.errors import InvalidInputError
from analysis.simulation_figures import (
    adaptation_speed_figure,
    curves_frame,
    iterations_by_arms_figure,
    sweep_frame,
    write_outputs,
)


def _result(arms: int, offset: float = 0.0) -> dict[str, Any]:
    def learner(base: float) -> dict[str, Any]:
        return {
            "p_correct": [base + offset + 0.01 * t for t in range(4)],
            "iterations_to_95": arms + base,
            "reached_95": 0.9,
            "wrong_95": 0.01,
        }

    return {
        "arms": arms,
        "iterations": 3,
        "participants": 10,
        "learners": {"meta": learner(0.5), "bayes": learner(0.6)},
    }


def test_curves_frame_is_long_and_complete() -> None:
    frame = curves_frame(_result(4))
    assert list(frame.columns) == ["learner", "answers", "p_correct"]
    assert len(frame) == 8
    assert frame.loc[(frame.learner == "bayes") & (frame.answers == 3), "p_correct"].item() == (
        pytest.approx(0.63)
    )


def test_sweep_frame_orders_by_learner_then_k_and_refuses_duplicates() -> None:
    frame = sweep_frame([_result(5), _result(3)])
    assert frame[frame.learner == "meta"]["arms"].tolist() == [3, 5]
    assert frame[frame.learner == "meta"]["iterations_to_95"].tolist() == [3.5, 5.5]
    with pytest.raises(InvalidInputError, match="K = 3"):
        sweep_frame([_result(3), _result(3)])
    with pytest.raises(InvalidInputError, match="learners"):
        sweep_frame([{"arms": 3}])


def test_figures_have_one_trace_per_learner() -> None:
    speed = adaptation_speed_figure(curves_frame(_result(4)), 4)
    assert [t.name for t in speed.data] == ["C2: meta-policy", "Bayes posterior (reference)"]
    assert list(speed.data[0].y) == pytest.approx([0.5, 0.51, 0.52, 0.53])
    by_arms = iterations_by_arms_figure(sweep_frame([_result(2), _result(3)]))
    assert list(by_arms.data[1].x) == [2, 3]
    assert "K = 4" in speed.layout.title.text


def test_write_outputs(tmp_path: Path) -> None:
    paths = write_outputs(tmp_path / "out", _result(4), [_result(2), _result(4)])
    assert [p.name for p in paths] == [
        "adaptation_curves.csv",
        "iterations_by_arms.csv",
        "simulation.html",
    ]
    assert len(pd.read_csv(paths[0])) == 8
    assert set(pd.read_csv(paths[1])["arms"]) == {2, 4}
    html = paths[2].read_text()
    assert html.count("Plotly.newPlot") == 2
    assert "Adaptation speed" in html


def test_the_reference_is_labelled_by_its_model() -> None:
    result = _result(4) | {
        "reference": "forward filter over slips and changes",
        "participants_answer": "binary answers, slip 0.1, hazard 0",
    }
    speed = adaptation_speed_figure(curves_frame(result), 4, result)
    names = [t.name for t in speed.data]
    assert names == ["C2: meta-policy", "reference: forward filter over slips and changes"]
    assert "participants: binary answers, slip 0.1, hazard 0" in speed.layout.title.text
    by_arms = iterations_by_arms_figure(sweep_frame([result]), result)
    assert by_arms.data[0].name == "reference: forward filter over slips and changes"
