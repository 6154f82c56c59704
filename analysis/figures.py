"""Plotly figures of the study, and the JSON-able data behind the live ones.

Every figure is built from a *payload*: a plain dict of ``data`` (Plotly traces) and ``layout``
plus the summary numbers it shows. The live dashboard pushes the payload and calls
``Plotly.react(div, payload.data, payload.layout)`` in the browser; the report and notebooks
turn the same payload into a :class:`plotly.graph_objects.Figure`. One builder, so the dashboard
and the report can never disagree.

The ``*_from_cells`` / ``*_from_curves`` builders take their table either as a DataFrame (the
report, notebooks) or as plain columns (the live dashboard, which recomputes several times a second
and for whom building a DataFrame of a few dozen cells would cost more than the figure). Both forms
go through the same code, on numpy columns.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any, Literal, TypeAlias

import numpy as np
import pandas as pd
import plotly.graph_objects as go

from analysis._checks import (
    ordered_levels,
    require_columns,
    require_frame,
    require_no_missing,
    to_python,
)
from analysis.adaptation import adaptation_curves
from analysis.descriptives import CELL_COLUMNS, cell_descriptives
from analysis.errors import InvalidInputError

__all__ = [
    "PALETTE",
    "Table",
    "adaptation_figure",
    "adaptation_payload",
    "adaptation_payload_from_curves",
    "condition_colors",
    "figure_from_payload",
    "mean_ci_figure",
    "mean_ci_payload",
    "mean_ci_payload_from_cells",
    "score_distribution_figure",
    "score_distribution_payload",
    "trajectories_figure",
    "trajectories_payload",
    "trust_confidence_payload",
]

PALETTE = ("#0072B2", "#E69F00", "#009E73", "#CC79A7", "#56B4E9", "#D55E00", "#F0E442", "#000000")
"""Okabe–Ito colours (distinguishable with colour-vision deficiencies), one per condition."""

BOX_POINTS_LIMIT = 500
"""Above this many values per box, quartiles are precomputed instead of shipping raw points."""

_BASE_LAYOUT: dict[str, Any] = {
    "font": {"family": "system-ui, -apple-system, Segoe UI, Roboto, sans-serif", "size": 13},
    "paper_bgcolor": "white",
    "plot_bgcolor": "white",
    "margin": {"l": 60, "r": 20, "t": 60, "b": 80},
    # The legend sits at the foot of the whole figure (y measured on the container, not the plot
    # area): placed as a fraction of the plot area it ran into the x-axis title on short charts.
    "legend": {"orientation": "h", "x": 0, "yref": "container", "y": 0, "yanchor": "bottom"},
    # Plotly hides the legend of a one-trace chart: a study with one condition enrolled so far
    # would show a line nobody can name.
    "showlegend": True,
}


def _axis(title: str, **extra: Any) -> dict[str, Any]:
    return {
        "title": {"text": title},
        "gridcolor": "#e5e5e5",
        "zeroline": False,
        "linecolor": "#444",
        **extra,
    }


def condition_colors(
    conditions: Sequence[Any], colors: Mapping[Any, str] | None = None
) -> dict[Any, str]:
    """A colour per condition: the ones given, then the palette in order."""
    given = dict(colors or {})
    out: dict[Any, str] = {}
    for i, condition in enumerate(conditions):
        out[condition] = given.get(condition, PALETTE[i % len(PALETTE)])
    return out


def _rgba(hex_color: str, alpha: float) -> str:
    h = hex_color.lstrip("#")
    r, g, b = (int(h[i : i + 2], 16) for i in (0, 2, 4))
    return f"rgba({r},{g},{b},{alpha})"


def _json_list(values: Any) -> list[Any]:
    """Plain Python list with NaN/NA as None (JSON has no NaN)."""
    array = np.asarray(values)
    if array.dtype.kind in "iub":
        return array.tolist()
    if array.dtype.kind == "f":
        return [None if not math.isfinite(v) else v for v in array.tolist()]
    out = []
    for v in np.asarray(values, dtype=object).tolist():
        plain = to_python(v)
        if isinstance(plain, float) and not math.isfinite(plain):
            plain = None
        out.append(plain)
    return out


Table: TypeAlias = pd.DataFrame | Mapping[str, Sequence[Any]]
"""A table of cells or curves: a DataFrame, or columns (name → values of one length) in order."""


class _Table:
    """A :data:`Table` as numpy columns, whichever form it came in (checked once)."""

    def __init__(self, table: Table, required: Sequence[str], what: str) -> None:
        if isinstance(table, pd.DataFrame):
            require_columns(table, required, what)
            self._frame: pd.DataFrame | None = table
            self.columns = {c: table[c].to_numpy() for c in table.columns}
        else:
            missing = [c for c in required if c not in table]
            if missing:
                raise InvalidInputError(
                    f"{what} has no column {', '.join(map(repr, missing))} "
                    f"(columns: {', '.join(map(str, table))})"
                )
            self._frame = None
            self.columns = {c: np.asarray(values) for c, values in table.items()}
        lengths = {len(values) for values in self.columns.values()}
        if len(lengths) > 1:
            raise InvalidInputError(f"{what} has columns of different lengths")
        self.length = lengths.pop() if lengths else 0

    def levels(self, column: str) -> list[Any]:
        """The column's levels as :func:`analysis._checks.ordered_levels` orders them."""
        if self._frame is not None:  # keeps a categorical column's declared order
            return ordered_levels(self._frame[column])
        present = [
            v for v in dict.fromkeys(self.columns[column].tolist()) if to_python(v) is not None
        ]
        try:
            return sorted(present)
        except TypeError:
            return sorted(present, key=str)

    def rows(self, column: str, value: Any) -> np.ndarray:
        """Positions of the rows whose ``column`` equals ``value``, in table order."""
        return np.flatnonzero(self.columns[column] == value)

    def records(self) -> list[dict[str, Any]]:
        """The rows as JSON-able dicts (NaN as None), columns in table order."""
        cols = {c: _json_list(values) for c, values in self.columns.items()}
        return [dict(zip(cols, row, strict=True)) for row in zip(*cols.values(), strict=True)]


def figure_from_payload(payload: Mapping[str, Any]) -> go.Figure:
    """A Plotly figure from a payload's ``data`` and ``layout``."""
    return go.Figure(data=list(payload["data"]), layout=dict(payload["layout"]))


# --------------------------------------------------------------------------- mean ± CI


def mean_ci_payload(
    data: pd.DataFrame,
    *,
    dv: str,
    within: str,
    between: str,
    confidence: float = 0.95,
    title: str | None = None,
    y_label: str | None = None,
    y_range: tuple[float, float] | None = None,
    within_label: str | None = None,
    style: Literal["bar", "point"] = "bar",
    colors: Mapping[Any, str] | None = None,
) -> dict[str, Any]:
    """Data and traces of the mean ± CI by session figure, conditions side by side.

    Parameters
    ----------
    data : pandas.DataFrame
        Long frame with ``dv``, ``within`` and ``between``.
    dv, within, between : str
        Column names.
    confidence : float
        Coverage of the error bars (t interval per cell, see
        :func:`analysis.descriptives.cell_descriptives`).
    title, y_label, within_label : str, optional
        Texts; default to the column names.
    y_range : (float, float), optional
        Fixed y axis (e.g. the Likert range) so live updates do not rescale.
    style : {"bar", "point"}
        Grouped bars with error bars (the seed paper's figures) or dodged points joined by lines.
    colors : mapping, optional
        Colour per condition.

    Returns
    -------
    dict
        ``{"kind": "mean_ci", "dv", "within", "between", "confidence", "cells": [...],
        "data": [...], "layout": {...}}``, JSON-serialisable. With no rows yet, ``cells`` and
        ``data`` are empty lists (the layout is still complete).
    """
    if isinstance(data, pd.DataFrame) and data.empty:
        # A study that has not started yet: an empty chart, not an error, for the dashboard.
        require_columns(data, [dv, within, between])
        cells = pd.DataFrame(columns=[between, within, *CELL_COLUMNS])
    else:
        cells = cell_descriptives(
            data, dv=dv, within=within, between=between, confidence=confidence
        )
    return mean_ci_payload_from_cells(
        cells,
        dv=dv,
        within=within,
        between=between,
        confidence=confidence,
        title=title,
        y_label=y_label,
        y_range=y_range,
        within_label=within_label,
        style=style,
        colors=colors,
    )


def mean_ci_payload_from_cells(
    cells: Table,
    *,
    dv: str,
    within: str,
    between: str,
    confidence: float = 0.95,
    title: str | None = None,
    y_label: str | None = None,
    y_range: tuple[float, float] | None = None,
    within_label: str | None = None,
    style: Literal["bar", "point"] = "bar",
    colors: Mapping[Any, str] | None = None,
) -> dict[str, Any]:
    """:func:`mean_ci_payload` from already computed :func:`cell_descriptives` cells (a
    :data:`Table`: the frame, or the same columns as plain values)."""
    if style not in ("bar", "point"):
        raise InvalidInputError(f"style must be 'bar' or 'point', got {style!r}")
    table = _Table(cells, [between, within, "n", "mean", "sd", "ci_low", "ci_high"], "cells")
    columns = table.columns
    conditions = table.levels(between)
    levels = table.levels(within)
    palette = condition_colors(conditions, colors)
    level_label = within_label or within
    ticktext = [f"{level_label} {to_python(v)}" for v in levels]
    pos = {v: i for i, v in enumerate(levels)}
    n_cond = len(conditions)
    width = 0.8 / max(n_cond, 1)
    traces: list[dict[str, Any]] = []
    for k, condition in enumerate(conditions):
        rows = table.rows(between, condition)
        at = columns[within][rows]
        mean = np.asarray(columns["mean"][rows], dtype=float)
        upper = np.asarray(columns["ci_high"][rows], dtype=float) - mean
        lower = mean - np.asarray(columns["ci_low"][rows], dtype=float)
        hover = [
            f"{condition}, {level_label} {to_python(w)}<br>M = {m:.2f}, SD = {sd:.2f}, n = {n}"
            f"<br>{confidence:.0%} CI [{lo:.2f}, {hi:.2f}]"
            for w, m, sd, n, lo, hi in zip(
                at,
                mean,
                columns["sd"][rows],
                columns["n"][rows],
                columns["ci_low"][rows],
                columns["ci_high"][rows],
                strict=True,
            )
        ]
        x = [pos[w] for w in at]
        trace: dict[str, Any] = {
            "name": str(to_python(condition)),
            "legendgroup": str(to_python(condition)),
            "y": _json_list(mean),
            "error_y": {
                "type": "data",
                "symmetric": False,
                "array": _json_list(upper),
                "arrayminus": _json_list(lower),
                "thickness": 1.5,
                "width": 4,
            },
            "hovertext": hover,
            "hoverinfo": "text",
            "marker": {"color": palette[condition]},
        }
        if style == "bar":
            trace.update(type="bar", x=[ticktext[i] for i in x], opacity=0.9)
        else:
            offset = (k - (n_cond - 1) / 2) * width / 2
            trace.update(
                type="scatter",
                mode="lines+markers",
                x=[xi + offset for xi in x],
                line={"color": palette[condition], "width": 2},
                marker={"color": palette[condition], "size": 9},
            )
        traces.append(trace)
    xaxis = (
        _axis(
            level_label.capitalize(), type="category", categoryorder="array", categoryarray=ticktext
        )
        if style == "bar"
        else _axis(level_label.capitalize(), tickvals=list(range(len(levels))), ticktext=ticktext)
    )
    layout = {
        **_BASE_LAYOUT,
        "title": {"text": title or f"{dv}: mean ± {confidence:.0%} CI"},
        "xaxis": xaxis,
        "yaxis": _axis(y_label or dv, **({"range": list(y_range)} if y_range else {})),
        "barmode": "group",
        "hovermode": "closest",
    }
    return {
        "kind": "mean_ci",
        "dv": dv,
        "within": within,
        "between": between,
        "confidence": confidence,
        "cells": table.records(),
        "data": traces,
        "layout": layout,
    }


def mean_ci_figure(
    data: pd.DataFrame,
    *,
    dv: str,
    within: str,
    between: str,
    confidence: float = 0.95,
    title: str | None = None,
    y_label: str | None = None,
    y_range: tuple[float, float] | None = None,
    within_label: str | None = None,
    style: Literal["bar", "point"] = "bar",
    colors: Mapping[Any, str] | None = None,
) -> go.Figure:
    """Mean ± CI by session, conditions dodged side by side (see :func:`mean_ci_payload`)."""
    return figure_from_payload(
        mean_ci_payload(
            data,
            dv=dv,
            within=within,
            between=between,
            confidence=confidence,
            title=title,
            y_label=y_label,
            y_range=y_range,
            within_label=within_label,
            style=style,
            colors=colors,
        )
    )


# --------------------------------------------------------------------------- trajectories


def trajectories_payload(
    data: pd.DataFrame,
    *,
    dv: str,
    within: str,
    between: str,
    subject: str,
    max_per_condition: int | None = None,
    title: str | None = None,
    y_label: str | None = None,
    y_range: tuple[float, float] | None = None,
    colors: Mapping[Any, str] | None = None,
) -> dict[str, Any]:
    """Each participant's values across sessions, one thin line each, plus the condition mean.

    Participants of a condition share one trace (lines separated by gaps), so thousands of
    participants stay light. ``max_per_condition`` keeps the first participants (by sorted
    code) of each condition; the payload's ``shown``/``total`` say how many were drawn.
    """
    data = require_frame(data)
    require_columns(data, [dv, within, between, subject])
    require_no_missing(data, [within, between, subject])
    levels = ordered_levels(data[within])
    conditions = ordered_levels(data[between])
    palette = condition_colors(conditions, colors)
    x_all = pd.Index(levels).get_indexer(data[within]).astype(float)
    y_all = pd.to_numeric(data[dv], errors="coerce").to_numpy(float)
    subj_codes, _ = pd.factorize(data[subject], sort=True)
    cond_all = data[between].to_numpy()
    traces: list[dict[str, Any]] = []
    shown: dict[str, int] = {}
    total: dict[str, int] = {}
    for condition in conditions:
        member = np.flatnonzero(cond_all == condition)
        name = str(to_python(condition))
        subjects_here = np.unique(subj_codes[member])  # sorted codes = sorted participant ids
        total[name] = len(subjects_here)
        if max_per_condition is not None and len(subjects_here) > max_per_condition:
            member = member[np.isin(subj_codes[member], subjects_here[:max_per_condition])]
        shown[name] = len(np.unique(subj_codes[member]))
        order = member[np.lexsort((x_all[member], subj_codes[member]))]
        codes = subj_codes[order]
        # One polyline per participant, separated by a gap (None) after each participant.
        ends = np.flatnonzero(np.append(codes[1:] != codes[:-1], True)) + 1
        xs = np.insert(x_all[order], ends, np.nan)
        ys = np.insert(y_all[order], ends, np.nan)
        color = palette[condition]
        traces.append(
            {
                "type": "scatter",
                "mode": "lines",
                "name": f"{name} participants",
                "legendgroup": name,
                "x": _json_list(xs),
                "y": _json_list(ys),
                "line": {"color": _rgba(color, 0.35), "width": 1},
                "hoverinfo": "skip",
                "connectgaps": False,
            }
        )
        all_member = np.flatnonzero((cond_all == condition) & ~np.isnan(y_all))
        sums = np.bincount(
            x_all[all_member].astype(int), weights=y_all[all_member], minlength=len(levels)
        )
        counts = np.bincount(x_all[all_member].astype(int), minlength=len(levels))
        with np.errstate(invalid="ignore", divide="ignore"):
            means = sums / counts
        present = counts > 0
        traces.append(
            {
                "type": "scatter",
                "mode": "lines+markers",
                "name": f"{name} mean",
                "legendgroup": name,
                "x": _json_list(np.flatnonzero(present)),
                "y": _json_list(means[present]),
                "line": {"color": color, "width": 3},
                "marker": {"color": color, "size": 8},
            }
        )
    ticktext = [f"{within} {to_python(v)}" for v in levels]
    layout = {
        **_BASE_LAYOUT,
        "title": {"text": title or f"{dv}: individual trajectories"},
        "xaxis": _axis(within.capitalize(), tickvals=list(range(len(levels))), ticktext=ticktext),
        "yaxis": _axis(y_label or dv, **({"range": list(y_range)} if y_range else {})),
    }
    return {
        "kind": "trajectories",
        "dv": dv,
        "shown": shown,
        "total": total,
        "data": traces,
        "layout": layout,
    }


def trajectories_figure(
    data: pd.DataFrame,
    *,
    dv: str,
    within: str,
    between: str,
    subject: str,
    max_per_condition: int | None = None,
    title: str | None = None,
    y_label: str | None = None,
    y_range: tuple[float, float] | None = None,
    colors: Mapping[Any, str] | None = None,
) -> go.Figure:
    """Individual trajectories by condition (see :func:`trajectories_payload`)."""
    return figure_from_payload(
        trajectories_payload(
            data,
            dv=dv,
            within=within,
            between=between,
            subject=subject,
            max_per_condition=max_per_condition,
            title=title,
            y_label=y_label,
            y_range=y_range,
            colors=colors,
        )
    )


# --------------------------------------------------------------------------- adaptation


def adaptation_payload(
    steps: pd.DataFrame,
    preferred_arms: Mapping[str, int],
    *,
    confidence: float = 0.95,
    title: str | None = None,
    colors: Mapping[Any, str] | None = None,
) -> dict[str, Any]:
    """Data and traces of the adaptation curves: one panel per category, a line per condition.

    Parameters
    ----------
    steps : pandas.DataFrame
        Step log (see :mod:`analysis.adaptation`).
    preferred_arms : mapping of str to int
        Preferred arm of each category; panels follow its order.
    confidence : float
        Coverage of the band.
    title : str, optional
    colors : mapping, optional
        Colour per condition.

    Returns
    -------
    dict
        ``{"kind": "adaptation", "confidence", "categories", "curves": [...], "data": [...],
        "layout": {...}}``, JSON-serialisable; ``curves`` are the rows of
        :func:`analysis.adaptation.adaptation_curves`.
    """
    curves = adaptation_curves(steps, preferred_arms, confidence=confidence)
    return adaptation_payload_from_curves(
        curves, list(preferred_arms), confidence=confidence, title=title, colors=colors
    )


def adaptation_payload_from_curves(
    curves: Table,
    categories: Sequence[str],
    *,
    confidence: float = 0.95,
    title: str | None = None,
    colors: Mapping[Any, str] | None = None,
) -> dict[str, Any]:
    """:func:`adaptation_payload` from already computed curves (a :data:`Table`: the frame of
    :func:`analysis.adaptation.adaptation_curves`, or the same columns as plain values)."""
    table = _Table(
        curves, ["condition", "category", "iteration", "mean", "ci_low", "ci_high"], "data"
    )
    columns = table.columns
    conditions = table.levels("condition") if table.length else []
    palette = condition_colors(conditions, colors)
    n_panels = max(len(categories), 1)
    gap = 0.04
    layout: dict[str, Any] = {
        **_BASE_LAYOUT,
        "title": {"text": title or "Adaptation: probability of the preferred question"},
        "yaxis": _axis("p(preferred question)", range=[0, 1], anchor="x"),
        "margin": {**_BASE_LAYOUT["margin"], "b": 90},
        "annotations": [],
        "hovermode": "closest",
    }
    traces: list[dict[str, Any]] = []
    for i, category in enumerate(categories):
        axis_id = "" if i == 0 else str(i + 1)
        layout[f"xaxis{axis_id}"] = _axis(
            "Iteration",
            domain=[
                i / n_panels + (gap if i else 0),
                (i + 1) / n_panels - (gap if i < n_panels - 1 else 0),
            ],
            anchor="y",
            dtick=2,
        )
        layout["annotations"].append(
            {
                "text": f"<b>{category}</b>",
                "xref": "paper",
                "yref": "paper",
                "x": (i + 0.5) / n_panels,
                "y": 1.0,
                "yanchor": "bottom",
                "showarrow": False,
            }
        )
        in_category = columns["category"] == category
        for condition in conditions:
            rows = np.flatnonzero(in_category & (columns["condition"] == condition))
            if rows.size == 0:
                continue
            x = _json_list(columns["iteration"][rows])
            low = _json_list(columns["ci_low"][rows])
            high = _json_list(columns["ci_high"][rows])
            color = palette[condition]
            common = {"xaxis": f"x{axis_id}", "yaxis": "y", "legendgroup": str(condition)}
            traces.append(
                {
                    "type": "scatter",
                    "x": x + x[::-1],
                    "y": high + low[::-1],
                    "fill": "toself",
                    "fillcolor": _rgba(color, 0.18),
                    "line": {"width": 0},
                    "hoverinfo": "skip",
                    "showlegend": False,
                    "name": f"{condition} {confidence:.0%} CI",
                    **common,
                }
            )
            traces.append(
                {
                    "type": "scatter",
                    "mode": "lines+markers",
                    "x": x,
                    "y": _json_list(columns["mean"][rows]),
                    "line": {"color": color, "width": 2},
                    "marker": {"size": 5, "color": color},
                    "name": str(condition),
                    "showlegend": i == 0,
                    "customdata": _json_list(columns["n"][rows]) if "n" in columns else None,
                    "hovertemplate": f"{condition}, {category}<br>iteration %{{x}}: "
                    "M = %{y:.3f}<br>n = %{customdata}<extra></extra>",
                    **common,
                }
            )
    return {
        "kind": "adaptation",
        "confidence": confidence,
        "categories": list(categories),
        "curves": table.records(),
        "data": traces,
        "layout": layout,
    }


def adaptation_figure(
    steps: pd.DataFrame,
    preferred_arms: Mapping[str, int],
    *,
    confidence: float = 0.95,
    title: str | None = None,
    colors: Mapping[Any, str] | None = None,
) -> go.Figure:
    """Adaptation curves with confidence bands (see :func:`adaptation_payload`)."""
    return figure_from_payload(
        adaptation_payload(steps, preferred_arms, confidence=confidence, title=title, colors=colors)
    )


# --------------------------------------------------------------------------- trust × confidence


def trust_confidence_payload(
    data: pd.DataFrame,
    *,
    dv: str,
    x: str = "confidence",
    between: str = "condition",
    title: str | None = None,
    x_label: str = "Robot's confidence (mean probability behind its replies)",
    y_label: str | None = None,
    y_range: tuple[float, float] | None = None,
    colors: Mapping[Any, str] | None = None,
) -> dict[str, Any]:
    """Trust against the robot's confidence, one point per participant × session, by condition.

    Each condition gets its points and its least-squares line over the range it covers: a
    description of the joint spread, not the mixed model (whose within- and between-participant
    slopes are in :mod:`analysis.adaptation_trust`).

    Returns
    -------
    dict
        ``{"kind": "trust_confidence", "dv", "x", "data": [...], "layout": {...}}``.
    """
    require_columns(data, [dv, x, between], "trust and adaptation data")
    rows = data[data[dv].notna() & data[x].notna()]
    levels = ordered_levels(rows[between])
    palette = condition_colors(levels, colors)
    traces: list[dict[str, Any]] = []
    for level in levels:
        part = rows[rows[between] == level]
        color = palette[level]
        xs, ys = part[x].to_numpy(float), part[dv].to_numpy(float)
        traces.append(
            {
                "type": "scatter",
                "mode": "markers",
                "name": str(level),
                "legendgroup": str(level),
                "x": _json_list(xs),
                "y": _json_list(ys),
                "marker": {"color": _rgba(color, 0.55), "size": 7},
                "hovertemplate": f"{level}<br>confidence %{{x:.2f}}<br>{dv} %{{y:.2f}}"
                "<extra></extra>",
            }
        )
        if len(xs) >= 2 and np.ptp(xs) > 0:
            slope, intercept = np.polyfit(xs, ys, 1)
            ends = np.array([xs.min(), xs.max()])
            traces.append(
                {
                    "type": "scatter",
                    "mode": "lines",
                    "name": f"{level} (least squares)",
                    "legendgroup": str(level),
                    "showlegend": False,
                    "x": _json_list(ends),
                    "y": _json_list(intercept + slope * ends),
                    "line": {"color": color, "width": 2},
                    "hoverinfo": "skip",
                }
            )
    layout = {
        **_BASE_LAYOUT,
        "title": {"text": title or f"{dv} and the robot's confidence"},
        "xaxis": _axis(x_label, range=[0, 1]),
        "yaxis": _axis(
            y_label or dv,
            **({"range": [y_range[0] - 0.25, y_range[1] + 0.25]} if y_range else {}),
        ),
    }
    return {"kind": "trust_confidence", "dv": dv, "x": x, "data": traces, "layout": layout}


# --------------------------------------------------------------------------- distributions


def score_distribution_payload(
    scores: pd.DataFrame,
    *,
    score: str = "score",
    scale: str = "scale",
    between: str = "condition",
    scale_labels: Mapping[str, str] | None = None,
    title: str | None = None,
    colors: Mapping[Any, str] | None = None,
) -> dict[str, Any]:
    """Box plots of questionnaire scores by condition, one group of boxes per scale.

    Boxes show the raw points when a box has at most :data:`BOX_POINTS_LIMIT` values; above
    that the quartiles and 1.5 IQR whiskers are computed here so the payload stays small.
    """
    scores = require_frame(scores, "scores")
    require_columns(scores, [score, scale, between], "scores")
    scales = list(pd.unique(scores[scale]))
    labels = {s: (scale_labels or {}).get(s, str(s)) for s in scales}
    conditions = ordered_levels(scores[between])
    palette = condition_colors(conditions, colors)
    traces: list[dict[str, Any]] = []
    for condition in conditions:
        rows = scores[(scores[between] == condition) & scores[score].notna()]
        color = palette[condition]
        trace: dict[str, Any] = {
            "type": "box",
            "name": str(to_python(condition)),
            "marker": {"color": color},
            "line": {"color": color},
            "boxmean": True,
        }
        largest_box = int(rows.groupby(scale).size().max()) if len(rows) else 0
        if largest_box <= BOX_POINTS_LIMIT:
            trace.update(
                x=[labels[s] for s in rows[scale]],
                y=_json_list(rows[score].to_numpy()),
                boxpoints="all",
                jitter=0.35,
                pointpos=0,
                marker={"color": color, "size": 4, "opacity": 0.6},
            )
        else:
            stats = _box_stats(rows, scale, score, scales)
            trace.update(x=[labels[s] for s in stats["scale"]], **{k: stats[k] for k in _BOX_KEYS})
        traces.append(trace)
    layout = {
        **_BASE_LAYOUT,
        "title": {"text": title or "Questionnaire scores by condition"},
        "boxmode": "group",
        "xaxis": _axis(""),
        "yaxis": _axis("Score"),
    }
    return {"kind": "score_distribution", "data": traces, "layout": layout}


_BOX_KEYS = ("q1", "median", "q3", "lowerfence", "upperfence", "mean")


def _box_stats(
    rows: pd.DataFrame, scale: str, score: str, scales: Sequence[Any]
) -> dict[str, list[Any]]:
    out: dict[str, list[Any]] = {"scale": [], **{k: [] for k in _BOX_KEYS}}
    for s in scales:
        values = rows.loc[rows[scale] == s, score].to_numpy(float)
        if values.size == 0:
            continue
        q1, median, q3 = np.quantile(values, [0.25, 0.5, 0.75])
        iqr = q3 - q1
        inside = values[(values >= q1 - 1.5 * iqr) & (values <= q3 + 1.5 * iqr)]
        out["scale"].append(s)
        for key, value in zip(
            _BOX_KEYS, (q1, median, q3, inside.min(), inside.max(), values.mean()), strict=True
        ):
            out[key].append(float(value))
    return out


def score_distribution_figure(
    scores: pd.DataFrame,
    *,
    score: str = "score",
    scale: str = "scale",
    between: str = "condition",
    scale_labels: Mapping[str, str] | None = None,
    title: str | None = None,
    colors: Mapping[Any, str] | None = None,
) -> go.Figure:
    """Questionnaire score distributions by condition (see :func:`score_distribution_payload`)."""
    return figure_from_payload(
        score_distribution_payload(
            scores,
            score=score,
            scale=scale,
            between=between,
            scale_labels=scale_labels,
            title=title,
            colors=colors,
        )
    )
