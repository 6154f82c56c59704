"""The power curve over N: the ANOVA's analytic power and the mixed model's simulated power.

One figure a PI can attach to an ethics application: how power grows with the number of
participants, the analytic line (G*Power's formulas) and the simulated points of the model
trustlab will actually fit, each with its Monte-Carlo interval. Self-contained HTML (plotly.js
inline), because labs often have no internet. The analysis page draws the analytic line alone
from a payload (:func:`power_curve_payload`, a plain dict as :mod:`analysis.figures`' payloads),
because it answers as the form is filled in and a simulation takes seconds.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import plotly.graph_objects as go

from analysis.errors import InvalidInputError
from analysis.power import PowerDesign, n_for_power
from analysis.power_simulation import SIMULATED_MODEL_NAMES, SimulatedPower

__all__ = ["curve_totals", "power_curve_figure", "power_curve_payload", "write_power_curve"]

CURVE_POINTS = 60
"""At most this many totals on the analytic curve (every multiple of k, or evenly spaced)."""


def curve_totals(groups: int, n_total: int) -> list[int]:
    """Totals N (multiples of ``groups``) from 2 per group to about twice ``n_total``, at most
    :data:`CURVE_POINTS` of them, ``n_total`` among them."""
    high = max(2 * n_total, 8 * groups)
    per_group = np.unique(np.linspace(2, high // groups, CURVE_POINTS).round().astype(int))
    return sorted({int(groups * p) for p in per_group} | {n_total})


def power_curve_payload(
    design: PowerDesign,
    f: float,
    *,
    n_total: int,
    target: float | None = None,
    title: str | None = None,
) -> dict[str, Any]:
    """The analytic power over N as a Plotly payload, ``n_total`` marked.

    Returns
    -------
    dict
        ``{"kind": "power_curve", "n", "power", "data": [...], "layout": {...}}``; powers at
        N ≤ k (no error df) are left out.
    """
    reach = n_total
    if f > 0:  # on to where the test is all but sure (.95), so the curve shows its shape
        try:
            reach = max(reach, min(n_for_power(design, f=f, target=0.95).n_total, 20 * n_total))
        except InvalidInputError:
            reach = 20 * n_total
    totals = [n for n in curve_totals(design.groups, max(n_total, reach // 2)) if n > design.groups]
    if n_total not in totals and n_total > design.groups:
        totals = sorted([*totals, n_total])
    powers = [design.power(f, n) for n in totals]
    data: list[dict[str, Any]] = [
        {
            "type": "scatter",
            "mode": "lines",
            "x": totals,
            "y": powers,
            "name": f"power (f = {f:.3f})",
            "hovertemplate": "N = %{x}: power %{y:.3f}<extra></extra>",
        },
        {
            "type": "scatter",
            "mode": "markers",
            "x": [n_total],
            "y": [design.power(f, n_total)],
            "name": f"N = {n_total}",
            "marker": {"size": 11},
            "hovertemplate": "N = %{x}: power %{y:.3f}<extra></extra>",
        },
    ]
    shapes = []
    if target is not None:
        shapes.append(
            {
                "type": "line",
                "xref": "paper",
                "x0": 0,
                "x1": 1,
                "y0": target,
                "y1": target,
                "line": {"dash": "dot", "color": "#888"},
            }
        )
    layout = {
        "title": {"text": title or _title(design)},
        "xaxis": {"title": {"text": "participants in total (N)"}, "gridcolor": "#e5e5e5"},
        "yaxis": {"title": {"text": "power"}, "range": [0, 1.02], "gridcolor": "#e5e5e5"},
        "shapes": shapes,
        "paper_bgcolor": "white",
        "plot_bgcolor": "white",
        "margin": {"l": 60, "r": 20, "t": 60, "b": 60},
        "showlegend": True,
        "legend": {"orientation": "h", "x": 0, "y": -0.25},
    }
    return {"kind": "power_curve", "n": totals, "power": powers, "data": data, "layout": layout}


def _title(design: PowerDesign) -> str:
    """The curve's title: the design, with only the values its test uses (ρ is in an SPSS η²;
    ε does not enter the between effect), so the title never shows a value the answer says is
    not used."""
    used = design.to_dict()
    parts = [f"{design.groups} groups × {design.sessions} sessions"]
    if used["rho_used"] and design.rho is not None:
        parts.append(f"ρ = {design.rho:.2f}")
    if used["epsilon_used"]:
        parts.append(f"ε = {design.epsilon:.3g}")
    parts.append(f"α = {design.alpha:g}")
    if design.convention == "spss":
        parts.append("η² as in SPSS")
    return f"Power of the {design.effect} test: {', '.join(parts)}"


def power_curve_figure(
    design: PowerDesign, f: float, simulated: Sequence[SimulatedPower], target: float | None = None
) -> go.Figure:
    """Analytic power over N (a line) and the simulated points with Wilson intervals."""
    n_values = [s.n_total for s in simulated]
    k = design.groups
    low = max(k + 1, min(n_values) - k)
    dense = np.arange(low, max(n_values) + k + 1)
    fitted = SIMULATED_MODEL_NAMES[simulated[0].kind if simulated else "lmm"]
    figure = go.Figure()
    figure.add_trace(
        go.Scatter(
            x=dense,
            y=[design.power(f, int(n)) for n in dense],
            mode="lines",
            name=f"RM-ANOVA, analytic (f = {f:.3f}, ρ = {design.rho}, ε = {design.epsilon:.3g})",
        )
    )
    figure.add_trace(
        go.Scatter(
            x=n_values,
            y=[s.power for s in simulated],
            mode="markers",
            name=f"{fitted}, simulated (95 % Wilson interval)",
            error_y={
                "type": "data",
                "symmetric": False,
                "array": [s.ci_high - s.power for s in simulated],
                "arrayminus": [s.power - s.ci_low for s in simulated],
            },
        )
    )
    if target is not None:
        figure.add_hline(y=target, line_dash="dot", annotation_text=f"target {target:g}")
    replicates = simulated[0].replicates if simulated else 0
    figure.update_layout(
        title=f"Power of the {design.effect} test, {k} groups × {design.sessions} sessions, "
        f"α = {design.alpha:g} ({replicates} datasets per N)",
        xaxis_title="participants in total (N)",
        yaxis_title="power",
        yaxis_range=[0, 1.02],
        template="plotly_white",
    )
    return figure


def write_power_curve(path: Path, figure: go.Figure) -> None:
    """The figure as a self-contained HTML page, written whole or not at all."""
    html = figure.to_html(full_html=True, include_plotlyjs=True)
    temporary = path.with_name(path.name + ".tmp")
    temporary.write_text(html, encoding="utf-8")
    temporary.replace(path)
