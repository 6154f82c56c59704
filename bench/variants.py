"""Benchmark: the design choices behind C2, re-measured (docs/engine.md, "Deviations").

Run from the repository root (one training after another, one thread; 2–5 minutes each)::

    .venv/bin/python bench/variants.py
    .venv/bin/python bench/variants.py --variants reward reward_unlimited

Trains conation K = 4 online-mode variants with the replication set's configuration (the paper's
Gaussian participants, models/pretrained/replication) except for one choice, and evaluates each
deployed (12 single answers) on 20,000 such simulated participants, seed 2026 (the default set's
choices are measured by bench/robust.py and docs/engine.md, "C2 for real participants"):

- ``shipped``: log-score objective, natural step on the expected gradient (``natural_expected``),
  step-scale calibration to wrong_95 ≤ .0075, selection of the snapshot fastest once calibrated;
- ``uncalibrated``: the same without the calibration (selection: wrong_95 ≤ .0095);
- ``score_function``: the natural step on the score-function gradient (``natural``, the previous
  default), calibrated the same way;
- ``reward``: the issue's expected-reward objective, same selection and calibration;
- ``reward_unlimited``: expected reward with no limit on wrong_95 in selection or calibration;
- ``plain_gradient``: the plain policy-gradient step instead of a natural one.

Prints figures only; never used as a test assertion.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
from pathlib import Path

_ROOT = Path(__file__).resolve().parents[1]
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _ROOT / "bench"]
sys.path.insert(0, str(_ROOT))

from bench.analysis import cpu_model  # noqa: E402
from models.checkpoints import Checkpoint  # noqa: E402
from models.pretrain import PretrainArgs, pretrain  # noqa: E402
from models.simulate import mean_p_correct, simulate_learner, summarise  # noqa: E402
from models.tasks import TaskDistribution  # noqa: E402

VARIANTS: dict[str, dict[str, object]] = {
    "shipped": {},
    "uncalibrated": {"calibrate": False},
    "score_function": {"online_rule": "natural"},
    "reward": {"objective": "reward"},
    "reward_unlimited": {"objective": "reward", "wrong_limit": 1.0, "calibrate": False},
    "plain_gradient": {"online_rule": "gradient"},
}


def evaluate(checkpoint: Checkpoint, participants: int, seed: int) -> dict[str, float]:
    """The deployed learner's figures at K = 4, 12 answers."""
    summary = summarise(
        simulate_learner(
            "meta",
            TaskDistribution(4),
            participants=participants,
            iterations=12,
            seed=seed,
            checkpoint=checkpoint,
        )
    )
    return {**summary, "mean_p_correct": mean_p_correct(summary)}


def main() -> None:
    """Train and evaluate each requested variant."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    parser.add_argument("--participants", type=int, default=20_000)
    parser.add_argument("--seed", type=int, default=2026)
    args = parser.parse_args()
    print(
        f"# {platform.python_implementation()} {platform.python_version()}, "
        f"nproc={os.cpu_count()}, CPU: {cpu_model()}; conation K = 4, evaluation "
        f"{args.participants} participants, seed {args.seed}"
    )
    for name in args.variants:
        print(f"  training {name} …", file=sys.stderr, flush=True)
        train_args = PretrainArgs(category="conation", evaluation_participants=100)
        for key, value in VARIANTS[name].items():
            setattr(train_args, key, value)
        with tempfile.TemporaryDirectory() as tmp:
            checkpoint = pretrain(train_args, Path(tmp) / name)
        s = evaluate(checkpoint, args.participants, args.seed)
        print(
            f"{name:<17} answers to 95 % {s['iterations_to_95']:.2f}  reached "
            f"{s['reached_95']:.3f}  wrong {s['wrong_95']:.4f}  mean p(1..12) "
            f"{s['mean_p_correct']:.3f}  (train {checkpoint.metrics['train_seconds']:.0f} s, "
            f"selected iteration {checkpoint.metrics['selected_iteration']}, step scale "
            f"{checkpoint.metrics['calibration'].get('scale', 'none')})",
            flush=True,
        )


if __name__ == "__main__":
    main()
