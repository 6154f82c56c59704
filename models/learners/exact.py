"""The exact learner for a declared feedback model: what a ``bayes`` condition runs (issue 36).

A lab that compares C2's meta-learned policy with the optimal statistical learner gives a
condition the exact posterior over what the participant prefers, under the participant model its
protocol declares (:mod:`models.feedback`), acting by posterior sampling. Two filters compute it:

- the seed paper's model (Gaussian answers, no slips, one preference for the whole study):
  :class:`models.learners.bayes.BayesLearner`, the reference issue 3 measured C2 against. It adds
  log-likelihoods, so it stays exact however small σ² is;
- every other model (yes/no answers, slips, a hazard of changing preference, or Gaussian answers
  with slips or a hazard): :class:`models.learners.belief.BeliefLearner`, the forward filter over
  (slip rate, preferred question). For the paper's model it is the same posterior in exact
  arithmetic, but it multiplies densities before taking their logarithm, and those underflow to
  0 once (yes − no)² / (2σ²) passes about 745: the Bayes learner is the one that is exact there.

:func:`unsupported` says which declared models cannot run as a live condition, and why.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from models.feedback import FeedbackModel
from models.learners.bayes import BayesLearner
from models.learners.belief import BeliefLearner
from models.tasks import TaskDistribution


def uses_bayes_learner(feedback: FeedbackModel) -> bool:
    """Whether the exact filter for ``feedback`` is the plain Bayes posterior (the paper's model:
    Gaussian answers that never slip, a preference that never changes)."""
    return feedback.kind == "gaussian" and not feedback.has_slips_or_changes


def exact_learner(
    n_arms: int, feedback: FeedbackModel, prior: Sequence[float] | None = None
) -> BayesLearner | BeliefLearner:
    """A fresh exact learner for participants who answer as ``feedback`` says, whose preferred
    question is drawn from ``prior`` (uniform when None). See the module docstring for which."""
    if uses_bayes_learner(feedback):
        tasks = TaskDistribution(
            n_arms=n_arms,
            preferred_prior=None if prior is None else tuple(float(p) for p in prior),
            mu_preferred=feedback.yes,
            mu_other=feedback.no,
            variance=feedback.variance,
        )
        return BayesLearner(tasks)
    return BeliefLearner(n_arms, feedback, None if prior is None else np.asarray(prior))


def unsupported(feedback: FeedbackModel) -> list[tuple[str, str]]:
    """Why the exact filter cannot run as a live condition for ``feedback``: ``(attribute of the
    model, reason)`` pairs, none when it can.

    A live condition must learn from every answer a participant gives. Two models make a real
    answer impossible, and an impossible answer leaves no posterior to continue from (the filter
    would have to ignore it, and the participant's answers would stop counting):

    - yes/no answers that never slip, with a preference that never changes: after one "yes" the
      filter is certain, and any later answer that contradicts it cannot happen under the model;
    - Gaussian answers that never slip, with σ² so small that (yes − no)² / (2σ²) overflows: the
      first answer leaves every other question at probability exactly 0, and a "no" to the one
      left has no question to go to.
    """
    slips = feedback.slip_values[feedback.slip_prior > 0]
    problems = []
    if feedback.kind == "binary" and not np.any(slips > 0) and feedback.hazard == 0:
        problems.append(
            (
                "slips",
                "with yes/no answers that never slip and a preference that never changes, the "
                "exact filter is certain after one yes and would have to ignore any answer that "
                "contradicts it: declare a slip rate (slip or slip_values) or a hazard",
            )
        )
    if uses_bayes_learner(feedback) and not math.isfinite(
        (feedback.yes - feedback.no) ** 2 / (2 * feedback.variance)
    ):
        problems.append(
            (
                "variance",
                f"σ² {feedback.variance:g} is too small for rewards {feedback.yes:g} and "
                f"{feedback.no:g}: every answer's log-likelihood overflows, so one answer would "
                "rule out every other question for good",
            )
        )
    return problems
