"""Benchmark: which lines the robot says, per condition and answer, under each reply basis.

Run from the repository root::

    .venv/bin/python bench/replies.py                    # 2,000 participants a seed, 8 seeds
    .venv/bin/python bench/replies.py --participants 500 --seeds 2026 2027

Simulated participants answer as the shipped protocol's feedback model says (yes/no answers that
slip at a rate drawn from 0–10 %, a preference that changes with hazard .02), preferring one of
the four questions of each category (uniform prior), 12 answers each. C1 is Exp3 (the protocol's
γ), C2 the shipped checkpoint of the category. Each answer's reply level is computed under the
paper's rule (``chosen``, the replication setting) and the shipped default (``heard``) from the
same answers, so the two tables differ only by the basis. Printed per condition and answer: the
share of each level's line (mean over seeds ± their standard deviation), and ``contra``: the share
of answers whose line says the robot expected them ("medium" or "high") although it gave the
answer it heard a probability below .5, or says it does not believe them ("low") although it gave
them .5 or more. Same seeds, same figures; never a test assertion.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
from pathlib import Path

import numpy as np

_ROOT = Path(__file__).resolve().parents[1]
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _ROOT / "bench"]
sys.path.insert(0, str(_ROOT))

from app.protocol import Protocol, default_protocol  # noqa: E402
from app.services.sessions.learners import feedback_model  # noqa: E402
from bench.analysis import cpu_model  # noqa: E402
from models.checkpoints import load_checkpoint, shipped_checkpoint  # noqa: E402
from models.feedback import FeedbackModel  # noqa: E402
from models.replies import exp3_beliefs, heard_probabilities  # noqa: E402
from models.simulate import BatchExp3, BatchLearner, BatchMetaPolicy, sample_actions  # noqa: E402

ANSWERS = 12
BASES = ("chosen", "heard")
CONDITIONS = ("C1", "C2")


def _answers(
    learner: BatchLearner, feedback: FeedbackModel, n: int, n_arms: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """(asked probability, said yes), each (n, 12), of one category's simulated participants."""
    preferred = rng.integers(0, n_arms, n)
    slips = feedback.sample_slips(rng, n)
    prior = np.full(n_arms, 1.0 / n_arms)
    rows = np.arange(n)
    asked = np.empty((n, ANSWERS))
    said_yes = np.empty((n, ANSWERS), dtype=bool)
    for t in range(ANSWERS):
        probs = np.broadcast_to(learner.probabilities(), (n, n_arms))
        actions = sample_actions(probs, rng)
        asked[:, t] = probs[rows, actions]
        rewards = feedback.rewards(rng, actions == preferred, slips)
        said_yes[:, t] = np.abs(rewards - feedback.yes) < np.abs(rewards - feedback.no)
        learner.update(actions, rewards)
        preferred = feedback.change_preference(rng, preferred, prior)
    return asked, said_yes


def _shares(
    protocol: Protocol, asked: np.ndarray, belief: np.ndarray, said_yes: np.ndarray, slip: float
) -> dict[tuple[str, str], np.ndarray]:
    """Per (answer, basis): the share of each level, and last the share of contradictions."""
    thresholds = np.asarray(protocol.replies.thresholds)
    heard = heard_probabilities(belief, said_yes, slip=slip)
    probability = {"chosen": asked, "heard": heard}
    out = {}
    for answer, mask in (("yes", said_yes), ("no", ~said_yes)):
        for basis in BASES:
            levels = np.searchsorted(thresholds, probability[basis][mask], side="right")
            expected = heard[mask] >= 0.5
            contra = np.where(expected, levels == 0, levels >= 2).mean()
            counts = np.bincount(levels, minlength=len(thresholds) + 1) / max(levels.size, 1)
            out[(answer, basis)] = np.append(counts, contra)
    return out


def _one_seed(protocol: Protocol, n: int, seed: int) -> dict[tuple[str, str, str], np.ndarray]:
    feedback = feedback_model(protocol)
    gamma = protocol.learners.exp3.gamma
    pooled: dict[str, list[np.ndarray]] = {c: [] for c in CONDITIONS}
    for index, category in enumerate(protocol.categories):
        n_arms = len(category.questions)
        checkpoint = load_checkpoint(shipped_checkpoint(n_arms, category.name), n_arms)
        for condition in CONDITIONS:
            rng = np.random.default_rng([seed, index, CONDITIONS.index(condition)])
            learner: BatchLearner
            if condition == "C1":
                learner = BatchExp3(n, n_arms, gamma)
            else:
                learner = BatchMetaPolicy(checkpoint)
            asked, said_yes = _answers(learner, feedback, n, n_arms, rng)
            belief = exp3_beliefs(asked, gamma=gamma, n_arms=n_arms) if condition == "C1" else asked
            pooled[condition].append(np.stack([asked, belief, said_yes]))
    result = {}
    for condition, parts in pooled.items():
        asked, belief, said = np.concatenate(parts, axis=1)
        shares = _shares(protocol, asked, belief, said.astype(bool), feedback.mean_slip)
        for (answer, basis), values in shares.items():
            result[(condition, answer, basis)] = values
    return result


def main() -> None:
    """Every seed, then one table of means ± standard deviations over the seeds."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--participants", type=int, default=2000, help="per category and seed")
    parser.add_argument("--seeds", type=int, nargs="+", default=list(range(2026, 2034)))
    args = parser.parse_args()
    protocol = default_protocol().protocol
    names = [level.name for level in protocol.replies.levels]
    print(
        f"# {platform.python_implementation()} {platform.python_version()}, "
        f"nproc={os.cpu_count()}, CPU: {cpu_model()}; {args.participants} participants per "
        f"category, seeds {args.seeds[0]}–{args.seeds[-1]} ({len(args.seeds)}), {ANSWERS} answers; "
        f"shipped protocol's feedback: {feedback_model(protocol).describe()}"
    )
    runs = [_one_seed(protocol, args.participants, seed) for seed in args.seeds]
    header = ["condition", "answer", "basis", *names, "contra"]
    print("| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    for key in runs[0]:
        values = np.stack([run[key] for run in runs])
        cells = [f"{m:.3f} ± {s:.3f}" for m, s in zip(values.mean(0), values.std(0), strict=True)]
        print("| " + " | ".join([*key, *cells]) + " |")


if __name__ == "__main__":
    main()
