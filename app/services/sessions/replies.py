"""The robot's reply to an answer, as the protocol's ``[replies]`` table says.

One function for the live answer (app.services.sessions.runtime) and for whoever checks a reply
afterwards, so the line a participant heard can always be recomputed from the step log: the
probabilities the question was asked with and after learning, the answer, and the learner's kind.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from app.protocol import Protocol
from app.services.sessions.learners import LearnerSpec, feedback_model
from models.replies import confidence_level, exp3_belief, reply_probability


@dataclass(frozen=True)
class Reply:
    """What the robot says, and why: the probability of the protocol's basis and its level."""

    probability: float
    level: int
    name: str
    text: str


def asked_belief(spec: LearnerSpec, before: Sequence[float], action: int) -> float:
    """The learner's belief, before the answer, that the asked question is the one the
    participant says yes to: the probability it asked with, except Exp3's exploration floor
    (models.replies.exp3_belief). For C2's policy the probability is what meta-training shaped
    towards the preferred question; for a posterior-sampling learner (a ``bayes`` condition's
    exact filter) it is the posterior that the asked question is the preferred one.

    The "heard" basis turns this belief into the probability of a yes with the declared mean
    slip rate, for every learner alike. For the exact filter with a slip prior, its own
    predictive probability of a yes would weigh the slip rates by their posterior instead; it is
    not used, because a reply must be recomputable from the step log (``trustlab verify``),
    which records the probabilities but not the filter's belief about the slip rate."""
    asked = float(before[action])
    if spec.kind == "exp3":
        return exp3_belief(asked, gamma=float(spec.config["gamma"]), n_arms=spec.n_arms)
    return asked


def choose_reply(
    protocol: Protocol,
    spec: LearnerSpec,
    *,
    before: Sequence[float],
    action: int,
    after: Sequence[float],
    said_yes: bool,
) -> Reply:
    """The reply to ``said_yes`` on question ``action``, asked with ``before`` and learnt into
    ``after`` (equal to ``before`` when the step does not adapt)."""
    replies = protocol.replies
    heard = replies.basis == "heard"  # only it predicts the answer, with the declared slips
    probability = reply_probability(
        replies.basis,
        asked=float(before[action]),
        updated=float(after[action]),
        belief=asked_belief(spec, before, action),
        said_yes=said_yes,
        slip=feedback_model(protocol).mean_slip if heard else 0.0,
    )
    level = confidence_level(probability, replies.thresholds)
    chosen = replies.levels[level]
    return Reply(probability, level, chosen.name, chosen.line(said_yes))
