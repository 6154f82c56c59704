"""Choose among checkpoints trained with different seeds, on one fixed validation set.

Run from the repository root::

    .venv/bin/python bench/seed_selection.py DIR [DIR ...]        # checkpoint directories
    .venv/bin/python bench/seed_selection.py --participants 20000 DIR ...
    .venv/bin/python bench/seed_selection.py --targets DIR ...      # also the issue's figures
    .venv/bin/python bench/seed_selection.py --temperatures DIR     # calibrations of DIR
    .venv/bin/python bench/seed_selection.py --temperatures --write OUT DIR

Scores every checkpoint by the filter objective (models/seed_selection.py) on the same
participants, drawn from the model each checkpoint was trained for with the selection seed, and
names the best per category and K. ``--targets`` also measures issue 36 item 2's figures on
validation draws (models.seed_selection.target_validation: the issue's scenarios, 20,000
participants each, the selection seed) and applies the selection rule for shipped checkpoints
(models.seed_selection.select_by_targets): among the candidates that meet every target on those
draws, the best filter objective; if none does, the shipped checkpoint stays. ``--temperatures``
makes the candidates each checkpoint calibrated by every temperature of
models.seed_selection.TEMPERATURES (1 to 1.1 by .0025; 1 is the checkpoint as trained), measured
and selected by the same rule; ``--write OUT`` writes the selected one, with its temperature, to
OUT/<category>-k<K> (models.checkpoints.with_temperature). The bench (bench/robust.py, seeds
2026 onwards) stays a held-out check: nothing it measures is used here. Prints figures only;
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

from models.checkpoints import (  # noqa: E402
    PRETRAINED_DIR,
    Checkpoint,
    checkpoint_name,
    load_checkpoint,
    shipped_checkpoint,
    trained_feedback,
    with_temperature,
)
from models.seed_selection import (  # noqa: E402
    SELECTION_SEED,
    TEMPERATURES,
    VALIDATION_PARTICIPANTS,
    Candidate,
    Score,
    TargetFigures,
    best_by_validation,
    filter_validation,
    select_by_targets,
    shortfalls,
    target_validation,
    temperature_candidates,
)


def _shipped_hash(category: str, arms: int) -> str | None:
    """The hash of the default set's checkpoint for ``category`` and K (None: none ships)."""
    try:
        return load_checkpoint(shipped_checkpoint(arms, category, directory=PRETRAINED_DIR)).sha256
    except (FileNotFoundError, ValueError):
        return None


def _describe(figures: TargetFigures) -> str:
    wrong = ", ".join(f"{v:.2f} × at {k}" for k, v in figures.wrong_ratio.items())
    answers = " / ".join(f"{v:.3f}" for v in figures.answers_ratio.values())
    missed = shortfalls(figures)
    return (
        f"wrong {wrong}; answers {answers} × ({', '.join(figures.answers_ratio)}); "
        f"recovered {figures.recovered:.3f} (filter {figures.filter_recovered:.3f}); "
        + ("qualifies" if not missed else "misses: " + "; ".join(missed))
    )


def calibrate(paths: list[Path], seed: int, write: Path | None) -> None:
    """Each checkpoint at every temperature, the rule's choice, and (``write``) the chosen one
    written with its temperature."""
    for path in paths:
        checkpoint = load_checkpoint(path)
        print(
            f"# {path} ({checkpoint.sha256[:12]}): temperatures {TEMPERATURES[0]:g}–"
            f"{TEMPERATURES[-1]:g}, validation draws seed {seed}"
        )
        found = temperature_candidates(checkpoint, seed=seed)
        for temperature, candidate in found:
            print(
                f"T = {temperature:<7g} {candidate.filter_score:.5f}  "
                f"{_describe(candidate.figures)}",
                flush=True,
            )
        chosen = select_by_targets([candidate for _, candidate in found])
        if chosen is None:
            print("none qualifies: the checkpoint stays as it is")
            continue
        temperature = next(t for t, c in found if c is chosen)
        print(f"selected: temperature {temperature:g} ({chosen.filter_score:.5f})")
        if write is not None:
            written = _write(checkpoint, temperature, chosen, write, seed)
            print(f"written: {written.path} (sha256 {written.sha256[:12]})")


def _write(
    checkpoint: Checkpoint, temperature: float, chosen: Candidate, out: Path, seed: int
) -> Checkpoint:
    note = {
        "selected_by": "models.seed_selection.select_by_targets over temperature_candidates",
        "temperatures": [TEMPERATURES[0], TEMPERATURES[-1], len(TEMPERATURES)],
        "validation_seed": seed,
        "validation_participants": VALIDATION_PARTICIPANTS,
        "filter_score": chosen.filter_score,
        "wrong_ratio": chosen.figures.wrong_ratio,
        "answers_ratio": chosen.figures.answers_ratio,
        "recovered": chosen.figures.recovered,
        "filter_recovered": chosen.figures.filter_recovered,
    }
    directory = out / checkpoint_name(checkpoint.category, checkpoint.n_arms)
    return with_temperature(checkpoint, temperature, directory, note=note)


def main() -> None:
    """Score each checkpoint and name the best of each category."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoints", type=Path, nargs="+")
    parser.add_argument("--participants", type=int, default=10_000)
    parser.add_argument("--seed", type=int, default=SELECTION_SEED)
    parser.add_argument("--targets", action="store_true", help="also the issue's figures")
    parser.add_argument(
        "--temperatures", action="store_true", help="select a temperature for each checkpoint"
    )
    parser.add_argument("--write", type=Path, default=None, help="with --temperatures: OUT dir")
    args = parser.parse_args()
    if args.write is not None and not args.temperatures:
        parser.error("--write needs --temperatures")
    if args.temperatures:
        calibrate(args.checkpoints, args.seed, args.write)
        return
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
            print(f"    {_describe(figures)}")
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
