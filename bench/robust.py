"""Benchmark: C2 on participants who behave like people, against issues 19 and 36's targets.

Run from the repository root::

    .venv/bin/python bench/robust.py                          # 8 seeds × 10,000 participants
    .venv/bin/python bench/robust.py --participants 2000 --seeds 8 --checkpoint-dir DIR

For each default category's K = 4 checkpoint, 12 answers: consistent yes/no answers, 5 % and 10 %
slips, a preference changed after answer 6, and the paper's Gaussian σ² = .1 feedback (with the
replication set, models/pretrained/replication, trained for it). Beside C2 (``meta``): C1 (Exp3,
γ = .5) and two exact references (the forward filter, models/learners/belief.py):

- ``model``: the filter for the model C2 was meta-trained for (recorded in its checkpoint), which
  knows no more about the participants than C2 does: the issue's "exact filter for the same
  model", which the ratio targets compare with;
- ``oracle``: the filter that knows how these participants answer (their slip rate exactly; in
  the change scenario a hazard of .02).

Every figure is a mean over ``--seeds`` seeds (2026, 2027, …; each seed its own participants)
with its spread: ``±`` the standard deviation over seeds and the range. One seed can flatter by
20 % (issue 36 found seed 2026 the easiest of eight), so targets are judged on the means. Each
target is printed as met or missed with its figure. Same seeds, same figures; never a test
assertion.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

_ROOT = Path(__file__).resolve().parents[1]
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _ROOT / "bench"]
sys.path.insert(0, str(_ROOT))

import numpy as np  # noqa: E402

from bench.analysis import cpu_model  # noqa: E402
from models.checkpoints import (  # noqa: E402
    REPLICATION_DIR,
    Checkpoint,
    load_checkpoint,
    shipped_checkpoint,
    trained_feedback,
)
from models.feedback import FeedbackModel  # noqa: E402
from models.learners.exp3 import DEFAULT_EXP3_GAMMA  # noqa: E402
from models.simulate import Scenario, mean_p_correct, simulate_adaptation  # noqa: E402
from models.tasks import TaskDistribution  # noqa: E402

CATEGORIES = ("conation", "affection", "cognition")
FIGURES = ("iterations_to_95", "reached_95", "wrong_95", "mean_p", "recovered", "p_new_final")
Figures = dict[str, list[float]]
"""One learner's figure name → its value for each seed."""
Target = tuple[str, Callable[[Figures, Figures], tuple[bool, str]]]


def mean(values: list[float]) -> float:
    return float(np.mean(values))


def spread(values: list[float]) -> str:
    """``mean ± sd [min–max]`` over seeds."""
    return (
        f"{np.mean(values):.4f} ± {np.std(values, ddof=1) if len(values) > 1 else 0.0:.4f} "
        f"[{min(values):.4f}–{max(values):.4f}]"
    )


def _at_most(key: str, limit: float) -> Target:
    return (
        f"meta {key} ≤ {limit:g}",
        lambda meta, _ref: (mean(meta[key]) <= limit, f"{mean(meta[key]):.4f}"),
    )


def _at_least(key: str, limit: float) -> Target:
    return (
        f"meta {key} ≥ {limit:g}",
        lambda meta, _ref: (mean(meta[key]) >= limit, f"{mean(meta[key]):.4f}"),
    )


def _ratio(key: str, factor: float) -> Target:
    """meta's mean ``key`` within ``factor`` × the model reference's (ratio of the means over
    seeds, with the range of the per-seed ratios)."""

    def check(meta: Figures, ref: Figures) -> tuple[bool, str]:
        ratio = mean(meta[key]) / max(mean(ref[key]), 1e-12)
        per_seed = [m / r for m, r in zip(meta[key], ref[key], strict=True) if r > 0]
        span = f" [{min(per_seed):.2f}–{max(per_seed):.2f}]" if per_seed else ""
        return ratio <= factor, f"{ratio:.2f}{span}"

    return f"{key} ≤ {factor:g} × reference (model)", check


SCENARIOS: dict[str, tuple[Scenario, list[Target]]] = {
    "consistent yes/no": (
        Scenario(feedback=FeedbackModel()),
        [
            _at_most("iterations_to_95", 3.5),
            _at_most("wrong_95", 0.01),
            _ratio("iterations_to_95", 1.1),
        ],
    ),
    "5 % slips": (
        Scenario(feedback=FeedbackModel(slips=(0.05,))),
        [_ratio("wrong_95", 1.25), _ratio("iterations_to_95", 1.1)],
    ),
    "10 % slips": (
        Scenario(feedback=FeedbackModel(slips=(0.1,))),
        [
            _ratio("wrong_95", 1.25),
            _at_least("reached_95", 0.97),
            _ratio("iterations_to_95", 1.1),
        ],
    ),
    "preference changed after answer 6": (
        Scenario(feedback=FeedbackModel(hazard=0.02), change_after=6),
        [_at_least("recovered", 0.85), _at_least("p_new_final", 0.9)],
    ),
    "paper's Gaussian σ² = .1": (
        Scenario(feedback=FeedbackModel.paper(0.1)),
        [_at_most("iterations_to_95", 3.4), _at_most("wrong_95", 0.01)],
    ),
}


def _figures(summary: dict[str, Any]) -> dict[str, float]:
    values = {key: float(summary[key]) for key in FIGURES if key in summary}
    values["mean_p"] = mean_p_correct(summary)
    return values


def run_scenario(
    checkpoint: Checkpoint, scenario: Scenario, participants: int, seeds: list[int]
) -> dict[str, Figures]:
    """Every learner's figures for each seed: C1, C2, the oracle and the model reference."""
    collected: dict[str, Figures] = {}

    def run(kinds: tuple[str, ...], case: Scenario, seed: int) -> dict[str, Any]:
        return simulate_adaptation(
            TaskDistribution(4),
            participants=participants,
            iterations=12,
            seed=seed,
            checkpoint=checkpoint,
            gamma=DEFAULT_EXP3_GAMMA,
            learners=kinds,
            scenario=case,
        )["learners"]

    assumed = replace(scenario, assumed=trained_feedback(checkpoint))
    for seed in seeds:
        learners = run(("exp3", "meta", "bayes"), scenario, seed)
        learners["oracle"] = learners.pop("bayes")
        learners["model"] = run(("bayes",), assumed, seed)["bayes"]
        for name, summary in learners.items():
            for key, value in _figures(summary).items():
                collected.setdefault(name, {}).setdefault(key, []).append(value)
    return collected


def main() -> None:
    """Every scenario for every category; prints each learner's means and each target."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--participants", type=int, default=10_000)
    parser.add_argument("--seed", type=int, default=2026, help="the first seed")
    parser.add_argument("--seeds", type=int, default=8, help="how many seeds (≥ 8 for the docs)")
    parser.add_argument("--checkpoint-dir", type=Path, default=None)
    parser.add_argument("--category", choices=CATEGORIES, action="append", default=None)
    parser.add_argument("--scenario", choices=list(SCENARIOS), action="append", default=None)
    args = parser.parse_args()
    seeds = list(range(args.seed, args.seed + args.seeds))
    print(
        f"# {platform.python_implementation()} {platform.python_version()}, "
        f"nproc={os.cpu_count()}, CPU: {cpu_model()}; {args.participants} participants × "
        f"{len(seeds)} seeds ({seeds[0]}–{seeds[-1]}), K = 4, 12 answers; "
        "mean ± sd over seeds [range]"
    )
    missed = total = 0
    for category in args.category or CATEGORIES:
        robust = load_checkpoint(shipped_checkpoint(4, category, directory=args.checkpoint_dir), 4)
        replication = load_checkpoint(shipped_checkpoint(4, category, directory=REPLICATION_DIR), 4)
        print(f"\n## {category}: {robust.path} ({robust.sha256[:12]})")
        for title in args.scenario or SCENARIOS:
            scenario, targets = SCENARIOS[title]
            start = time.perf_counter()
            gaussian = scenario.feedback is not None and scenario.feedback.kind == "gaussian"
            checkpoint = replication if gaussian else robust
            learners = run_scenario(checkpoint, scenario, args.participants, seeds)
            print(
                f"{title} ({scenario.describe()}; C2 {checkpoint.path.parent.parent.name}/"
                f"{checkpoint.path.name}; {time.perf_counter() - start:.1f} s)"
            )
            for name, figures in learners.items():
                shown: tuple[str, ...] = ("iterations_to_95", "reached_95", "wrong_95", "mean_p")
                if "recovered" in figures:
                    shown += ("recovered", "p_new_final")
                print(f"  {name:<6} " + "  ".join(f"{k} {spread(figures[k])}" for k in shown))
            checks = [
                (label, *check(learners["meta"], learners["model"])) for label, check in targets
            ]
            ahead = mean(learners["meta"]["mean_p"]) > mean(learners["exp3"]["mean_p"])
            checks.append(("C2 ahead of C1 on mean p", ahead, ""))
            for label, ok, figure in checks:
                missed += not ok
                total += 1
                print(f"    {'met   ' if ok else 'MISSED'} {label} {figure}")
    print(f"\n{missed} of {total} target(s) missed")


if __name__ == "__main__":
    main()
