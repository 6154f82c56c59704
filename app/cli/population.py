"""``trustlab population fit``: a study's population from its step log, as a verified file.

Reads the steps of one or more stored studies (or an exported steps CSV), fits each category's
prior over the preferred question, slip rate and hazard by EM with bootstrap intervals over
participants (app/services/sessions/population_fit.py), writes the population file and, beside it, a
figure of the fitted prior with its intervals (``FILE-stem.prior.html``), and prints a one-page
summary. Nothing is written when the input is unusable.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from app.cli.common import JsonFlag, emit_json, open_database, require_current_schema
from app.errors import InvalidInput

if TYPE_CHECKING:
    import pandas as pd

    from analysis.population import Population


population_cli = typer.Typer(help="Populations fitted from earlier participants.")


def register(cli: typer.Typer) -> None:
    """Attach ``population`` to the top-level command."""
    cli.add_typer(population_cli, name="population")


@population_cli.command("fit")
def fit(
    out: Annotated[Path, typer.Option("--out", help="The population file to write.")],
    study: Annotated[
        list[str] | None, typer.Option("--study", help="A stored study (repeat for several).")
    ] = None,
    steps: Annotated[
        Path | None, typer.Option("--steps", help="An exported steps CSV instead of studies.")
    ] = None,
    replicates: Annotated[
        int, typer.Option("--replicates", help="Bootstrap resamples per category.")
    ] = 200,
    seed: Annotated[int, typer.Option("--seed", help="Seed of the bootstrap.")] = 0,
    enrolling_reason: Annotated[
        str | None,
        typer.Option(
            "--enrolling-reason",
            help="Fit from a study that is still enrolling anyway, for this reason (recorded).",
        ),
    ] = None,
    as_json: JsonFlag = False,
) -> None:
    """Fit the population (prior, slip rate, hazard per category) of earlier participants."""
    from analysis.population import write_population, write_prior_figure
    from app.services.sessions.population_fit import fit_population

    if (not study) == (steps is None):
        raise InvalidInput("give either --study NAME (one or more) or --steps CSV")
    if replicates < 1:
        raise InvalidInput("--replicates must be at least 1")
    if out.is_dir():
        raise InvalidInput(f"--out {out} is a directory: give the population file's path")
    figure = out.with_name(out.stem + ".prior.html")
    if enrolling_reason is not None and not enrolling_reason.strip():
        raise InvalidInput("--enrolling-reason needs the reason, in words")
    if enrolling_reason is not None and steps is not None:
        raise InvalidInput(
            "--enrolling-reason is for --study: a steps CSV does not say whether its study is "
            "still enrolling (check that it is closed before exporting it)"
        )
    if steps is not None:
        frame, source, arms = _from_csv(steps)
    else:
        frame, source, arms = _from_studies(study or [], enrolling_reason)
    total = replicates * frame["category"].nunique()
    with typer.progressbar(length=total, label="bootstrap", file=None, hidden=as_json) as bar:
        population = fit_population(
            frame,
            source,
            arms=arms,
            replicates=replicates,
            seed=seed,
            progress=lambda: bar.update(1),
        )
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        write_population(out, population)
        write_prior_figure(figure, population)
    except OSError as exc:
        raise InvalidInput(f"cannot write {out}: {exc}") from None
    if as_json:
        emit_json(
            {"path": str(out), "figure": str(figure), "sha256": population.sha256}
            | population.content
        )
    else:
        typer.echo(summary(population, out) + f"\n\nfigure of the fitted prior: {figure}")


def _from_csv(path: Path) -> tuple[pd.DataFrame, dict[str, Any], dict[str, int] | None]:
    import pandas as pd

    from analysis.population import STEP_COLUMNS

    try:
        frame = pd.read_csv(path)
    except (OSError, UnicodeDecodeError, pd.errors.ParserError, pd.errors.EmptyDataError) as exc:
        raise InvalidInput(f"cannot read the steps CSV {path}: {exc}") from None
    missing = [column for column in STEP_COLUMNS if column not in frame.columns]
    if missing:
        raise InvalidInput(f"{path}: the steps CSV lacks the column(s) {', '.join(missing)}")
    return frame, {"steps": str(path)}, None


def _from_studies(
    names: list[str], enrolling_reason: str | None
) -> tuple[pd.DataFrame, dict[str, Any], dict[str, int]]:
    """The studies' steps, their questions and K per category. A study still enrolling is
    refused unless the lab records why (docs/engine.md: a prior fitted on a running study's
    participants confounds a between-subjects comparison)."""
    import pandas as pd

    from analysis.exports.tables import steps_table
    from app.services import studies
    from app.services.analysis_views import study_data
    from app.services.privacy.sites import Scope
    from app.settings import Settings
    from app.tables import StudyStatus

    database = open_database(Settings())
    require_current_schema(database)
    frames: list[pd.DataFrame] = []
    questions: dict[str, list[str]] = {}
    statuses: dict[str, str] = {}
    with database.read_session() as db:
        for name in names:
            found = studies.get_study(db, name)
            dataset = study_data.load_dataset(db, study=found, scope=Scope.every_site())
            for category, texts in dataset.protocol["categories"].items():
                if questions.setdefault(category, list(texts)) != list(texts):
                    raise InvalidInput(
                        f"category {category!r} asks other questions in {name!r} than in "
                        f"{names[0]!r}: a population is fitted over one set of questions"
                    )
            frame = steps_table(dataset)
            frame["participant"] = name + "/" + frame["participant"].astype(str)
            frames.append(frame)
            statuses[name] = found.status
    enrolling = sorted(name for name, status in statuses.items() if status == StudyStatus.OPEN)
    if enrolling and enrolling_reason is None:
        raise InvalidInput(
            f"{', '.join(enrolling)} is still enrolling: a prior fitted on a running study's "
            "participants confounds its conditions; close its enrolment first (its study page) or "
            "pass --enrolling-reason TEXT"
        )
    steps = pd.concat(frames, ignore_index=True)
    if steps.empty:
        raise InvalidInput(f"{', '.join(names)}: no answered steps to fit a population from")
    source: dict[str, Any] = {
        "studies": names,
        "status_when_fitted": statuses,
        "questions": questions,
    }
    if enrolling:
        source["enrolling_reason"] = enrolling_reason
    return steps, source, {category: len(texts) for category, texts in questions.items()}


def summary(population: Population, path: Path) -> str:
    """The one-page summary: per category N, the prior with its intervals, slip and hazard."""
    source = population.content["source"]
    where = ", ".join(source["studies"]) if "studies" in source else source["steps"]
    lines = [
        f"population fitted from {where} (steps sha256 {source['steps_sha256'][:12]}…)",
        f"written to {path} (sha256 {population.sha256[:12]}…); 95 % bootstrap intervals",
    ]
    for name, fitted in population.categories.items():
        lines.append("")
        lines.append(
            f"{name}: {fitted['participants']} participants, {fitted['answers']} answers"
            + ("" if fitted["converged"] else " (EM did not converge)")
        )
        for k, (p, (low, high)) in enumerate(zip(fitted["prior"], fitted["prior_ci"], strict=True)):
            lines.append(f"  question {k}: p(preferred) {p:.3f}  [{low:.3f}, {high:.3f}]")
        lines.append(
            f"  slip {fitted['slip']:.3f} [{fitted['slip_ci'][0]:.3f}, {fitted['slip_ci'][1]:.3f}]"
            f"   hazard {fitted['hazard']:.3f} "
            f"[{fitted['hazard_ci'][0]:.3f}, {fitted['hazard_ci'][1]:.3f}]"
        )
    return "\n".join(lines)
