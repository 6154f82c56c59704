"""``trustlab simulate adaptation`` and ``trustlab pretrain``: the adaptation engine from the shell.

The main ``trustlab`` Typer app calls :func:`register`. ``simulate adaptation --json`` prints
exactly one JSON object (issue 3)::

    {"arms": K, "iterations": T, "participants": N,
     "learners": {"exp3": {"p_correct": [T + 1 numbers], "iterations_to_95": …,
                           "reached_95": …, "wrong_95": …},
                  "meta": {…}, "random_init": {…}, "bayes": {…}}}

With ``--population`` it also carries ``population``: the fitted population C2 was trained for,
which population the participants were drawn from (``participants.drawn_from``: ``fitted`` or
``declared``) and that in one line (``summary``); app/cli/simulated_population.py.

With ``--out DIR`` it also writes the CSVs and the HTML page of the paper's figures (a) and (b);
(b) runs meta, random_init and bayes for every K with a shipped generic checkpoint.

``pretrain`` meta-trains checkpoints into ``OUT/<category>-k<K>/``; ``--category all`` trains the
three default categories. Bad input prints one line ``error: …`` on stderr and exits with 2.
torch is imported only inside ``pretrain``: the rest of the command line stays fast to start.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from app.cli.simulated_population import Declared, caution, population_participants

if TYPE_CHECKING:
    from models.checkpoints import Checkpoint
    from models.feedback import FeedbackModel
    from models.simulate import Scenario


__all__ = ["DEFAULT_CATEGORIES", "EXIT_BAD_INPUT", "register"]

EXIT_BAD_INPUT = 2
"""Exit status for unusable input (as for command-line usage errors)."""

DEFAULT_CATEGORIES = ("conation", "affection", "cognition")
"""The protocol's three categories, trained by ``pretrain --category all``."""

SWEEP_LEARNERS = ("meta", "random_init", "bayes")
"""The learners of figure (b), as in the paper's Appendix."""


DEFAULT_EXP3_GAMMA = 0.5
"""models.learners.exp3.DEFAULT_EXP3_GAMMA, for ``--help``: repeated here because showing help
imports no learner (tests/app/test_cli.py checks that they agree)."""


def register(cli: typer.Typer) -> None:
    """Add ``simulate adaptation`` and ``pretrain`` to the ``trustlab`` command line."""
    simulate = typer.Typer(help="Simulated participants: the engine's objective measures.")
    simulate.command("adaptation")(simulate_adaptation_command)
    cli.add_typer(simulate, name="simulate")
    cli.command("pretrain")(pretrain_command)


def _fail(message: str) -> typer.Exit:
    typer.echo("error: " + " ".join(message.split()), err=True)
    return typer.Exit(EXIT_BAD_INPUT)


def _prior(text: str | None, arms: int) -> tuple[float, ...] | None:
    if text is None:
        return None
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise _fail(f"--preferred-prior must be comma-separated numbers, got {text!r}") from None
    if len(values) != arms:
        raise _fail(f"--preferred-prior needs {arms} numbers (one per question), got {len(values)}")
    return values


def _scenario(
    kind: str | None, slip: float, hazard: float, change_after: int | None, acceptable: int
) -> Scenario:
    """The participants the flags describe (ValueError says which flag is wrong)."""
    from models.feedback import FeedbackModel
    from models.simulate import Scenario
    from models.tasks import DEFAULT_VARIANCE

    if kind is None and (slip or hazard or acceptable != 1):
        kind = "gaussian"
    if kind is None:
        return Scenario(change_after=change_after)
    if kind not in ("binary", "gaussian"):
        raise ValueError(f"--feedback must be binary or gaussian, got {kind!r}")
    try:
        model = FeedbackModel(
            kind=kind,  # type: ignore[arg-type]
            slips=(slip,),
            hazard=hazard,
            variance=DEFAULT_VARIANCE,
        )
    except ValueError as exc:
        raise ValueError(f"--slip / --hazard: {exc}") from None
    return Scenario(feedback=model, change_after=change_after, acceptable=acceptable)


def _checkpoint_set(mode: str, directory: Path | None, scenario: Scenario) -> Path:
    """``--checkpoint-dir``, else the shipped set trained for how the participants answer (the
    replication set for the paper's Gaussian participants, the default set for yes/no ones)."""
    from models.checkpoints import PRETRAINED_DIR, shipped_set
    from models.feedback import FeedbackModel
    from models.tasks import DEFAULT_VARIANCE

    if directory is not None or mode != "online":
        return PRETRAINED_DIR if directory is None else directory
    return shipped_set(scenario.feedback or FeedbackModel.paper(DEFAULT_VARIANCE))


def _checkpoint(
    arms: int, category: str | None, mode: str, path: Path | None, root: Path
) -> Checkpoint:
    from models.checkpoints import load_checkpoint, shipped_checkpoint

    location = path if path is not None else shipped_checkpoint(arms, category, mode, root)
    return load_checkpoint(location, expected_arms=arms)


def simulate_adaptation_command(
    arms: Annotated[int, typer.Option("--arms", help="Number of questions K.")] = 4,
    iterations: Annotated[int, typer.Option("--iterations", help="Answers per participant.")] = 12,
    participants: Annotated[
        int, typer.Option("--participants", help="Simulated participants.")
    ] = 2000,
    seed: Annotated[int, typer.Option("--seed", help="Random seed (same seed, same run).")] = 0,
    out: Annotated[
        Path | None, typer.Option("--out", help="Write CSVs and the HTML figures (a), (b) here.")
    ] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object.")] = False,
    gamma: Annotated[
        float, typer.Option("--gamma", help="Exp3's exploration rate γ (C1).")
    ] = DEFAULT_EXP3_GAMMA,
    category: Annotated[
        str | None,
        typer.Option("--category", help="Use this category's checkpoint (generic if unset)."),
    ] = None,
    mode: Annotated[
        str, typer.Option("--mode", help="Shipped checkpoint set: online or paper.")
    ] = "online",
    checkpoint: Annotated[
        Path | None, typer.Option("--checkpoint", help="Use this checkpoint directory instead.")
    ] = None,
    preferred_prior: Annotated[
        str | None,
        typer.Option(
            "--preferred-prior", help="Comma-separated prior over the preferred question."
        ),
    ] = None,
    checkpoint_dir: Annotated[
        Path | None,
        typer.Option("--checkpoint-dir", help="A retrained set (<mode>/<name>-k<K>/) to use."),
    ] = None,
    feedback: Annotated[
        str | None,
        typer.Option(
            "--feedback",
            help="binary (yes 1 / no 0) or gaussian answers; unset: the paper's Gaussian model.",
        ),
    ] = None,
    slip: Annotated[
        float | None,
        typer.Option(
            "--slip",
            help="Share of answers that say the opposite (0 ≤ P < .5; unset: 0, or the fitted "
            "one with --population).",
        ),
    ] = None,
    hazard: Annotated[
        float | None,
        typer.Option(
            "--hazard",
            help="Chance per answer that the preference changes (unset: 0, or the fitted one "
            "with --population).",
        ),
    ] = None,
    change_after: Annotated[
        int | None,
        typer.Option("--change-after", help="A new preferred question after answer N."),
    ] = None,
    acceptable: Annotated[
        int,
        typer.Option("--acceptable", help="Participants say yes to M questions (default 1)."),
    ] = 1,
    population: Annotated[
        Path | None,
        typer.Option(
            "--population",
            help="The fitted population C2 was trained for (trustlab population fit): "
            "participants are drawn from it (optimistic) unless --true-population or "
            "--preferred-prior declares the true one.",
        ),
    ] = None,
    true_population: Annotated[
        Path | None,
        typer.Option(
            "--true-population",
            help="With --population: draw the participants from this population file instead "
            "(e.g. fitted on held-out participants), the one the lab believes true.",
        ),
    ] = None,
) -> None:
    """Simulate participants answering Exp3, the meta-policy, its random init and the exact
    reference (Bayes; a forward filter when participants slip or change their minds). With
    --population, from the fitted population C2 was trained for (optimistic) unless
    --true-population or --preferred-prior declares the true one; the output says which."""
    from models.simulate import simulate_adaptation
    from models.tasks import TaskDistribution

    if participants < 1 or iterations < 1:
        raise _fail("--participants and --iterations must be at least 1")
    prior = _prior(preferred_prior, arms)
    drawn = None
    try:
        if population is None:
            if true_population is not None:
                raise ValueError(
                    "--true-population is the truth beside the fitted population C2 was trained "
                    "for: name that one with --population FILE"
                )
            scenario = _scenario(feedback, slip or 0.0, hazard or 0.0, change_after, acceptable)
            tasks = TaskDistribution(arms, prior)
        else:
            declared = Declared(prior, slip, hazard, feedback, acceptable)
            drawn = population_participants(
                population,
                true_path=true_population,
                declared=declared,
                category=category,
                arms=arms,
                change_after=change_after,
            )
            category, tasks, scenario = drawn.category, drawn.tasks, drawn.scenario
        root = _checkpoint_set(mode, checkpoint_dir, scenario)
        ckpt = _checkpoint(arms, category, mode, checkpoint, root)
        if drawn is not None:
            drawn = drawn.for_checkpoint(ckpt)
        result = simulate_adaptation(
            tasks,
            participants=participants,
            iterations=iterations,
            seed=seed,
            checkpoint=ckpt,
            gamma=gamma,
            scenario=scenario,
        )
        sweep = []
        if out is not None:
            sweep = _sweep(participants, iterations, seed, mode, root, scenario)
    except ValueError as error:
        raise _fail(str(error)) from None
    if drawn is not None:
        result["population"] = drawn.record
        warning = caution(drawn)
        if warning is not None:
            typer.echo(f"warning: {warning}", err=True)
    if out is not None:
        from analysis.simulation_figures import write_outputs

        try:
            write_outputs(out, result, sweep)
        except OSError as error:
            raise _fail(f"cannot write to {out}: {error}") from None
    if as_json:
        typer.echo(json.dumps(result, allow_nan=False))
    else:
        typer.echo(render(result, ckpt))


def _sweep(
    participants: int, iterations: int, seed: int, mode: str, root: Path, scenario: Scenario
) -> list[dict[str, Any]]:
    """Figure (b)'s simulations: meta, random_init and bayes for every K with a checkpoint, on
    the same participants as figure (a) (a preference changed after answer N only where there
    are more answers than N)."""
    from models.checkpoints import GENERIC, available_arms, checkpoint_name, load_checkpoint
    from models.simulate import simulate_adaptation
    from models.tasks import TaskDistribution

    results = []
    for k in available_arms(mode, root):
        ckpt = load_checkpoint(root / mode / checkpoint_name(GENERIC, k), k)
        results.append(
            simulate_adaptation(
                TaskDistribution(k),
                participants=participants,
                iterations=iterations,
                seed=seed,
                checkpoint=ckpt,
                gamma=DEFAULT_EXP3_GAMMA,
                learners=SWEEP_LEARNERS,
                scenario=_for_arms(scenario, k),
            )
        )
    if not results:
        raise ValueError(f"no generic {mode} checkpoints ship, so figure (b) cannot be drawn")
    return results


def _for_arms(scenario: Scenario, arms: int) -> Scenario:
    """``scenario`` for K = ``arms``: with at most K − 1 acceptable questions."""
    return replace(scenario, acceptable=min(scenario.acceptable, arms - 1))


def render(result: dict[str, Any], checkpoint: Checkpoint) -> str:
    """A readable table of the simulation's figures."""
    calibrated = f", temperature {checkpoint.temperature:g}" if checkpoint.temperature != 1 else ""
    lines = [
        f"{result['participants']} simulated participants, K = {result['arms']}, "
        f"{result['iterations']} answers; meta = {checkpoint.path} ({checkpoint.sha256[:12]}"
        f"{calibrated})",
        f"participants: {result['participants_answer']}; reference (bayes): {result['reference']}",
    ]
    population = result.get("population")
    if population is not None:
        lines += [population["summary"], population["c2"]]
    lines.append("")
    changed = any("recovered" in s for s in result["learners"].values())
    header = (
        f"{'learner':<12} {'answers to 95%':>14} {'reached 95%':>12} {'wrong 95%':>10} "
        f"{'mean p 1..T':>12}"
    )
    lines.append(header + (f" {'recovered':>10} {'p new final':>12}" if changed else ""))
    for name, s in result["learners"].items():
        mean_p = sum(s["p_correct"][1:]) / (len(s["p_correct"]) - 1)
        line = (
            f"{name:<12} {s['iterations_to_95']:>14.2f} {s['reached_95']:>12.3f} "
            f"{s['wrong_95']:>10.4f} {mean_p:>12.3f}"
        )
        if changed:
            line += f" {s['recovered']:>10.3f} {s['p_new_final']:>12.3f}"
        lines.append(line)
    lines += ["", "share of replies at each level (low, medium-low, medium, high):"]
    for name, s in result["learners"].items():
        shares = " ".join(f"{v:6.3f}" for v in s["reply_levels"].values())
        lines.append(f"{name:<12} {shares}")
    return "\n".join(lines)


def pretrain_command(
    out: Annotated[
        Path,
        typer.Option(
            "--out",
            help="Parent directory: writes OUT/<category>-k<K>/ (e.g. models/pretrained/online).",
        ),
    ],
    category: Annotated[
        str,
        typer.Option("--category", help="Category name, 'generic', or 'all' (the three defaults)."),
    ] = "all",
    mode: Annotated[str, typer.Option("--mode", help="online (C2's default) or paper.")] = "online",
    arms: Annotated[int, typer.Option("--arms", help="Number of questions K.")] = 4,
    seed: Annotated[int, typer.Option("--seed", help="Random seed (same seed, same file).")] = 0,
    objective: Annotated[
        str | None,
        typer.Option(
            "--objective",
            help="online: filter (default for yes/no models), log_score (default for the "
            "paper's Gaussian model) or reward.",
        ),
    ] = None,
    meta_batches: Annotated[
        int | None,
        typer.Option(
            "--meta-batches",
            help="Outer steps (online 60, or 150 for natural/gradient; paper 200).",
        ),
    ] = None,
    tasks_per_batch: Annotated[
        int | None, typer.Option("--tasks-per-batch", help="Tasks per step (online 200, paper 40).")
    ] = None,
    horizon: Annotated[int, typer.Option("--horizon", help="online: answers per task.")] = 12,
    validate_every: Annotated[
        int, typer.Option("--validate-every", help="online: meta-batches between validations.")
    ] = 5,
    online_rule: Annotated[
        str,
        typer.Option(
            "--online-rule",
            help="online: natural_expected (deployed), natural or gradient (docs/engine.md).",
        ),
    ] = "natural_expected",
    calibrate: Annotated[
        bool,
        typer.Option(
            "--calibrate/--no-calibrate",
            help="online: keep the snapshot fastest once its steps are scaled down to confidently "
            "wrong ≤ 0.75 % (docs/engine.md).",
        ),
    ] = True,
    wrong_penalty: Annotated[
        float,
        typer.Option("--wrong-penalty", help="online log_score: weight of log(1 − max wrong p)."),
    ] = 0.0,
    preferred_prior: Annotated[
        str | None,
        typer.Option(
            "--preferred-prior", help="Comma-separated prior over the preferred question."
        ),
    ] = None,
    force: Annotated[
        bool,
        typer.Option("--force", help="Overwrite checkpoint directories that already exist."),
    ] = False,
    protocol: Annotated[
        Path | None,
        typer.Option(
            "--protocol",
            help="online: train for this protocol's feedback model (learners.feedback) and "
            "reward map (default: the shipped protocol's).",
        ),
    ] = None,
    paper_feedback: Annotated[
        bool,
        typer.Option(
            "--paper-feedback",
            help="online: train for the paper's Gaussian feedback instead, as the replication set.",
        ),
    ] = False,
    anchor: Annotated[
        bool | None,
        typer.Option(
            "--anchor/--no-anchor",
            help="online: start exactly at the task prior (default on; off: --paper-feedback).",
        ),
    ] = None,
    forgetting: Annotated[
        bool | None,
        typer.Option(
            "--forgetting/--no-forgetting",
            help="online: meta-learn a forgetting step (default: on for a model with slips or a "
            "hazard).",
        ),
    ] = None,
    surprise_gates: Annotated[
        bool | None,
        typer.Option(
            "--surprise-gates/--no-surprise-gates",
            help="online: let an answer's surprise scale its step and forgetting (default: on "
            "with forgetting).",
        ),
    ] = None,
    surprise_memory: Annotated[
        bool | None,
        typer.Option(
            "--surprise-memory/--no-surprise-memory",
            help="online: let the gates' step also see the surprises before each answer "
            '(default: off; docs/engine.md, "C2 calibrated under slips").',
        ),
    ] = None,
    question_trace: Annotated[
        str | None,
        typer.Option(
            "--question-trace",
            help="online: keep one trace per question, of every surprise (surprise) or of "
            "contradictions net of confirmations (contradiction), so the gates tell repeated "
            "contradictions of one question (a change of mind) from scattered ones (slips) "
            '(default: none; docs/engine.md, "C2 calibrated under slips").',
        ),
    ] = None,
    population: Annotated[
        Path | None,
        typer.Option(
            "--population",
            help="online: train each category on the prior fitted from earlier participants "
            "(trustlab population fit); the checkpoint records the population.",
        ),
    ] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object.")] = False,
) -> None:
    """Meta-train checkpoints (MAML with a TRPO outer step) and write them with their hash."""
    from models.checkpoints import checkpoint_name
    from models.pretrain import PretrainArgs

    names = list(DEFAULT_CATEGORIES) if category == "all" else [category]
    root = out
    try:
        training = training_feedback(
            mode,
            protocol,
            paper_feedback,
            anchor,
            forgetting,
            surprise_gates,
            surprise_memory,
            question_trace,
        )
        if objective is not None:
            training["objective"] = objective
        fitted = (
            {}
            if population is None
            else _population_priors(population, category, arms, protocol, preferred_prior, training)
        )
        if fitted:  # --category all: the population's own categories, each with its K
            names = list(fitted)
        jobs = [
            PretrainArgs(
                category=name,
                arms=fitted[name][2] if fitted else arms,
                mode=mode,
                seed=seed,
                meta_batches=meta_batches,
                tasks_per_batch=tasks_per_batch,
                horizon=horizon,
                validate_every=validate_every,
                online_rule=online_rule,
                calibrate=calibrate,
                wrong_penalty=wrong_penalty,
                preferred_prior=fitted[name][0] if fitted else _prior(preferred_prior, arms),
                population=fitted[name][1] if fitted else None,
                **training,
            ).resolved()
            for name in names
        ]
    except ValueError as error:
        raise _fail(str(error)) from None
    targets = [root / checkpoint_name(args.category, args.arms) for args in jobs]
    # Refused before anything is trained: studies enrolled with a checkpoint need it as it was.
    taken = [str(target) for target in targets if target.exists() and any(target.iterdir())]
    if taken and not force:
        raise _fail(
            f"{', '.join(taken)} already hold{'s' if len(taken) == 1 else ''} a checkpoint: "
            "retire it first (docs/engine.md, 'Retraining and reproducing') or pass --force"
        )
    written = []
    for args, target in zip(jobs, targets, strict=True):
        try:
            checkpoint = _train_with_progress(args, target, show=not as_json)
        except (ValueError, OSError) as error:
            raise _fail(str(error)) from None
        evaluation = checkpoint.metrics["evaluation"]
        written.append(
            {
                "path": str(checkpoint.path),
                "sha256": checkpoint.sha256,
                "train_seconds": checkpoint.metrics["train_seconds"],
                "iterations_to_95": evaluation["iterations_to_95"],
                "reached_95": evaluation["reached_95"],
                "wrong_95": evaluation["wrong_95"],
                "mean_p_correct": evaluation["mean_p_correct"],
            }
        )
        if not as_json:
            typer.echo(
                f"{checkpoint.path}: sha256 {checkpoint.sha256[:12]}…, "
                f"{checkpoint.metrics['train_seconds']:.1f} s; deployed: "
                f"{evaluation['iterations_to_95']:.2f} answers to 95 %, "
                f"wrong {evaluation['wrong_95']:.4f}"
            )
            if checkpoint.metrics.get("calibration", {}).get("within_limit") is False:
                typer.echo(
                    f"warning: {checkpoint.path}: no step scale down to 0.5 brought wrong_95 "
                    "within the calibration limit; see calibration in its metrics.json",
                    err=True,
                )
    if as_json:
        typer.echo(json.dumps({"checkpoints": written}, allow_nan=False))


def training_feedback(
    mode: str,
    protocol: Path | None,
    paper: bool,
    anchor: bool | None,
    forgetting: bool | None,
    gates: bool | None,
    memory: bool | None = None,
    trace: str | None = None,
) -> dict[str, Any]:
    """The ``PretrainArgs`` fields for the feedback model a run trains for.

    The paper's Gaussian model (``--paper-feedback``, paper mode, or a protocol declaring it)
    trains as every checkpoint before issue 19 did: plain rewards, calibrated selection. Any
    other model trains anchored at the prior, with a forgetting step when participants may slip
    or change their minds (and surprise gates on it; their memory and per-question trace only
    when asked), scored and selected against the exact filter for the model (``objective`` and
    ``selection`` ``filter``; docs/engine.md, "C2 for real participants"). Explicit flags
    override these defaults.
    """
    from app.protocol import default_protocol, load_protocol_file
    from app.services.sessions.learners import feedback_model

    if mode != "online" or paper:
        if protocol is not None:
            raise ValueError("--protocol and --paper-feedback (or --mode paper) exclude each other")
        return {
            "anchor": bool(anchor),
            "forgetting": bool(forgetting),
            "surprise_gates": bool(gates),
            "surprise_memory": bool(memory),
            "question_trace": trace,
        }
    loaded = default_protocol() if protocol is None else load_protocol_file(protocol)
    model = feedback_model(loaded.protocol)
    if model.kind == "gaussian" and not model.has_slips_or_changes:
        return {
            "variance": model.variance,
            "anchor": bool(anchor),
            "forgetting": bool(forgetting),
            "surprise_gates": bool(gates),
            "surprise_memory": bool(memory),
            "question_trace": trace,
        }
    forgets = model.has_slips_or_changes if forgetting is None else forgetting
    return {
        "feedback": model.to_json(),
        "anchor": True if anchor is None else anchor,
        "forgetting": forgets,
        "surprise_gates": forgets if gates is None else gates,
        "surprise_memory": bool(memory),
        "question_trace": trace,
        "bounded_baseline": model.kind == "binary",
        "objective": "filter",
        "selection": "filter",
    }


def _population_priors(
    path: Path,
    category: str,
    arms: int,
    protocol: Path | None,
    preferred_prior: str | None,
    training: dict[str, Any],
) -> dict[str, tuple[tuple[float, ...], dict[str, Any], int]]:
    """Each category's training prior, population record and K from a verified population file:
    ``--category all`` means every category the population has (each with its own K), a named
    one must match ``--arms``.

    The categories' questions are checked against the protocol's (``--protocol`` or the shipped
    one) where it has the category, and recorded with the population in the checkpoint, so study
    creation can compare them even for a population fitted from a steps CSV (which carries no
    question texts). The slips and hazard C2 trains for stay the protocol's declared model
    (docs/engine.md, "Basic trust from earlier participants"); a fitted rate outside it is
    reported on stderr so the lab can widen ``[learners.feedback]``.
    """
    from analysis.population import read_population
    from app.protocol import default_protocol, load_protocol_file
    from models.checkpoints import GENERIC
    from models.feedback import FeedbackModel

    if preferred_prior is not None:
        raise ValueError("--population and --preferred-prior exclude each other")
    if category == GENERIC:
        raise ValueError(
            "a population is fitted per category: name one with --category (or all), not generic"
        )
    if "feedback" not in training:
        raise ValueError(
            "--population trains for a protocol's yes/no feedback model, in online mode"
        )
    loaded = default_protocol() if protocol is None else load_protocol_file(protocol)
    compared = "the shipped protocol" if protocol is None else str(protocol)
    known = {spec.name: list(spec.questions) for spec in loaded.protocol.categories}
    fitted_population = read_population(path)
    names = list(fitted_population.categories) if category == "all" else [category]
    model = FeedbackModel.from_json(training["feedback"])
    priors: dict[str, tuple[tuple[float, ...], dict[str, Any], int]] = {}
    for name in names:
        k = int(fitted_population.categories[name]["arms"]) if category == "all" else arms
        if name in known and len(known[name]) != k:
            raise ValueError(
                f"category {name!r} has {len(known[name])} questions in {compared}, {k} where "
                "the population was fitted: the questions differ (--protocol FILE for yours)"
            )
        try:
            prior = fitted_population.training_prior(name, k, known.get(name))
        except ValueError as exc:
            if name in known and "questions" in str(exc):
                message = f"{exc} (compared with {compared}; --protocol FILE for yours)"
                raise ValueError(message) from None
            raise
        record = fitted_population.record(name) | {"questions": known.get(name)}
        priors[name] = (prior, record, k)
    for name in names:  # warnings only once nothing is refused
        for problem in _outside_model(priors[name][1], model):
            typer.echo(f"warning: {name}: {problem}", err=True)
    return priors


def _outside_model(record: dict[str, Any], model: FeedbackModel) -> list[str]:
    """The fitted slip or hazard the declared feedback model does not cover."""
    problems = []
    slip_low = float(record["slip_ci"][0])
    if slip_low > float(model.slip_values.max()):
        problems.append(
            f"the fitted slip rate {record['slip']:.3f} (interval from {slip_low:.3f}) is above "
            f"every slip rate of the protocol's model ({model.describe()})"
        )
    hazard_low, hazard_high = (float(v) for v in record["hazard_ci"])
    if not hazard_low <= model.hazard <= hazard_high:
        problems.append(
            f"the protocol's hazard {model.hazard:g} is outside the fitted interval "
            f"[{hazard_low:.3f}, {hazard_high:.3f}]"
        )
    return problems


def _train_with_progress(args: Any, target: Path, *, show: bool) -> Checkpoint:
    """Run :func:`models.pretrain.pretrain` under a tqdm bar showing the running objective."""
    from tqdm import tqdm

    from models.pretrain import pretrain

    with tqdm(
        total=args.meta_batches,
        desc=f"{args.mode} {args.category} K={args.arms}",
        disable=not show,
        leave=False,
    ) as bar:

        def progress(iteration: int, running: float) -> None:
            bar.update(1)
            bar.set_postfix(objective=f"{running:.4f}")

        return pretrain(args, target, progress)
