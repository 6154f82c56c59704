"""Figures of the engine's objective measures: the paper's adaptation-speed and Appendix figures.

(a) mean probability of the preferred question after 0..T answers, one line per learner (C1 vs C2
and the references); (b) mean answers until 95 % against the number of questions K, for the
meta-policy, the same network from a random initialisation and the Bayesian reference.

Inputs are the plain objects ``trustlab simulate adaptation --json`` prints (one per K), so this
module needs nothing from the engine. :func:`write_outputs` writes the tidy CSVs behind both
figures and one self-contained HTML page (plotly.js embedded: labs are often offline).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import pandas as pd
import plotly.graph_objects as go

from analysis.errors import InvalidInputError
from analysis.exports.csvfile import write_csv
from analysis.figures import PALETTE

__all__ = [
    "LEARNER_LABELS",
    "adaptation_speed_figure",
    "curves_frame",
    "iterations_by_arms_figure",
    "reference_label",
    "sweep_frame",
    "write_outputs",
]

LEARNER_LABELS: dict[str, str] = {
    "exp3": "C1: Exp3",
    "meta": "C2: meta-policy",
    "random_init": "same network, random init",
    "bayes": "Bayes posterior (reference)",
}
"""Legend labels of the simulated learners."""

_COLORS = dict(zip(LEARNER_LABELS, PALETTE, strict=False))
_LAYOUT: dict[str, Any] = {
    "font": {"family": "system-ui, -apple-system, Segoe UI, Roboto, sans-serif", "size": 13},
    "paper_bgcolor": "white",
    "plot_bgcolor": "white",
    "legend": {"orientation": "h", "y": -0.2, "x": 0},
    "margin": {"l": 60, "r": 20, "t": 60, "b": 60},
}


def _learners(result: Mapping[str, Any]) -> Mapping[str, Any]:
    try:
        learners = result["learners"]
        int(result["arms"])
    except (KeyError, TypeError, ValueError):
        raise InvalidInputError("simulation result needs 'arms' and 'learners'") from None
    if not isinstance(learners, Mapping) or not learners:
        raise InvalidInputError("simulation result has no learners")
    return learners


def curves_frame(result: Mapping[str, Any]) -> pd.DataFrame:
    """Long table ``learner, answers, p_correct`` of one simulation result."""
    rows = []
    for learner, summary in _learners(result).items():
        for answers, value in enumerate(summary["p_correct"]):
            rows.append({"learner": learner, "answers": answers, "p_correct": float(value)})
    return pd.DataFrame(rows, columns=["learner", "answers", "p_correct"])


def sweep_frame(results: Sequence[Mapping[str, Any]]) -> pd.DataFrame:
    """One row per K and learner: ``arms, learner, iterations_to_95, reached_95, wrong_95``.

    Raises
    ------
    InvalidInputError
        If two results have the same K (a sweep has one simulation per K).
    """
    rows, seen = [], set()
    for result in results:
        learners = _learners(result)
        arms = int(result["arms"])
        if arms in seen:
            raise InvalidInputError(f"two simulation results for K = {arms}")
        seen.add(arms)
        for learner, summary in learners.items():
            rows.append(
                {
                    "arms": arms,
                    "learner": learner,
                    "iterations_to_95": float(summary["iterations_to_95"]),
                    "reached_95": float(summary["reached_95"]),
                    "wrong_95": float(summary["wrong_95"]),
                }
            )
    columns = ["arms", "learner", "iterations_to_95", "reached_95", "wrong_95"]
    return pd.DataFrame(rows, columns=columns).sort_values(["learner", "arms"], kind="stable")


def reference_label(result: Mapping[str, Any] | None) -> str:
    """The reference's legend label, naming what it assumes: the plain Bayes posterior (the
    paper's participants) or the forward filter for participants who slip or change their minds
    (the result's ``reference``, as ``simulate_adaptation`` writes it)."""
    reference = None if result is None else result.get("reference")
    if not isinstance(reference, str) or not reference:
        return LEARNER_LABELS["bayes"]
    return f"reference: {reference}"


def _label(name: str, reference: str) -> str:
    return reference if name == "bayes" else LEARNER_LABELS.get(name, name)


def adaptation_speed_figure(
    curves: pd.DataFrame, arms: int, result: Mapping[str, Any] | None = None
) -> go.Figure:
    """(a) Mean p(preferred question) after 0..T answers, one line per learner, 95 % marked;
    with the simulation's ``result``, the reference is labelled by its model and the subtitle
    says how the participants answered (and which population they were drawn from)."""
    figure = go.Figure()
    reference = reference_label(result)
    for learner, group in curves.groupby("learner", sort=False):
        name = str(learner)
        figure.add_trace(
            go.Scatter(
                x=group["answers"].tolist(),
                y=group["p_correct"].tolist(),
                mode="lines+markers",
                name=_label(name, reference),
                line={"color": _COLORS.get(name, "#000000")},
            )
        )
    figure.add_hline(y=0.95, line_dash="dot", line_color="#888888", annotation_text="95 %")
    participants = None if result is None else result.get("participants_answer")
    title = f"Adaptation speed: belief in the preferred question (K = {arms})"
    if isinstance(participants, str) and participants:
        title += f"<br><sup>participants: {participants}</sup>"
    drawn = _drawn_from(result)
    if drawn:
        title += f"<br><sup>{drawn}</sup>"
    figure.update_layout(
        **_LAYOUT,
        title=title,
        xaxis={"title": "answers", "dtick": 1, "gridcolor": "#eeeeee"},
        yaxis={"title": "mean p(preferred question)", "range": [0, 1.02], "gridcolor": "#eeeeee"},
    )
    return figure


def _drawn_from(result: Mapping[str, Any] | None) -> str:
    """Which population the participants were drawn from, when a population was named: the
    fitted one C2 was trained for (optimistic) or the one the lab declared true."""
    population = None if result is None else result.get("population")
    summary = population.get("summary") if isinstance(population, Mapping) else None
    return summary if isinstance(summary, str) else ""


def iterations_by_arms_figure(
    sweep: pd.DataFrame, result: Mapping[str, Any] | None = None
) -> go.Figure:
    """(b) Mean answers until 95 % against K, one line per learner (13 = never within 12), the
    reference labelled by its model as in figure (a)."""
    figure = go.Figure()
    reference = reference_label(result)
    for learner, group in sweep.groupby("learner", sort=False):
        name = str(learner)
        figure.add_trace(
            go.Scatter(
                x=group["arms"].tolist(),
                y=group["iterations_to_95"].tolist(),
                mode="lines+markers",
                name=_label(name, reference),
                line={"color": _COLORS.get(name, "#000000")},
            )
        )
    figure.update_layout(
        **_LAYOUT,
        title="Answers until 95 % belief in the preferred question, by number of questions",
        xaxis={"title": "number of questions K", "dtick": 1, "gridcolor": "#eeeeee"},
        yaxis={"title": "mean answers to 95 %", "rangemode": "tozero", "gridcolor": "#eeeeee"},
    )
    return figure


def write_outputs(
    out: Path, result: Mapping[str, Any], sweep_results: Sequence[Mapping[str, Any]]
) -> list[Path]:
    """Write ``adaptation_curves.csv``, ``iterations_by_arms.csv`` and ``simulation.html``.

    ``result`` feeds figure (a), ``sweep_results`` (one result per K) figure (b). Returns the
    paths written; ``out`` is created if needed. The CSVs are written like every export
    (:func:`analysis.exports.csvfile.write_csv`).
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    curves = curves_frame(result)
    sweep = sweep_frame(sweep_results)
    paths = [out / "adaptation_curves.csv", out / "iterations_by_arms.csv", out / "simulation.html"]
    write_csv(curves, paths[0])
    write_csv(sweep, paths[1])
    speed = adaptation_speed_figure(curves, int(result["arms"]), result)
    by_arms = iterations_by_arms_figure(sweep, sweep_results[0] if sweep_results else result)
    body = speed.to_html(full_html=False, include_plotlyjs=True) + by_arms.to_html(
        full_html=False, include_plotlyjs=False
    )
    paths[2].write_text(
        "<!doctype html><html><head><meta charset='utf-8'><title>trustlab: adaptation "
        f"simulations</title></head><body>{body}</body></html>\n",
        encoding="utf-8",
    )
    return paths
