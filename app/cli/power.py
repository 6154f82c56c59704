"""``trustlab power``: how many participants, and why, before the study runs.

Exactly one of three things is left open and answered: the power (``--n`` and an effect size),
the total N for a target power (``--target-power`` and an effect size) or the smallest
detectable effect (``--n`` and ``--target-power``, no effect size). The effect size is Cohen's
``--f``, a partial ``--eta2`` (read under ``--convention gpower|spss``), or a ``--means`` table
with its ``--sd``; ``--pilot`` estimates ρ, ε and the effects from a stored study or a long CSV.
The formulas are :mod:`analysis.power`'s. With ``--json`` it prints one object (the
:meth:`analysis.power.PowerAnswer.to_dict` contract); bad input prints one line ``error: …``
and exits with status 2.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from app.cli.analysis import bad_input, read_csv_file

if TYPE_CHECKING:
    import numpy as np
    import pandas as pd

    from analysis.power import PowerAnswer
    from analysis.power_ordinal import LatentOrdinalModel
    from analysis.power_pilot import PilotEstimate
    from analysis.power_simulation import SimulatedPower


__all__ = ["parse_means", "power_command", "register", "render_answer"]


def register(cli: typer.Typer) -> None:
    """Add the ``power`` command to the ``trustlab`` command line."""
    cli.command("power")(power_command)


def power_command(
    effect: Annotated[
        str,
        typer.Option("--effect", help="The effect to plan for: between, within or interaction."),
    ],
    groups: Annotated[
        int | None, typer.Option("--groups", help="Between levels k (conditions).")
    ] = None,
    sessions: Annotated[
        int | None, typer.Option("--sessions", help="Within levels m (sessions).")
    ] = None,
    f: Annotated[float | None, typer.Option("--f", help="Cohen's f of the effect.")] = None,
    eta2: Annotated[
        float | None,
        typer.Option("--eta2", help="Partial eta² of the effect, read under --convention."),
    ] = None,
    convention: Annotated[
        str,
        typer.Option(
            "--convention",
            help="How the effect size is read: gpower (G*Power's default: f of the population, "
            "with rho) or spss (G*Power's 'as in SPSS': the partial eta² an ANOVA table prints, "
            "rho already in it).",
        ),
    ] = "gpower",
    means: Annotated[
        str | None,
        typer.Option(
            "--means",
            help="Cell means, a row per group, sessions by commas, groups by semicolons "
            "(e.g. '3.0,2.4;2.9,3.2'): f from the table, as G*Power's effect size from means.",
        ),
    ] = None,
    sd: Annotated[
        str | None,
        typer.Option("--sd", help="With --means: one SD, or one per mean in the same layout."),
    ] = None,
    rho: Annotated[
        float | None,
        typer.Option("--rho", help="Correlation among the repeated measures, in (−1, 1)."),
    ] = None,
    epsilon: Annotated[
        float | None,
        typer.Option(
            "--epsilon", help="Non-sphericity correction ε in [1/(m − 1), 1] (default 1)."
        ),
    ] = None,
    alpha: Annotated[float, typer.Option("--alpha", help="Significance level.")] = 0.05,
    n: Annotated[int | None, typer.Option("--n", help="Total number of participants.")] = None,
    target_power: Annotated[
        float | None, typer.Option("--target-power", help="The power to reach, in (0, 1).")
    ] = None,
    pilot: Annotated[
        str | None,
        typer.Option(
            "--pilot",
            help="A stored study's name or a long CSV: rho, epsilon and f estimated from its "
            "complete participants (bootstrap intervals), unless given.",
        ),
    ] = None,
    dv: Annotated[
        str | None,
        typer.Option(
            "--dv", help="With --pilot: the rating column of the CSV, or the study's measure."
        ),
    ] = None,
    within: Annotated[
        str, typer.Option("--within", help="With a --pilot CSV: the session column.")
    ] = "session",
    between: Annotated[
        str, typer.Option("--between", help="With a --pilot CSV: the condition column.")
    ] = "condition",
    subject: Annotated[
        str, typer.Option("--subject", help="With a --pilot CSV: the participant column.")
    ] = "participant",
    replicates: Annotated[
        int, typer.Option("--replicates", help="With --pilot: bootstrap resamples.")
    ] = 500,
    seed: Annotated[
        int, typer.Option("--seed", help="Seed of the bootstrap and of the simulation.")
    ] = 0,
    simulate: Annotated[
        int | None,
        typer.Option(
            "--simulate",
            help="Also simulate this many datasets at the N asked or found and fit each with "
            "the --model (power with a Monte-Carlo interval).",
        ),
    ] = None,
    model: Annotated[
        str,
        typer.Option(
            "--model",
            help="With --simulate: the model fitted to each dataset: lmm (the random-intercept "
            "linear mixed model) or ordinal (the proportional-odds model of one Likert item, "
            "datasets from a latent logistic model with a random intercept).",
        ),
    ] = "lmm",
    categories: Annotated[
        int | None,
        typer.Option(
            "--categories",
            help="With --model ordinal and no --pilot: rating categories K (default 5), "
            "thresholds equally spaced on the latent scale.",
        ),
    ] = None,
    curve: Annotated[
        Path | None,
        typer.Option(
            "--curve",
            help="With --simulate: write the power curve over N (analytic and simulated) as "
            "a self-contained HTML page.",
        ),
    ] = None,
    as_json: Annotated[
        bool, typer.Option("--json", help="Print one JSON object (the stable contract).")
    ] = False,
) -> None:
    """Power, sample size or detectable effect of the mixed ANOVA's between, within or
    interaction test (G*Power 3.1's formulas), from effect sizes or a pilot."""
    # The pilot's and the simulations' modules (numpy, pandas, SciPy, the mixed models) are
    # imported in their branches below: an analytic answer is pure Python (analysis.power).
    import math

    from analysis.errors import AnalysisError, InvalidInputError
    from analysis.power import EFFECTS
    from analysis.power_models import SIMULATED_MODELS

    estimate: PilotEstimate | None = None
    pilot_data: tuple[pd.DataFrame, dict[str, str]] | None = None
    population: LatentOrdinalModel | None = None
    try:
        _check_model_options(model, simulate, categories, pilot)
        if pilot is not None:
            from analysis.power_pilot import estimate_pilot

            data, columns = read_pilot(pilot, dv, within=within, between=between, subject=subject)
            pilot_data = (data, columns)
            estimate = estimate_pilot(
                data,
                dv=columns["dv"],
                within=columns["within"],
                between=columns["between"],
                subject=columns["subject"],
                replicates=replicates,
                seed=seed,
            )
            groups = estimate.groups if groups is None else groups
            sessions = estimate.sessions if sessions is None else sessions
            rho = estimate.estimates["rho"] if rho is None else rho
            if (
                epsilon is None
                and effect != "between"
                and math.isfinite(estimate.estimates["epsilon"])
            ):
                epsilon = max(estimate.estimates["epsilon"], 1 / max(sessions - 1, 1))
            if f is None and eta2 is None and means is None and not (n and target_power):
                f = estimate.f(effect) if effect in EFFECTS else None
        answer = answer_question(
            effect=effect,
            groups=groups,
            sessions=sessions,
            f=f,
            eta2=eta2,
            convention=convention,
            means=means,
            sd=sd,
            rho=rho,
            epsilon=epsilon,
            alpha=alpha,
            n=n,
            target_power=target_power,
        )
        bracket = _bracket(answer, estimate)
        if curve is not None and simulate is None:
            raise InvalidInputError("--curve draws the simulated power: add --simulate R")
        simulated: list[SimulatedPower] = []
        if simulate is not None:
            from tqdm import tqdm

            from analysis.power_ordinal import simulate_ordinal_power_curve
            from analysis.power_simulation import simulate_power_curve

            table, spread = _simulation_model(answer, estimate, means, sd)
            if model == "ordinal":
                population = _ordinal_population(
                    answer, estimate, pilot_data, table, spread, categories
                )
            n_values = _curve_n(answer) if curve is not None else [answer.n_total]
            with tqdm(
                total=simulate * len(n_values),
                desc="datasets",
                unit="fit",
                file=sys.stderr,
                leave=False,
            ) as bar:
                if population is not None:
                    simulated = simulate_ordinal_power_curve(
                        answer.design.effect,
                        population=population,
                        n_values=n_values,
                        replicates=simulate,
                        seed=seed,
                        alpha=answer.design.alpha,
                        progress=lambda: bar.update(1),
                    )
                else:
                    simulated = simulate_power_curve(
                        answer.design.effect,
                        means=table,
                        sd=spread,
                        rho=answer.design.rho if answer.design.rho is not None else float("nan"),
                        n_values=n_values,
                        replicates=simulate,
                        seed=seed,
                        alpha=answer.design.alpha,
                        progress=lambda: bar.update(1),
                    )
            if curve is not None:
                from analysis.power_figures import power_curve_figure, write_power_curve

                figure = power_curve_figure(answer.design, answer.f, simulated, answer.target_power)
                try:
                    write_power_curve(curve, figure)
                except OSError as error:
                    raise InvalidInputError(f"cannot write {curve}: {error}") from None
    except AnalysisError as error:
        raise bad_input(str(error)) from None
    at_n = next((s for s in simulated if s.n_total == answer.n_total), None)
    if as_json:
        payload = answer.to_dict()
        if estimate is not None:
            payload["pilot"] = estimate.to_dict()
            payload["pilot"]["source"] = pilot
            payload["pilot_range"] = {k: v.to_dict() for k, v in bracket.items()}
        if simulated:
            payload["simulated_model"] = {
                "kind": model,
                "description": SIMULATED_MODELS[model],
                "population": population.to_dict()
                if population is not None
                else {"cell_means": table.tolist(), "sd": spread, "rho": answer.design.rho},
            }
            payload["simulation"] = at_n.to_dict() if at_n else None
            payload["curve"] = [s.to_dict() for s in simulated] if curve is not None else None
            payload["curve_file"] = str(curve) if curve is not None else None
        typer.echo(json.dumps(_finite(payload), allow_nan=False))
    else:
        text = render_answer(answer)
        if estimate is not None:
            text = render_pilot(estimate, pilot or "", bracket) + "\n\n" + text
        if simulated:
            text += "\n\n" + render_simulation(simulated, at_n, curve, population)
        typer.echo(text)


def _simulation_model(
    answer: PowerAnswer, estimate: PilotEstimate | None, means: str | None, sd: str | None
) -> tuple[np.ndarray, float]:
    """The cell means and SD the datasets are drawn from: the pilot's or the --means table's
    when the answer's f is theirs, else a pattern with the answer's f (SD 1)."""
    import numpy as np

    from analysis.errors import InvalidInputError
    from analysis.power import effect_sizes_from_means
    from analysis.power_simulation import effect_pattern

    design = answer.design
    if design.convention != "gpower" or design.rho is None:
        raise InvalidInputError(
            "--simulate draws datasets from the population: use --convention gpower with --rho"
        )
    if answer.question == "detectable effect":
        raise InvalidInputError("--simulate needs an effect size (the power or N question)")
    effect = design.effect
    if estimate is not None and answer.f == estimate.f(effect):
        return estimate.means, estimate.estimates["sd"]
    if means is not None and sd is not None:
        table = np.asarray(parse_means(means, "--means"), dtype=float)
        sds = np.asarray(parse_means(sd, "--sd"), dtype=float)
        spread = float(np.sqrt(np.mean(sds**2)))
        if effect_sizes_from_means(table, spread if sds.size == 1 else sds)[effect] == answer.f:
            return table, spread
    return effect_pattern(effect, answer.f, design.groups, design.sessions), 1.0


def _check_model_options(
    model: str, simulate: int | None, categories: int | None, pilot: str | None
) -> None:
    """One line for a --model or --categories that cannot apply."""
    from analysis.errors import InvalidInputError
    from analysis.power_models import SIMULATED_MODELS

    if model not in SIMULATED_MODELS:
        raise InvalidInputError(
            f"--model must be one of {', '.join(SIMULATED_MODELS)}, not {model!r}"
        )
    if model != "lmm" and simulate is None:
        raise InvalidInputError(f"--model {model} chooses the simulated model: add --simulate R")
    if categories is not None and model != "ordinal":
        raise InvalidInputError("--categories goes with --model ordinal")
    if categories is not None and pilot is not None:
        raise InvalidInputError(
            "--categories or --pilot: with a pilot, its ratings give the categories"
        )


def _ordinal_population(
    answer: PowerAnswer,
    estimate: PilotEstimate | None,
    pilot_data: tuple[pd.DataFrame, dict[str, str]] | None,
    table: np.ndarray,
    spread: float,
    categories: int | None,
) -> LatentOrdinalModel:
    """The latent population of the ordinal datasets: the pilot's fitted ordinal model when the
    answer's f is the pilot's, else the cell pattern :func:`_simulation_model` chose (in SD
    units, read on the latent scale) with the pilot's category proportions or equally spaced
    thresholds."""
    import pandas as pd

    from analysis.errors import InvalidInputError
    from analysis.power_ordinal import (
        DEFAULT_CATEGORIES,
        latent_model,
        observed_proportions,
        pilot_latent_model,
    )

    design = answer.design
    rho = float(design.rho if design.rho is not None else float("nan"))
    pattern = (table - table.mean()) / spread
    if estimate is not None and pilot_data is not None:
        data, columns = pilot_data
        if answer.f == estimate.f(design.effect):
            population = pilot_latent_model(data, **columns, rho=rho)
            if population.cell_means.shape != (design.groups, design.sessions):
                raise InvalidInputError(
                    f"the pilot's ordinal model has {population.cell_means.shape[0]} group(s) × "
                    f"{population.cell_means.shape[1]} session(s); --groups {design.groups} "
                    f"--sessions {design.sessions} say otherwise"
                )
            return population
        ratings = pd.to_numeric(data[columns["dv"]], errors="coerce").to_numpy(float)
        return latent_model(
            pattern,
            rho=rho,
            proportions=observed_proportions(ratings, columns["dv"]),
            source=f"the {design.effect} pattern with f = {answer.f:.3g}",
        )
    return latent_model(
        pattern,
        rho=rho,
        categories=DEFAULT_CATEGORIES if categories is None else categories,
        source=f"the {design.effect} pattern with f = {answer.f:.3g}",
    )


def _curve_n(answer: PowerAnswer) -> list[int]:
    """Six totals, multiples of k, from about half to twice the N asked or found."""
    import numpy as np

    k = answer.design.groups
    per_group = max(answer.n_total // k, 2)
    steps = np.unique(np.round(np.geomspace(max(per_group / 2, 2), per_group * 2, 6)).astype(int))
    values = sorted({int(k * s) for s in steps} | {answer.n_total})
    return [n for n in values if n // k >= 2 and n % k == 0]


_MODEL_WORDS = {
    "lmm": "the mixed model (random intercept, REML, Satterthwaite df)",
    "ordinal": "the ordinal model (proportional odds, Wald χ², participant-clustered SEs)",
}


def render_simulation(
    simulated: list[SimulatedPower],
    at_n: SimulatedPower | None,
    curve: Path | None,
    population: LatentOrdinalModel | None = None,
) -> str:
    """The simulated power (and the curve's points) in words."""
    from analysis.apa_numbers import format_number

    lines = []
    if population is not None:
        shares = "/".join(f"{p * 100:.0f}" for p in population.category_proportions())
        sizes = population.effect_sizes()
        lines.append(
            f"Ordinal datasets drawn from {population.source}; latent rho "
            f"{format_number(population.rho, 3)}; expected category shares {shares} %; latent "
            f"f: between {format_number(sizes['between'], 3)}, within "
            f"{format_number(sizes['within'], 3)}, interaction "
            f"{format_number(sizes['interaction'], 3)}"
        )
    if at_n is not None:
        lines.append(
            f"Simulated power of {_MODEL_WORDS[at_n.kind]} at "
            f"N = {at_n.n_total}: {format_number(at_n.power, 3)} "
            f"[{format_number(at_n.ci_low, 3)}, {format_number(at_n.ci_high, 3)}] "
            f"(95 % Wilson; {at_n.rejections} of {at_n.replicates} datasets, seed {at_n.seed}"
            + (f", {at_n.failures} fits without a test" if at_n.failures else "")
            + ")"
        )
    if curve is not None:
        lines.append(f"Power curve ({curve}):")
        lines += [
            f"  N = {s.n_total:>4}  {format_number(s.power, 3)}  "
            f"[{format_number(s.ci_low, 3)}, {format_number(s.ci_high, 3)}]"
            for s in simulated
        ]
    return "\n".join(lines)


def read_pilot(
    source: str, dv: str | None, *, within: str, between: str, subject: str
) -> tuple[pd.DataFrame, dict[str, str]]:
    """A pilot's long data and its columns (``dv``, ``within``, ``between``, ``subject``): a
    CSV file as it is, a stored study's measure (``--dv``, default ``trust_1``) as the report
    analyses it."""
    from analysis.errors import InvalidInputError

    path = Path(source)
    if path.exists() or source.endswith(".csv"):
        if dv is None:
            raise InvalidInputError("--pilot with a CSV needs --dv (the rating column)")
        return read_csv_file(path), {
            "dv": dv,
            "within": within,
            "between": between,
            "subject": subject,
        }
    from analysis.study import analyse_study
    from app.cli.common import open_database, require_current_schema
    from app.services import studies
    from app.services.analysis_views import study_data
    from app.services.privacy.sites import Scope
    from app.settings import Settings

    database = open_database(Settings())
    require_current_schema(database)
    with database.read_session() as db:
        dataset = study_data.load_dataset(
            db, study=studies.get_study(db, source), scope=Scope.every_site()
        )
    key = dv or "trust_1"
    outcome = analyse_study(dataset).outcome(key)
    columns = {"dv": key, "within": "session", "between": "condition", "subject": "participant"}
    return outcome.data.rename(columns={"value": key}), columns


def _bracket(answer: PowerAnswer, estimate: PilotEstimate | None) -> dict[str, PowerAnswer]:
    """The same question at the ends of the pilot's interval for f (ρ and ε as used)."""
    import math

    from analysis.errors import AnalysisError
    from analysis.power import n_for_power, power_for_n

    if estimate is None or answer.question == "detectable effect":
        return {}
    low, high = estimate.intervals[f"f_{answer.design.effect}"]
    if not (math.isfinite(low) and math.isfinite(high)) or answer.f != estimate.f(
        answer.design.effect
    ):
        return {}
    answers = {}
    for name, size in (("f_ci_low", low), ("f_ci_high", high)):
        try:
            if answer.question == "power":
                answers[name] = power_for_n(answer.design, f=size, n_total=answer.n_total)
            else:
                answers[name] = n_for_power(
                    answer.design, f=size, target=answer.target_power or 0.8
                )
        except AnalysisError:  # e.g. an f of 0 never reaches the target
            continue
    return answers


def _finite(value: Any) -> Any:
    """NaN and ±inf as None, all the way down (JSON has no NaN)."""
    import math

    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_finite(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def render_pilot(estimate: PilotEstimate, source: str, bracket: dict[str, PowerAnswer]) -> str:
    """The pilot's estimates with their intervals, and the answer at the ends of f's."""
    from analysis._checks import to_python
    from analysis.apa_numbers import format_number
    from analysis.power_pilot import PILOT_QUANTITIES

    sizes = ", ".join(
        f"{to_python(g)} {n}"
        for g, n in zip(estimate.group_levels, estimate.group_sizes, strict=True)
    )
    pct = f"{estimate.confidence * 100:g} %"
    lines = [
        f"Pilot {source} ({estimate.dv!r}): {sizes} complete participants, "
        f"{estimate.sessions} sessions, {estimate.excluded} left out as incomplete; "
        f"{pct} bootstrap intervals ({estimate.replicates} resamples of participants within "
        f"condition, seed {estimate.seed})",
    ]
    labels = {
        "rho": "rho (corr. among sessions)",
        "epsilon": "epsilon (Greenhouse-Geisser)",
        "sd": "SD of one rating",
        "var_participant": "participant variance",
        "var_residual": "residual variance",
        "f_between": "f between",
        "f_within": "f within",
        "f_interaction": "f interaction",
    }
    for name in PILOT_QUANTITIES:
        low, high = estimate.intervals[name]
        lines.append(
            f"  {labels[name]:<29} {format_number(estimate.estimates[name], 3):>7}  "
            f"[{format_number(low, 3)}, {format_number(high, 3)}]"
        )
    for name, other in bracket.items():
        end = "low" if name.endswith("low") else "high"
        what = (
            f"power {format_number(other.power, 3)}"
            if other.question == "power"
            else f"N = {other.n_total}"
        )
        lines.append(
            f"  at the {end} end of f's interval (f = {format_number(other.f, 3)}): {what}"
        )
    return "\n".join(lines)


def answer_question(
    *,
    effect: str,
    groups: int | None,
    sessions: int | None,
    f: float | None,
    eta2: float | None,
    convention: str,
    means: str | None,
    sd: str | None,
    rho: float | None,
    epsilon: float | None,
    alpha: float,
    n: int | None,
    target_power: float | None,
) -> PowerAnswer:
    """The question the options ask, answered (:class:`AnalysisError` for bad input)."""
    from analysis.errors import InvalidInputError
    from analysis.power import (
        EFFECTS,
        PowerDesign,
        detectable_effect,
        effect_sizes_from_means,
        f_from_eta2,
        n_for_power,
        power_for_n,
    )

    if effect not in EFFECTS:
        raise InvalidInputError(f"--effect must be one of {', '.join(EFFECTS)}, not {effect!r}")
    given = [name for name, value in (("--f", f), ("--eta2", eta2), ("--means", means)) if value]
    if f == 0 or eta2 == 0:
        given = given or ["--f" if f == 0 else "--eta2"]
    if len(given) > 1:
        raise InvalidInputError(f"give one effect size, not {' and '.join(given)}")
    if (means is None) != (sd is None):
        raise InvalidInputError("--means and --sd go together")
    size: float | None = f
    if eta2 is not None:
        size = f_from_eta2(eta2)
    if means is not None and sd is not None:
        table = parse_means(means, "--means")
        sds: Any = parse_means(sd, "--sd")
        if len(sds) == 1 and len(sds[0]) == 1:
            sds = sds[0][0]
        k, m = len(table), len(table[0])
        if (groups, sessions) != (None, None) and (groups, sessions) != (k, m):
            raise InvalidInputError(
                f"--means has {k} group(s) × {m} session(s); --groups {groups} "
                f"--sessions {sessions} say otherwise"
            )
        groups, sessions = k, m
        size = effect_sizes_from_means(table, sds)[effect]
        if convention != "gpower":
            raise InvalidInputError(
                "an f from --means describes the population: use --convention gpower"
            )
    if groups is None or sessions is None:
        raise InvalidInputError("--groups and --sessions are needed (or a --means table)")
    design = PowerDesign(
        effect,
        groups,
        sessions,
        rho,
        epsilon=1.0 if epsilon is None else epsilon,
        alpha=alpha,
        convention=convention,  # type: ignore[arg-type]
    )
    asked = [size is None, n is None, target_power is None]
    if sum(asked) != 1:
        raise InvalidInputError(
            "leave exactly one of effect size, --n and --target-power open: give an effect "
            "size and --n (power), an effect size and --target-power (N), or --n and "
            "--target-power (the smallest detectable effect)"
        )
    if size is None:
        return detectable_effect(design, n_total=n, target=target_power)  # type: ignore[arg-type]
    if n is None:
        return n_for_power(design, f=size, target=target_power)  # type: ignore[arg-type]
    return power_for_n(design, f=size, n_total=n)


def parse_means(text: str, option: str) -> list[list[float]]:
    """A table written as ``a,b;c,d`` (rows by semicolons), every row as long as the first."""
    from analysis.errors import InvalidInputError

    try:
        rows = [[float(cell) for cell in row.split(",")] for row in text.split(";")]
    except ValueError:
        raise InvalidInputError(
            f"{option} must be numbers, commas between sessions and semicolons between groups: "
            f"{text!r}"
        ) from None
    if any(len(row) != len(rows[0]) for row in rows):
        raise InvalidInputError(f"{option}: every group needs as many values as the first")
    return rows


def render_answer(answer: PowerAnswer) -> str:
    """The answer in words, then every number behind it."""
    from analysis.apa_numbers import format_number

    design = answer.design
    what = {
        "between": "between-groups effect",
        "within": "within (session) effect",
        "interaction": "group × session interaction",
    }[design.effect]
    size = (
        f"f = {format_number(answer.f, 4)} (η² = {format_number(answer.eta2, 4)}, "
        f"{design.convention} convention)"
    )
    if answer.question == "power":
        head = (
            f"Power {format_number(answer.power, 3)} to detect the {what} with N = {answer.n_total}"
        )
    elif answer.question == "sample size":
        head = (
            f"N = {answer.n_total} ({answer.n_total // design.groups} per group) reaches power "
            f"{format_number(answer.power, 3)} (target {answer.target_power:g}) for the {what}"
        )
    else:
        head = (
            f"With N = {answer.n_total}, the smallest {what} detected with power "
            f"{answer.target_power:g} is {size}"
        )
    rho = "—" if design.rho is None else format_number(design.rho, 3)
    lines = [
        head,
        "",
        f"  design       {design.groups} group(s) × {design.sessions} session(s), "
        f"alpha {design.alpha:g}",
        f"  effect size  {size}",
        f"  rho          {rho}"
        + ("" if design.to_dict()["rho_used"] else " (not used by this convention)"),
        f"  epsilon      {format_number(design.epsilon, 3)}"
        + ("" if design.uses_epsilon else " (not used by the between effect)"),
        f"  lambda       {format_number(answer.lam, 4)}",
        f"  df           {format_number(answer.df1, 3)}, {format_number(answer.df2, 3)}",
        f"  critical F   {format_number(answer.f_critical, 4)}",
        f"  power        {format_number(answer.power, 4)}",
    ]
    return "\n".join(lines)
