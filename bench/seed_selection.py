"""Choose among checkpoints trained with different seeds, on one fixed validation set.

Run from the repository root::

    .venv/bin/python bench/seed_selection.py DIR [DIR ...]        # checkpoint directories
    .venv/bin/python bench/seed_selection.py --participants 20000 DIR ...
    .venv/bin/python bench/seed_selection.py --targets DIR ...      # also the issue's figures

Scores every checkpoint by the filter objective (models/seed_selection.py) on the same
participants, drawn from the model each checkpoint was trained for with the selection seed, and
names the best per category and K. ``--targets`` also prints the issue's figures on 20,000
participants of the training model (models.seed_selection.target_validation), which the filter
objective barely separates (docs/engine.md, "C2 calibrated under slips"). The bench
(bench/robust.py) stays a held-out check: nothing it measures is used here. Prints figures only;
never used as a test assertion.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

_ROOT = Path(__file__).resolve().parents[1]
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _ROOT / "bench"]
sys.path.insert(0, str(_ROOT))

from models.checkpoints import load_checkpoint, trained_feedback  # noqa: E402
from models.seed_selection import (  # noqa: E402
    SELECTION_SEED,
    Score,
    best_by_validation,
    filter_validation,
    target_validation,
)


def main() -> None:
    """Score each checkpoint and name the best of each category."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoints", type=Path, nargs="+")
    parser.add_argument("--participants", type=int, default=10_000)
    parser.add_argument("--seed", type=int, default=SELECTION_SEED)
    parser.add_argument("--targets", action="store_true", help="also the issue's figures")
    args = parser.parse_args()
    groups: dict[tuple[str, int, str], list[Score]] = {}
    print(f"# filter objective on {args.participants} participants, seed {args.seed}")
    for path in args.checkpoints:
        checkpoint = load_checkpoint(path)
        start = time.perf_counter()
        score = filter_validation(checkpoint, args.participants, args.seed)
        print(
            f"{path}  ({checkpoint.sha256[:12]})  {score.filter_score:.5f} ± "
            f"{score.standard_error:.5f}  ({time.perf_counter() - start:.1f} s)"
        )
        if args.targets:
            figures = target_validation(checkpoint, seed=args.seed)
            print(
                f"    wrong {figures['wrong_ratio']:.2f} × filter, answers "
                f"{figures['answers_ratio']:.3f} ×, recovered {figures['recovered']:.3f} "
                f"(filter {figures['filter_recovered']:.3f})"
            )
        model = trained_feedback(checkpoint).describe()
        groups.setdefault((checkpoint.category, checkpoint.n_arms, model), []).append(score)
    for (category, arms, _), scores in groups.items():
        best = best_by_validation(scores)
        print(f"best {category} K = {arms}: {best.checkpoint.path} ({best.filter_score:.5f})")


if __name__ == "__main__":
    main()
