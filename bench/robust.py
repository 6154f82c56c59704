"""Benchmark: C2 on participants who behave like people, against issue 19's targets.

Run from the repository root::

    .venv/bin/python bench/robust.py                          # 10,000 participants, seed 2026
    .venv/bin/python bench/robust.py --participants 2000 --checkpoint-dir DIR

For each default category's K = 4 checkpoint, 12 answers: consistent yes/no answers, 5 % and 10 %
slips, a preference changed after answer 6, and the paper's Gaussian σ² = .1 feedback (with the
replication set, models/pretrained/replication, trained for it). Beside C2 (``meta``): C1 (Exp3,
γ = .5) and two exact references (the forward filter, models/learners/belief.py):

- ``model``: the filter for the model C2 was meta-trained for (recorded in its checkpoint), which
  knows no more about the participants than C2 does: the issue's "exact reference for the same
  model", and the one the 1.1 × target compares with;
- ``oracle``: the filter that knows how these participants answer (their slip rate exactly; in
  the change scenario a hazard of .02).

Each target of the issue is printed as met or missed, with the figure. Figures to stdout; same
seed, same figures; never a test assertion.
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

from bench.analysis import cpu_model  # noqa: E402
from models.checkpoints import (  # noqa: E402
    REPLICATION_DIR,
    load_checkpoint,
    shipped_checkpoint,
    trained_feedback,
)
from models.feedback import FeedbackModel  # noqa: E402
from models.learners.exp3 import DEFAULT_EXP3_GAMMA  # noqa: E402
from models.simulate import Scenario, mean_p_correct, simulate_adaptation  # noqa: E402
from models.tasks import TaskDistribution  # noqa: E402

CATEGORIES = ("conation", "affection", "cognition")
Target = tuple[str, Callable[[dict[str, Any], dict[str, Any]], tuple[bool, str]]]


def _at_most(key: str, limit: float) -> Target:
    return (
        f"meta {key} ≤ {limit:g}",
        lambda meta, _ref: (meta[key] <= limit, f"{meta[key]:.4f}"),
    )


def _at_least(key: str, limit: float) -> Target:
    return (
        f"meta {key} ≥ {limit:g}",
        lambda meta, _ref: (meta[key] >= limit, f"{meta[key]:.4f}"),
    )


def _near_reference(factor: float = 1.1) -> Target:
    def check(meta: dict[str, Any], ref: dict[str, Any]) -> tuple[bool, str]:
        ratio = meta["iterations_to_95"] / ref["iterations_to_95"]
        return ratio <= factor, f"{ratio:.2f}"

    return f"answers to .95 ≤ {factor:g} × reference (model)", check


SCENARIOS: dict[str, tuple[Scenario, list[Target]]] = {
    "consistent yes/no": (
        Scenario(feedback=FeedbackModel()),
        [_at_most("iterations_to_95", 3.5), _at_most("wrong_95", 0.01), _near_reference()],
    ),
    "5 % slips": (
        Scenario(feedback=FeedbackModel(slips=(0.05,))),
        [_at_most("wrong_95", 0.01), _near_reference()],
    ),
    "10 % slips": (
        Scenario(feedback=FeedbackModel(slips=(0.1,))),
        [_at_most("wrong_95", 0.03), _at_least("reached_95", 0.97), _near_reference()],
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


def main() -> None:
    """Every scenario for every category; prints each learner and each target."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--participants", type=int, default=10_000)
    parser.add_argument("--seed", type=int, default=2026)
    parser.add_argument("--checkpoint-dir", type=Path, default=None)
    parser.add_argument("--category", choices=CATEGORIES, action="append", default=None)
    args = parser.parse_args()
    print(
        f"# {platform.python_implementation()} {platform.python_version()}, "
        f"nproc={os.cpu_count()}, CPU: {cpu_model()}; {args.participants} participants, "
        f"seed {args.seed}, K = 4, 12 answers"
    )
    missed = 0
    for category in args.category or CATEGORIES:
        robust = load_checkpoint(shipped_checkpoint(4, category, directory=args.checkpoint_dir), 4)
        replication = load_checkpoint(shipped_checkpoint(4, category, directory=REPLICATION_DIR), 4)
        print(f"\n## {category}: {robust.path} ({robust.sha256[:12]})")
        for title, (scenario, targets) in SCENARIOS.items():
            start = time.perf_counter()
            gaussian = scenario.feedback is not None and scenario.feedback.kind == "gaussian"
            checkpoint = replication if gaussian else robust

            def run(kinds: tuple[str, ...], case: Scenario) -> dict[str, Any]:
                return simulate_adaptation(
                    TaskDistribution(4),
                    participants=args.participants,
                    iterations=12,
                    seed=args.seed,
                    checkpoint=checkpoint,  # noqa: B023 (called at once)
                    gamma=DEFAULT_EXP3_GAMMA,
                    learners=kinds,
                    scenario=case,
                )["learners"]

            learners = run(("exp3", "meta", "bayes"), scenario)
            learners["oracle"] = learners.pop("bayes")
            assumed = replace(scenario, assumed=trained_feedback(checkpoint))
            learners["model"] = run(("bayes",), assumed)["bayes"]
            print(
                f"{title} ({scenario.describe()}; C2 {checkpoint.path.parent.parent.name}/"
                f"{checkpoint.path.name}; {time.perf_counter() - start:.1f} s)"
            )
            for name, s in learners.items():
                extra = (
                    f"  recovered {s['recovered']:.3f}  p new {s['p_new_final']:.3f}"
                    if "recovered" in s
                    else ""
                )
                print(
                    f"  {name:<6} answers to .95 {s['iterations_to_95']:5.2f}  reached "
                    f"{s['reached_95']:.3f}  wrong {s['wrong_95']:.4f}  mean p "
                    f"{mean_p_correct(s):.3f}{extra}"
                )
            checks = [
                (label, *check(learners["meta"], learners["model"])) for label, check in targets
            ]
            ahead = mean_p_correct(learners["meta"]) > mean_p_correct(learners["exp3"])
            checks.append(("C2 ahead of C1 on mean p", ahead, ""))
            for label, ok, figure in checks:
                missed += not ok
                print(f"    {'met   ' if ok else 'MISSED'} {label} {figure}")
    print(f"\n{missed} target(s) missed")


if __name__ == "__main__":
    main()
