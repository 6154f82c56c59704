"""The power curve over N: the ANOVA's analytic power and the mixed model's simulated power.

One figure a PI can attach to an ethics application: how power grows with the number of
participants, the analytic line (G*Power's formulas) and the simulated points of the model
trustlab will actually fit, each with its Monte-Carlo interval. Self-contained HTML (plotly.js
inline), because labs often have no internet.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import plotly.graph_objects as go

from analysis.power import PowerDesign
from analysis.power_simulation import SimulatedPower

__all__ = ["power_curve_figure", "write_power_curve"]


def power_curve_figure(
    design: PowerDesign, f: float, simulated: Sequence[SimulatedPower], target: float | None = None
) -> go.Figure:
    """Analytic power over N (a line) and the simulated points with Wilson intervals."""
    n_values = [s.n_total for s in simulated]
    k = design.groups
    low = max(k + 1, min(n_values) - k)
    dense = np.arange(low, max(n_values) + k + 1)
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
            name="mixed model, simulated (95 % Wilson interval)",
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
