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
from typing import TYPE_CHECKING, Annotated, Any

import typer

from app.cli.analysis import bad_input, read_csv_file

if TYPE_CHECKING:
    import pandas as pd

    from analysis.lmm import LinearMixedModels, MixedModelFit
    from analysis.ordinal import OrdinalFit


__all__ = ["mixed_command", "register"]


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
    within_levels: Annotated[
        str,
        typer.Option(
            "--within-levels",
            help="The within levels in order, comma-separated (e.g. pre,mid,post); default: "
            "numbers ascending, text in natural order (S2 before S10).",
        ),
    ] = "",
    covariate: Annotated[
        list[str] | None,
        typer.Option(
            "--covariate",
            help="A participant-level categorical column added to the linear models as a main "
            "effect (e.g. language in a study run in several; repeatable).",
        ),
    ] = None,
    as_json: Annotated[
        bool, typer.Option("--json", help="Print one JSON object (the stable contract).")
    ] = False,
) -> None:
    """Linear mixed models (REML, Satterthwaite df) that keep incomplete participants."""
    from tqdm import tqdm

    from analysis.errors import AnalysisError
    from analysis.lmm import linear_mixed_models
    from analysis.ordinal import ordinal_model

    data = read_csv_file(csv)
    levels = _declared_levels(within_levels, data, within)
    ordinal_reason = _ordinal_reason(data, dv)
    steps = 1 + int(random_slope) + int(not ordinal_reason)
    problem = ""
    ordinal = None
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
                within_levels=levels,
                covariates=tuple(covariate or ()),
            )
            bar.update(1 + int(random_slope))
        except AnalysisError as error:
            problem = str(error)
        if not problem and not ordinal_reason:
            bar.set_postfix_str("proportional-odds model")
            try:  # its failure must not hide the linear models
                ordinal = ordinal_model(
                    data,
                    dv=dv,
                    within=within,
                    between=between,
                    subject=subject,
                    within_levels=levels,
                )
            except AnalysisError as error:
                ordinal_reason = str(error)
            bar.update(1)
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


def _declared_levels(text: str, data: pd.DataFrame, within: str) -> list[Any] | None:
    """``--within-levels`` as values of the column's type (numbers when the column is numeric)."""
    import pandas as pd

    if not text:
        return None
    levels: list[Any] = [part.strip() for part in text.split(",") if part.strip()]
    if within in data.columns and pd.api.types.is_numeric_dtype(data[within]):
        try:
            numbers = [float(level) for level in levels]
        except ValueError:
            raise bad_input(
                f"--within-levels: {within!r} holds numbers, so the levels must be numbers: {text}"
            ) from None
        levels = [int(n) if n.is_integer() else n for n in numbers]
    return levels


def _ordinal_reason(data: pd.DataFrame, dv: str) -> str:
    """Why the ordinal model is not fitted (empty when it is)."""
    import numpy as np
    import pandas as pd

    from analysis.ordinal import not_single_item

    if dv not in data.columns:
        return ""  # linear_mixed_models names the missing column
    values = pd.to_numeric(data[dv], errors="coerce").to_numpy(float)
    if not np.isfinite(values).any():
        return f"{dv} has no numeric ratings"
    return not_single_item(values, dv)


def render_text(models: LinearMixedModels, ordinal: OrdinalFit | None, ordinal_reason: str) -> str:
    """Plain-text summary: each model's status, tests and variances, the comparison, sentences,
    the marginal means, who was kept; a model that failed says so once, in its own line."""
    from analysis.apa import format_number
    from analysis.mixed_prose import comparison_sentence, lmm_sentences, ordinal_sentences

    steps = ", ".join(f"{level} = {i}" for i, level in enumerate(models.within_levels))
    lines = [
        f"Linear mixed models of {models.dv!r}: {models.between} (between) × {models.within} "
        f"(within), {models.n_obs} ratings of {models.n_subjects} participants",
        f"{models.within} levels in order (slope steps): {steps}",
    ]
    for fit in models.models:
        lines += ["", *_fit_lines(fit)]
    comparison = comparison_sentence(models)
    if comparison:
        lines += ["", comparison]
    preferred = models.preferred
    if preferred.converged:
        lines += ["", *(f"  {s}" for s in lmm_sentences(models))]
        lines += ["", f"Estimated marginal means ({preferred.name} model, 95 % CI):"]
        lines += _aligned(
            [("", models.between, models.within, "EMM", "SE", "df", "95 % CI")]
            + [
                (
                    "",
                    str(r[models.between]),
                    str(r[models.within]),
                    format_number(r["emmean"], 3),
                    format_number(r["se"], 3),
                    format_number(r["df"], 1),
                    f"[{format_number(r['ci_low'], 3)}, {format_number(r['ci_high'], 3)}]",
                )
                for r in preferred.emmeans.to_dict("records")
            ]
        )
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
    import numpy as np

    from analysis.apa import format_number

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
