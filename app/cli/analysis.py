"""``trustlab anova``: the mixed ANOVA of a CSV file from the command line.

The main ``trustlab`` Typer app calls :func:`register`. With ``--json`` the command prints
exactly one JSON object, the contract used by external checks::

    {"ss_type": 3, "n_subjects_used": N,
     "excluded_subjects": [{"subject": …, "reason": …}],
     "effects": {"between": E, "within": E, "interaction": E},
     "sphericity": {"W": …, "p": …, "eps_gg": …}}

where ``E = {"F", "df1", "df2", "p", "np2", "ng2", "p_gg" (within and interaction only)}``.
Bad input (missing file or column, duplicates, degenerate data) prints one line
``error: …`` on stderr and exits with status 2, without a traceback.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

if TYPE_CHECKING:
    import pandas as pd

    from analysis.anova import MixedAnovaResult


__all__ = ["EXIT_BAD_INPUT", "anova_command", "bad_input", "read_csv_file", "register"]

EXIT_BAD_INPUT = 2
"""Exit status for unusable input (as for command-line usage errors)."""


def register(cli: typer.Typer) -> None:
    """Add the ``anova`` command to the ``trustlab`` command line."""
    cli.command("anova")(anova_command)


def bad_input(message: str) -> typer.Exit:
    """Print ``error: message`` (one line) and return the exit to raise (status 2)."""
    typer.echo("error: " + " ".join(message.split()), err=True)
    return typer.Exit(EXIT_BAD_INPUT)


def read_csv_file(path: Path) -> pd.DataFrame:
    """Read a CSV file, turning every way it can be unreadable into one ``error:`` line."""
    import pandas as pd

    if not path.exists():
        raise bad_input(f"no such file: {path}")
    if path.is_dir():
        raise bad_input(f"{path} is a directory, not a CSV file")
    try:
        return pd.read_csv(path)
    except pd.errors.EmptyDataError:
        raise bad_input(f"{path} is empty") from None
    except (pd.errors.ParserError, UnicodeDecodeError, PermissionError) as error:
        raise bad_input(f"cannot read {path} as CSV: {error}") from None


def anova_command(
    csv: Annotated[Path, typer.Argument(help="Long-format CSV: one row per subject × level.")],
    dv: Annotated[str, typer.Option("--dv", help="Column of the dependent variable.")],
    within: Annotated[str, typer.Option("--within", help="Within-subject factor (session).")],
    between: Annotated[str, typer.Option("--between", help="Between factor (condition).")],
    subject: Annotated[str, typer.Option("--subject", help="Participant identifier column.")],
    ss_type: Annotated[
        int, typer.Option("--ss-type", help="Sums of squares: 3 (SPSS/JASP/afex) or 2.")
    ] = 3,
    as_json: Annotated[
        bool, typer.Option("--json", help="Print one JSON object (the stable contract).")
    ] = False,
) -> None:
    """Mixed ANOVA (between × within) with sphericity statistics, type III by default."""
    from analysis.anova import mixed_anova
    from analysis.errors import AnalysisError

    if ss_type not in (2, 3):
        raise bad_input(f"--ss-type must be 2 or 3, not {ss_type}")
    data = read_csv_file(csv)
    try:
        result = mixed_anova(
            data,
            dv=dv,
            within=within,
            between=between,
            subject=subject,
            ss_type=3 if ss_type == 3 else 2,
        )
    except AnalysisError as error:
        raise bad_input(str(error)) from None
    if as_json:
        typer.echo(json.dumps(result.to_dict(), allow_nan=False))
    else:
        typer.echo(render_table(result))


def render_table(result: MixedAnovaResult) -> str:
    """A readable plain-text summary: the ANOVA table, sphericity, APA lines and exclusions."""
    from analysis.apa import anova_sentences, format_df, format_number, sphericity_sentence

    design = result.design
    kind = "III" if result.ss_type == 3 else "II"
    lines = [
        f"Mixed ANOVA of {design.dv!r}: {design.between} (between) × {design.within} (within), "
        f"type {kind} sums of squares",
        f"{result.n_subjects_used} participants used, {len(result.excluded)} excluded",
        "",
    ]
    header = ("Effect", "F", "df1", "df2", "p", "np2", "ng2", "eps", "p_GG")
    rows = [header]
    for row in result.table.to_dict("records"):
        rows.append(
            (
                str(row["Source"]),
                format_number(row["F"], 3),
                format_df(row["DF1"]),
                format_df(row["DF2"]),
                _p(row["p_unc"]),
                format_number(row["np2"], 3),
                format_number(row["ng2"], 3),
                format_number(row["eps"], 3),
                _p(row["p_GG_corr"]),
            )
        )
    widths = [max(len(r[i]) for r in rows) for i in range(len(header))]
    for r in rows:
        lines.append(
            "  ".join(
                cell.ljust(widths[i]) if i == 0 else cell.rjust(widths[i])
                for i, cell in enumerate(r)
            ).rstrip()
        )
    lines += ["", sphericity_sentence(result), ""]
    lines += [f"  {text}" for text in anova_sentences(result)["text"]]
    if len(result.excluded):
        lines += ["", "Excluded:"]
        lines += [f"  {r.subject}: {r.reason}" for r in result.excluded.itertuples(index=False)]
    return "\n".join(lines)


def _p(value: float) -> str:
    if value != value:  # NaN
        return "—"
    return "<.001" if value < 0.001 else f"{value:.4f}"
