"""``trustlab mixed``: the linear mixed models (and the ordinal model) of a CSV file.

The counterpart of ``trustlab anova`` on the same long CSV. With ``--json`` it prints exactly
one JSON object::

    {"lmm": {…LinearMixedModels.to_dict()…}, "ordinal": {…} | null, "ordinal_skipped": "…"}

The ordinal (proportional-odds) model is fitted when the dependent variable holds whole numbers
with at most 11 distinct values (a single rating item); otherwise ``ordinal`` is null and
``ordinal_skipped`` says why. Progress goes to stderr (one step per model), so the JSON on stdout
stays clean. A model that does not converge says so in one line; bad input prints one line
``error: …`` and exits with status 2.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import pandas as pd
import typer
from tqdm import tqdm

from analysis.apa import format_number
from analysis.errors import AnalysisError
from analysis.lmm import LinearMixedModels, MixedModelFit, linear_mixed_models
from analysis.mixed_prose import comparison_sentence, lmm_sentences, ordinal_sentences
from analysis.ordinal import OrdinalFit, ordinal_model
from app.cli.analysis import bad_input, read_csv_file

__all__ = ["MAX_ORDINAL_CATEGORIES", "mixed_command", "register"]

MAX_ORDINAL_CATEGORIES = 11
"""More distinct whole-number values than this (0–10 scales) is not treated as one item."""


def register(cli: typer.Typer) -> None:
    """Add the ``mixed`` command to the ``trustlab`` command line."""
    cli.command("mixed")(mixed_command)


def mixed_command(
    csv: Annotated[Path, typer.Argument(help="Long-format CSV: one row per subject × level.")],
    dv: Annotated[str, typer.Option("--dv", help="Column of the dependent variable.")],
    within: Annotated[str, typer.Option("--within", help="Within-subject factor (session).")],
    between: Annotated[str, typer.Option("--between", help="Between factor (condition).")],
    subject: Annotated[str, typer.Option("--subject", help="Participant identifier column.")],
    random_slope: Annotated[
        bool,
        typer.Option(
            "--random-slope",
            help="Also fit (1 + within | subject) and compare it with the intercept model.",
        ),
    ] = False,
    as_json: Annotated[
        bool, typer.Option("--json", help="Print one JSON object (the stable contract).")
    ] = False,
) -> None:
    """Linear mixed models (REML, Satterthwaite df) that keep incomplete participants."""
    data = read_csv_file(csv)
    ordinal_reason = _ordinal_reason(data, dv)
    steps = 1 + int(random_slope) + int(not ordinal_reason)
    problem = ""
    with tqdm(total=steps, desc="models", unit="model", file=sys.stderr, leave=False) as bar:
        try:
            bar.set_postfix_str("linear mixed model" + ("s" if random_slope else ""))
            models = linear_mixed_models(
                data,
                dv=dv,
                within=within,
                between=between,
                subject=subject,
                random_slope=random_slope,
            )
            bar.update(1 + int(random_slope))
            ordinal = None
            if not ordinal_reason:
                bar.set_postfix_str("proportional-odds model")
                ordinal = ordinal_model(
                    data, dv=dv, within=within, between=between, subject=subject
                )
                bar.update(1)
        except AnalysisError as error:
            problem = str(error)
    if problem:  # after the bar has cleared its line
        raise bad_input(problem)
    if as_json:
        payload: dict[str, Any] = {
            "lmm": models.to_dict(),
            "ordinal": ordinal.to_dict() if ordinal else None,
            "ordinal_skipped": ordinal_reason,
        }
        typer.echo(json.dumps(payload, allow_nan=False))
    else:
        typer.echo(render_text(models, ordinal, ordinal_reason))


def _ordinal_reason(data: pd.DataFrame, dv: str) -> str:
    """Why the ordinal model is not fitted (empty when it is)."""
    if dv not in data.columns:
        return ""  # linear_mixed_models names the missing column
    values = pd.to_numeric(data[dv], errors="coerce").dropna().to_numpy(float)
    if len(values) == 0 or np.any(values != np.round(values)):
        return f"{dv} is not whole-number ratings (e.g. a scale mean)"
    if len(np.unique(values)) > MAX_ORDINAL_CATEGORIES:
        return f"{dv} has more than {MAX_ORDINAL_CATEGORIES} distinct values"
    return ""


def render_text(models: LinearMixedModels, ordinal: OrdinalFit | None, ordinal_reason: str) -> str:
    """Plain-text summary: each model's status, tests and variances, sentences, who was kept."""
    lines = [
        f"Linear mixed models of {models.dv!r}: {models.between} (between) × {models.within} "
        f"(within), {models.n_obs} ratings of {models.n_subjects} participants",
    ]
    for fit in models.models:
        lines += ["", *_fit_lines(fit)]
    if models.slope is not None:
        lines += ["", comparison_sentence(models)]
    lines += ["", *(f"  {s}" for s in lmm_sentences(models))]
    if len(models.kept):
        lines += ["", "Kept by the mixed model, excluded by the ANOVA:"]
        lines += [f"  {r.subject}: {r.reason}" for r in models.kept.itertuples(index=False)]
    lines.append("")
    if ordinal is not None:
        lines.append(f"Ordinal model: {ordinal.formula}")
        lines += [f"  {s}" for s in ordinal_sentences(ordinal)]
    else:
        lines.append(f"Ordinal model not fitted: {ordinal_reason}.")
    return "\n".join(lines)


def _fit_lines(fit: MixedModelFit) -> list[str]:
    lines = [f"{fit.name}: {fit.formula}"]
    if not fit.converged:
        return [*lines, f"  {fit.problem}"]
    lines.append(
        f"  REML logLik {format_number(fit.loglik, 2)}, AIC {format_number(fit.aic, 1)}, "
        f"optimizer {fit.optimizer}, {fit.df_method} df; {fit.status}"
    )
    header = ("Effect", "F", "df1", "df2", "p")
    rows = [header] + [
        (
            str(r["Source"]),
            format_number(r["F"], 3),
            format_number(r["df1"], 0),
            format_number(r["df2"], 2),
            _p(r["p"]),
        )
        for r in fit.tests.to_dict("records")
    ]
    lines += _aligned(rows)
    lines += [
        f"  {r['component']}: SD {format_number(r['sd'], 3)}"
        + ("" if np.isnan(r["corr"]) else f", corr {format_number(r['corr'], 3)}")
        for r in fit.variance.to_dict("records")
    ]
    return lines


def _aligned(rows: Sequence[tuple[str, ...]]) -> list[str]:
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    return [
        "  "
        + "  ".join(
            c.ljust(widths[i]) if i == 0 else c.rjust(widths[i]) for i, c in enumerate(r)
        ).rstrip()
        for r in rows
    ]


def _p(value: float) -> str:
    if value != value:  # NaN
        return "—"
    return "<.001" if value < 0.001 else f"{value:.4f}"
