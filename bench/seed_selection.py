"""Choose among checkpoints trained with different seeds, on one fixed validation set.

Run from the repository root::

    .venv/bin/python bench/seed_selection.py DIR [DIR ...]        # checkpoint directories
    .venv/bin/python bench/seed_selection.py --participants 20000 DIR ...
    .venv/bin/python bench/seed_selection.py --targets DIR ...      # also the issue's figures

Scores every checkpoint by the filter objective (models/seed_selection.py) on the same
participants, drawn from the model each checkpoint was trained for with the selection seed, and
names the best per category and K. ``--targets`` also measures issue 36 item 2's figures on
validation draws (models.seed_selection.target_validation: the issue's scenarios, 20,000
participants each, the selection seed) and applies the selection rule for shipped checkpoints
(models.seed_selection.select_by_targets): among the candidates that meet every target on those
draws, the best filter objective; if none does, the shipped checkpoint stays. The bench
(bench/robust.py, seeds 2026 onwards) stays a held-out check: nothing it measures is used here.
Prints figures only; never used as a test assertion.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

_ROOT = Path(__file__).resolve().parents[1]
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _ROOT / "bench"]
sys.path.insert(0, str(_ROOT))

from models.checkpoints import (  # noqa: E402
    PRETRAINED_DIR,
    load_checkpoint,
    shipped_checkpoint,
    trained_feedback,
)
from models.seed_selection import (  # noqa: E402
    SELECTION_SEED,
    Candidate,
    Score,
    best_by_validation,
    filter_validation,
    select_by_targets,
    shortfalls,
    target_validation,
)


def _shipped_hash(category: str, arms: int) -> str | None:
    """The hash of the default set's checkpoint for ``category`` and K (None: none ships)."""
    try:
        return load_checkpoint(shipped_checkpoint(arms, category, directory=PRETRAINED_DIR)).sha256
    except (FileNotFoundError, ValueError):
        return None


def main() -> None:
    """Score each checkpoint and name the best of each category."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoints", type=Path, nargs="+")
    parser.add_argument("--participants", type=int, default=10_000)
    parser.add_argument("--seed", type=int, default=SELECTION_SEED)
    parser.add_argument("--targets", action="store_true", help="also the issue's figures")
    args = parser.parse_args()
    groups: dict[tuple[str, int, str], list[Score]] = {}
    candidates: dict[tuple[str, int, str], list[Candidate]] = {}
    print(f"# filter objective on {args.participants} participants, seed {args.seed}")
    for path in args.checkpoints:
        checkpoint = load_checkpoint(path)
        start = time.perf_counter()
        score = filter_validation(checkpoint, args.participants, args.seed)
        shipped = checkpoint.sha256 == _shipped_hash(checkpoint.category, checkpoint.n_arms)
        print(
            f"{path}  ({checkpoint.sha256[:12]}{', shipped' if shipped else ''})  "
            f"{score.filter_score:.5f} ± {score.standard_error:.5f}  "
            f"({time.perf_counter() - start:.1f} s)"
        )
        key = (checkpoint.category, checkpoint.n_arms, trained_feedback(checkpoint).describe())
        groups.setdefault(key, []).append(score)
        if args.targets:
            figures = target_validation(checkpoint, seed=args.seed)
            wrong = ", ".join(f"{v:.2f} × at {k}" for k, v in figures.wrong_ratio.items())
            answers = " / ".join(f"{v:.3f}" for v in figures.answers_ratio.values())
            missed = shortfalls(figures)
            print(
                f"    wrong {wrong}; answers {answers} × ({', '.join(figures.answers_ratio)}); "
                f"recovered {figures.recovered:.3f} (filter {figures.filter_recovered:.3f}); "
                + ("qualifies" if not missed else "misses: " + "; ".join(missed))
            )
            candidates.setdefault(key, []).append(Candidate(str(path), score.filter_score, figures))
    for key, scores in groups.items():
        category, arms, _ = key
        best = best_by_validation(scores)
        print(f"best {category} K = {arms}: {best.checkpoint.path} ({best.filter_score:.5f})")
        if args.targets:
            chosen = select_by_targets(candidates[key])
            print(
                f"selected by the targets {category} K = {arms}: "
                + (
                    f"{chosen.name} ({chosen.filter_score:.5f})"
                    if chosen is not None
                    else "none qualifies, the shipped checkpoint stays"
                )
            )


if __name__ == "__main__":
    main()
