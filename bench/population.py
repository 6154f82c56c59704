"""Benchmark: does C2 meta-trained on a fitted pilot population adapt faster (issue 20)?

Run from the repository root (eight trainings, two at a time, 3–5 minutes each)::

    .venv/bin/python bench/population.py                      # 10,000 participants, seed 2026
    .venv/bin/python bench/population.py --checkpoints DIR    # keep (and reuse) the trainings
    .venv/bin/python bench/population.py --held-out 8         # issue 36's held-out check

For each held-out population (K = 4, 12 answers): a pilot study of N participants is simulated
(questions asked at random, as an Exp3 pilot nearly does), its steps fitted with
``app.services.sessions.population_fit.fit_population``, and C2 meta-trained on the fitted
population's smoothed prior (``Population.training_prior``) for the shipped protocol's feedback
model, exactly as ``trustlab pretrain --population`` does. Then, on 10,000 fresh participants of the
true population, answers to .95 for:

- ``fitted``: C2 trained on the pilot's population;
- ``uniform``: C2 trained on the uniform prior (the shipped generic K = 4 checkpoint);
- ``random init``: the fitted checkpoint's update rule from random weights and no prior (the
  Appendix's comparison: what meta-training added);
- ``pilot ref``: the exact filter that knows only what the pilot tells (the training prior C2
  was given, and the model): the best any learner trained on that pilot could do;
- ``reference``: the exact forward filter that knows the true population (prior, slips, hazard).

``--pilot-draws D`` then measures, without training, how much the pilot itself limits: for D
pilots per N (right and wrong), the pilot filter with the fitted shares as they are (maximum
likelihood) and smoothed as C2 is trained (one pseudo-participant per question).

``--held-out S`` instead runs issue 36's held-out check in miniature, over S pilots: a pilot of
2 × 24 participants of .7/.1/.1/.1 with slips is split in halves, C2 trained for the first half's
fitted population, and C2, C1 (Exp3), the shipped uniform C2 and the exact reference evaluated on
participants drawn as ``trustlab simulate adaptation`` draws them: from that fitted population
(``--population`` alone, what the command did before issue 36), from the held-out half's fitted
population (``--true-population``: its smoothed shares), from the held-out half's raw shares,
and from the truth. It prints C2's answers to .95, its gains over C1 and over the uniform C2 and
what each draw overstates C2's gain by against the truth: means over the pilots with their
standard deviation. ``--meta-batches`` shortens the trainings (the held-out check in miniature).

Populations: .7/.1/.1/.1 with slips (the shipped protocol's 0–10 % and hazard .02) for pilots of
N = 6, 12, 24, 48, and without slips (N = 24); .4/.2/.2/.2 and uniform with slips (N = 24); and a
wrong pilot (skewed .7 to question 1, the real population to question 0). One pilot is drawn per
row: its fitted prior is printed beside the figures. Targets are printed met or missed; figures to
stdout; same seed, same figures; never a test assertion.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

_ROOT = Path(__file__).resolve().parents[1]
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _ROOT / "bench"]
sys.path.insert(0, str(_ROOT))

import numpy as np  # noqa: E402

from analysis.population import Population, read_population, write_population  # noqa: E402
from app.cli.engine import training_feedback  # noqa: E402
from app.cli.simulated_population import (  # noqa: E402
    Declared,
    PopulationDraw,
    population_participants,
)
from app.services.sessions.population_fit import fit_population, sequences_from_steps  # noqa: E402
from bench.analysis import cpu_model  # noqa: E402
from bench.population_fit import simulated_steps  # noqa: E402
from models.checkpoints import (  # noqa: E402
    GENERIC,
    Checkpoint,
    load_checkpoint,
    shipped_checkpoint,
    shipped_set,
)
from models.feedback import FeedbackModel  # noqa: E402
from models.learners.belief import BatchBelief  # noqa: E402
from models.learners.exp3 import DEFAULT_EXP3_GAMMA  # noqa: E402
from models.population import fit_category  # noqa: E402
from models.pretrain_config import PretrainArgs  # noqa: E402
from models.simulate import Scenario, run, simulate_adaptation, summarise  # noqa: E402
from models.tasks import TaskDistribution  # noqa: E402

SKEWED = (0.7, 0.1, 0.1, 0.1)
MILD = (0.4, 0.2, 0.2, 0.2)
UNIFORM = (0.25, 0.25, 0.25, 0.25)
WRONG = (0.1, 0.7, 0.1, 0.1)
CONSISTENT = FeedbackModel(kind="binary")


@dataclass(frozen=True)
class Case:
    """One row: a pilot of ``pilot_n`` from ``pilot_prior``, evaluated on ``prior``."""

    name: str
    prior: tuple[float, ...]
    pilot_n: int
    slips: bool = True
    pilot_prior: tuple[float, ...] | None = None

    @property
    def pilot(self) -> tuple[float, ...]:
        return self.pilot_prior or self.prior


CASES = (
    Case("skewed N=6", SKEWED, 6),
    Case("skewed N=12", SKEWED, 12),
    Case("skewed N=24", SKEWED, 24),
    Case("skewed N=48", SKEWED, 48),
    Case("skewed, no slips N=24", SKEWED, 24, slips=False),
    Case("mild N=24", MILD, 24),
    Case("uniform N=24", UNIFORM, 24),
    Case("wrong pilot N=24", SKEWED, 24, pilot_prior=WRONG),
)


def shipped_model() -> FeedbackModel:
    """The shipped protocol's feedback model (what C2 trains for and participants with slips
    answer by)."""
    return FeedbackModel.from_json(
        training_feedback("online", None, False, None, None, None)["feedback"]
    )


def pilot_population(case: Case, seed: int) -> Population:
    """The pilot study's steps, fitted as ``trustlab population fit`` fits them."""
    model = shipped_model() if case.slips else CONSISTENT
    steps = simulated_steps(case.pilot_n, seed, case.pilot, model, categories=(GENERIC,))
    source = {"steps": f"bench pilot: {case.name}"}
    return fit_population(steps, source, arms={GENERIC: 4}, replicates=20, seed=seed)


def train_args(population: Population, seed: int, overrides: dict[str, Any]) -> PretrainArgs:
    """``trustlab pretrain --population`` for the generic K = 4 network (the same network as the
    shipped uniform checkpoint, so the two differ only in the prior they were trained on)."""
    training = training_feedback("online", None, False, None, None, None)
    return replace(
        PretrainArgs(
            category=GENERIC,
            arms=4,
            seed=seed,
            preferred_prior=population.training_prior(GENERIC, 4),
            population=population.record(GENERIC),
            **training,
        ),
        **overrides,
    ).resolved()


def _train(job: tuple[PretrainArgs, Path]) -> tuple[str, float]:
    from models.pretrain import pretrain

    args, target = job
    start = time.perf_counter()
    checkpoint = pretrain(args, target)
    return str(checkpoint.path), time.perf_counter() - start


def _reusable(target: Path, population: Population, args: PretrainArgs) -> bool:
    try:
        config = json.loads((target / "config.json").read_text())
    except (OSError, json.JSONDecodeError):
        return False
    same_run = config.get("meta_batches") == args.meta_batches
    return bool(same_run and config.get("population", {}).get("sha256") == population.sha256)


def evaluate(
    case: Case, fitted: Checkpoint, uniform: Checkpoint, participants: int, seed: int
) -> dict[str, float]:
    """Answers to .95 of each learner on participants of the true population."""
    model = shipped_model() if case.slips else CONSISTENT
    tasks = TaskDistribution(4, case.prior)
    scenario = Scenario(feedback=model)
    common: dict[str, Any] = {"participants": participants, "iterations": 12, "seed": seed}
    common |= {"gamma": DEFAULT_EXP3_GAMMA, "scenario": scenario}
    own = simulate_adaptation(
        tasks, checkpoint=fitted, learners=("meta", "random_init", "bayes"), **common
    )
    base = simulate_adaptation(tasks, checkpoint=uniform, learners=("meta",), **common)
    pilot = BatchBelief(participants, 4, model, np.asarray(fitted.prior), 1)
    rng = np.random.default_rng(seed)
    preferred = tasks.sample_preferred(rng, participants)  # as simulate_learner draws them
    limited = summarise(
        run(pilot, tasks, preferred, 12, np.random.default_rng([seed, 7]), scenario)
    )
    figures = {
        "fitted": own["learners"]["meta"]["iterations_to_95"],
        "pilot ref": limited["iterations_to_95"],
        "uniform": base["learners"]["meta"]["iterations_to_95"],
        "random init": own["learners"]["random_init"]["iterations_to_95"],
        "reference": own["learners"]["bayes"]["iterations_to_95"],
    }
    figures["wrong 95 fitted"] = own["learners"]["meta"]["wrong_95"]
    figures["wrong 95 uniform"] = base["learners"]["meta"]["wrong_95"]
    return figures


def _filter_answers(
    prior: np.ndarray, tasks: TaskDistribution, model: FeedbackModel, participants: int, seed: int
) -> float:
    """Answers to .95 of the exact filter that starts at ``prior`` on ``tasks``' participants."""
    preferred = tasks.sample_preferred(np.random.default_rng(seed), participants)
    learner = BatchBelief(participants, tasks.n_arms, model, prior, 1)
    scenario = Scenario(feedback=model)
    return float(
        summarise(run(learner, tasks, preferred, 12, np.random.default_rng([seed, 7]), scenario))[
            "iterations_to_95"
        ]
    )


def pilot_limits(draws: int, participants: int, seed: int) -> list[str]:
    """How far a pilot of N can take any learner: the exact filter started at the pilot's fitted
    shares (maximum likelihood) or at them smoothed (as C2 is trained), over ``draws`` pilots."""
    model = shipped_model()
    tasks = TaskDistribution(4, SKEWED)
    truth = _filter_answers(tasks.prior, tasks, model, participants, seed)
    lines = [
        f"pilot-limited (the exact filter from the pilot's prior; {draws} pilots per row, "
        f"{participants} participants of .7/.1/.1/.1 with slips; knowing the truth: {truth:.3f}):",
        f"{'pilot':<12} {'N':>3} {'MLE mean':>9} {'≤1.1×ref':>9} {'smoothed mean':>14} "
        f"{'≤1.1×ref':>9}",
    ]
    for pilot_prior, label in ((SKEWED, "right"), (WRONG, "wrong")):
        for n in (6, 12, 24, 48):
            raw, smooth = [], []
            for draw in range(draws):
                steps = simulated_steps(n, seed + 1000 + draw, pilot_prior, model, (GENERIC,))
                sequences = sequences_from_steps(steps, {GENERIC: 4})[GENERIC]
                shares = fit_category(sequences).prior
                raw.append(_filter_answers(shares, tasks, model, participants, seed))
                smoothed = (shares * n + 1.0) / (n + 4)
                smooth.append(_filter_answers(smoothed, tasks, model, participants, seed))
            limit = 1.1 * truth
            lines.append(
                f"{label:<12} {n:>3} {np.mean(raw):>9.3f} {np.mean(np.asarray(raw) <= limit):>9.2f}"
                f" {np.mean(smooth):>14.3f} {np.mean(np.asarray(smooth) <= limit):>9.2f}"
            )
    return lines


HALF = 24
"""Participants in each half of the held-out check's pilot."""
DRAWS = {
    "fitted": "fitted (--population alone)",
    "held-out": "held-out (--true-population)",
    "held-out shares": "held-out, unsmoothed shares",
    "truth": "truth",
}
"""Where the held-out check draws participants from: the fitting half's population as
``--population`` alone draws it (its shares), the held-out half's as ``--true-population`` draws
it (its smoothed shares), the held-out half's raw shares (what ``--true-population`` would draw
without smoothing), and the true population."""


def held_out_populations(pilot: int, seed: int) -> tuple[Population, Population]:
    """One pilot of 2 × :data:`HALF` participants of .7/.1/.1/.1 with slips, each half fitted as
    ``trustlab population fit`` fits it: the half C2 is trained for, and the held-out half."""
    steps = simulated_steps(2 * HALF, seed, SKEWED, shipped_model(), categories=(GENERIC,))
    halves = []
    for name, rows in (
        ("fitting", steps.participant < HALF),
        ("held-out", steps.participant >= HALF),
    ):
        source = {"steps": f"bench held-out check, pilot {pilot}: {name} half"}
        halves.append(
            fit_population(steps[rows], source, arms={GENERIC: 4}, replicates=20, seed=seed)
        )
    return halves[0], halves[1]


def _draws(
    fitted: Path, held_out: Path, c2: Checkpoint
) -> dict[str, tuple[TaskDistribution, Scenario]]:
    """The participants of each of :data:`DRAWS`, the first two exactly as the command draws
    them (app/cli/simulated_population.py), checked to be the population C2 was trained for."""

    def draw(true_path: Path | None) -> PopulationDraw:
        return population_participants(
            fitted,
            true_path=true_path,
            declared=Declared(),
            category=GENERIC,
            arms=4,
            change_after=None,
        ).for_checkpoint(c2)

    optimistic, declared = draw(None), draw(held_out)
    assert optimistic.optimistic and not declared.optimistic
    shares = TaskDistribution(4, read_population(held_out).prior(GENERIC, 4))
    return {
        "fitted": (optimistic.tasks, optimistic.scenario),
        "held-out": (declared.tasks, declared.scenario),
        "held-out shares": (shares, declared.scenario),
        "truth": (TaskDistribution(4, SKEWED), Scenario(feedback=shipped_model())),
    }


def held_out_row(
    c2: Checkpoint,
    uniform: Checkpoint,
    fitted: Path,
    held_out: Path,
    participants: int,
    seed: int,
) -> dict[str, dict[str, float]]:
    """Answers to .95 of C2, C1, the uniform C2 and the reference on each of :data:`DRAWS`."""
    common: dict[str, Any] = {"participants": participants, "iterations": 12, "seed": seed}
    common["gamma"] = DEFAULT_EXP3_GAMMA
    row = {}
    for name, (tasks, scenario) in _draws(fitted, held_out, c2).items():
        own = simulate_adaptation(
            tasks, checkpoint=c2, learners=("exp3", "meta", "bayes"), scenario=scenario, **common
        )
        base = simulate_adaptation(
            tasks, checkpoint=uniform, learners=("meta",), scenario=scenario, **common
        )
        figures = {key: own["learners"][key]["iterations_to_95"] for key in ("exp3", "bayes")}
        figures["c2"] = own["learners"]["meta"]["iterations_to_95"]
        figures["uniform"] = base["learners"]["meta"]["iterations_to_95"]
        row[name] = figures
    return row


def _spread(values: list[float], sign: str = "") -> str:
    """Mean ± standard deviation (n − 1) of ``values``."""
    array = np.asarray(values)
    sd = float(array.std(ddof=1)) if array.size > 1 else float("nan")
    return f"{array.mean():{sign}.3f} ± {sd:.3f}"


MEASURES: dict[str, Callable[[dict[str, float]], float]] = {
    "C2 answers": lambda d: d["c2"],
    "gain over C1": lambda d: d["exp3"] - d["c2"],
    "gain over uniform C2": lambda d: d["uniform"] - d["c2"],
    "gap to reference": lambda d: d["c2"] - d["bayes"],
}
"""What the held-out check reports per draw (answers to .95; C1 is Exp3, the reference the exact
filter that knows the draw's population)."""


def held_out_summary(rows: list[dict[str, dict[str, float]]]) -> list[str]:
    """Per draw, means over the pilots (± their standard deviation) of each of
    :data:`MEASURES` and of C2's gain over C1 minus the same on the truth: what drawing from
    that population overstates."""
    lines = [
        f"{'mean ± SD over ' + str(len(rows)) + ' pilots':<30}"
        + "".join(f"{name:>22}" for name in MEASURES)
        + f"{'gain overstated':>20}"
    ]
    gain = MEASURES["gain over C1"]
    for name, label in DRAWS.items():
        cells = [
            _spread([measure(row[name]) for row in rows], "" if key == "C2 answers" else "+")
            for key, measure in MEASURES.items()
        ]
        over = _spread([gain(row[name]) - gain(row["truth"]) for row in rows], "+")
        lines.append(f"{label:<30}" + "".join(f"{c:>22}" for c in cells) + f"{over:>20}")
    fitted = [gain(row["fitted"]) - gain(row["held-out"]) for row in rows]
    lines.append(
        "drawing from the fitted population, not the held-out one, overstates C2's gain over C1 "
        f"by {_spread(fitted, '+')} answers"
    )
    return lines


def held_out_check(
    pilots: int,
    participants: int,
    seed: int,
    checkpoints: Path,
    overrides: dict[str, Any],
    workers: int,
) -> list[str]:
    """Issue 36's held-out check over ``pilots`` pilots: train (or reuse) C2 for each fitting
    half, evaluate it on each draw, and summarise."""
    directory = checkpoints / "held-out"
    directory.mkdir(parents=True, exist_ok=True)
    jobs, pairs = [], []
    for pilot in range(pilots):
        fitted, held_out = held_out_populations(pilot, seed + 100 + pilot)
        paths = (directory / f"pilot{pilot}.fitted.json", directory / f"pilot{pilot}.held-out.json")
        write_population(paths[0], fitted)
        write_population(paths[1], held_out)
        args = train_args(fitted, seed + 100 + pilot, overrides)
        target = directory / f"pilot{pilot}"
        if not _reusable(target, fitted, args):
            jobs.append((args, target))
        pairs.append((target, *paths))
    start = time.perf_counter()
    with ProcessPoolExecutor(max_workers=workers) as pool:
        for path, seconds in pool.map(_train, jobs):
            print(f"# trained {path} in {seconds:.0f} s", flush=True)
    print(
        f"# held-out check: {len(jobs)} trainings in {time.perf_counter() - start:.0f} s "
        f"({pilots - len(jobs)} reused from {directory})"
    )
    uniform = load_checkpoint(shipped_checkpoint(4, directory=shipped_set(shipped_model())), 4)
    lines = [
        f"{'pilot':<6} {'fitted prior':<20} {'held-out prior':<20} "
        + " ".join(f"{'C2 ' + name:>18}" for name in DRAWS)
    ]
    rows = []
    for pilot, (target, fitted_path, held_path) in enumerate(pairs):
        row = held_out_row(
            load_checkpoint(target, 4), uniform, fitted_path, held_path, participants, seed
        )
        rows.append(row)
        priors = [
            "/".join(f"{v:.2f}" for v in read_population(path).prior(GENERIC, 4))
            for path in (fitted_path, held_path)
        ]
        lines.append(
            f"{pilot:<6} {priors[0]:<20} {priors[1]:<20} "
            + " ".join(f"{row[name]['c2']:>18.3f}" for name in DRAWS)
        )
    return lines + held_out_summary(rows)


def _check(label: str, ok: bool, figure: str) -> str:
    return f"  {'met   ' if ok else 'MISSED'} {label}: {figure}"


def targets(rows: dict[str, dict[str, float]], fits: dict[str, Population]) -> list[str]:
    """The issue's targets, met or missed, from the rows that exist."""
    lines = []
    key = "skewed N=24"
    if key in rows:
        row = rows[key]
        lines.append(
            _check(
                "skewed N=24: fitted ≤ 0.8 × uniform",
                row["fitted"] <= 0.8 * row["uniform"],
                f"{row['fitted']:.3f} vs 0.8 × {row['uniform']:.3f} = {0.8 * row['uniform']:.3f}",
            )
        )
        lines.append(
            _check(
                "skewed N=24: fitted ≤ 1.1 × reference",
                row["fitted"] <= 1.1 * row["reference"],
                f"{row['fitted']:.3f} vs 1.1 × {row['reference']:.3f} = "
                f"{1.1 * row['reference']:.3f}",
            )
        )
        gain = row["random init"] - row["fitted"]
        lines.append(
            _check("skewed N=24: meta ahead of random init by ≥ 0.5", gain >= 0.5, f"{gain:.3f}")
        )
    if "uniform N=24" in rows:
        row = rows["uniform N=24"]
        loss = row["fitted"] - row["uniform"]
        lines.append(_check("uniform N=24: fitted − uniform ≤ 0.05", loss <= 0.05, f"{loss:+.3f}"))
    if "skewed N=48" in fits:
        fitted = fits["skewed N=48"].categories[GENERIC]
        error = float(np.abs(np.asarray(fitted["prior"]) - np.asarray(SKEWED)).max())
        lines.append(_check("N=48: prior within ±.05", error <= 0.05, f"max error {error:.3f}"))
        slip_error = abs(float(fitted["slip"]) - float(shipped_model().slip_values.mean()))
        lines.append(
            _check(
                "N=48: slip within ±.03 (of the participants' mean slip .05)",
                slip_error <= 0.03,
                f"{fitted['slip']:.4f}",
            )
        )
    return lines


def main() -> None:
    """Fit, train, evaluate and print each row, then the targets."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--participants", type=int, default=10_000)
    parser.add_argument("--seed", type=int, default=2026)
    parser.add_argument("--checkpoints", type=Path, default=Path("/tmp/trustlab-bench-population"))
    parser.add_argument("--case", action="append", default=None, help="Only these rows (names).")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--pilot-draws", type=int, default=0, help="Pilot-limited table.")
    parser.add_argument(
        "--held-out", type=int, default=0, help="Only issue 36's held-out check, over S pilots."
    )
    parser.add_argument("--meta-batches", type=int, default=None, help="Smoke runs only.")
    parser.add_argument("--tasks-per-batch", type=int, default=None, help="Smoke runs only.")
    args = parser.parse_args()
    cases = [c for c in CASES if args.case is None or c.name in args.case]
    overrides: dict[str, Any] = {}
    if args.meta_batches:
        overrides |= {"meta_batches": args.meta_batches, "validate_every": 1}
        overrides |= {"validation_participants": 500, "evaluation_participants": 500}
    if args.tasks_per_batch:
        overrides["tasks_per_batch"] = args.tasks_per_batch
    print(
        f"# {platform.python_implementation()} {platform.python_version()}, "
        f"nproc={os.cpu_count()}, CPU: {cpu_model()}; {args.participants} participants per row, "
        f"12 answers, seed {args.seed}; C2 trained for {shipped_model().describe()}"
    )
    if args.held_out:
        lines = held_out_check(
            args.held_out, args.participants, args.seed, args.checkpoints, overrides, args.workers
        )
        print("\n".join(lines))
        return
    fits = {c.name: pilot_population(c, args.seed + i) for i, c in enumerate(cases)}
    jobs, targets_by_case = [], {}
    for i, case in enumerate(cases):
        run = train_args(fits[case.name], args.seed + i, overrides)
        target = args.checkpoints / case.name.replace(" ", "_").replace(",", "").replace("=", "")
        targets_by_case[case.name] = target
        if not _reusable(target, fits[case.name], run):
            jobs.append((run, target))
    start = time.perf_counter()
    with ProcessPoolExecutor(max_workers=args.workers) as pool:
        for path, seconds in pool.map(_train, jobs):
            print(f"# trained {path} in {seconds:.0f} s", flush=True)
    print(
        f"# {len(jobs)} trainings in {time.perf_counter() - start:.0f} s "
        f"({len(cases) - len(jobs)} reused from {args.checkpoints})"
    )
    uniform = load_checkpoint(shipped_checkpoint(4, directory=shipped_set(shipped_model())), 4)
    header = f"{'row':<24} {'pilot prior (fitted)':<26} {'fitted':>7} {'uniform':>8} "
    header += f"{'random':>7} {'pilot ref':>9} {'ref':>6} {'wrong95 f/u':>12}"
    print(header)
    rows = {}
    for case in cases:
        fitted = load_checkpoint(targets_by_case[case.name], 4)
        row = evaluate(case, fitted, uniform, args.participants, args.seed)
        rows[case.name] = row
        prior = "/".join(f"{v:.2f}" for v in fits[case.name].categories[GENERIC]["prior"])
        print(
            f"{case.name:<24} {prior:<26} {row['fitted']:>7.3f} {row['uniform']:>8.3f} "
            f"{row['random init']:>7.3f} {row['pilot ref']:>9.3f} {row['reference']:>6.3f} "
            f"{row['wrong 95 fitted']:>5.3f}/{row['wrong 95 uniform']:.3f}",
            flush=True,
        )
    if "wrong pilot N=24" in rows:
        row = rows["wrong pilot N=24"]
        print(
            "harm of a wrong pilot: fitted − uniform = "
            f"{row['fitted'] - row['uniform']:+.3f} answers"
        )
    print("targets (answers to .95 unless said):")
    print("\n".join(targets(rows, fits)))
    if args.pilot_draws:
        print("\n".join(pilot_limits(args.pilot_draws, min(args.participants, 4000), args.seed)))


if __name__ == "__main__":
    main()
