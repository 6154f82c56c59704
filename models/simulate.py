"""Objective measures: simulated participants answering the four learners (the paper's Results §A).

Each simulated participant prefers one question (drawn from the task prior) and answers with the
paper's Gaussian feedback, or as a :class:`Scenario` says: by a feedback model with slips and a
hazard of changed preference (models/feedback.py), and optionally with a preference that changes
after a given answer. The reference ``bayes`` is the exact posterior for the scenario's model: the
plain posterior without slips or changes, the forward filter (models/learners/belief.py) with them.
A learner asks ``iterations`` questions; after 0, 1, …, ``iterations``
answers we record its probability of the preferred question and whether any other question
reached 95 %. The learners run *batched* — one array row per participant — with exactly the update
rules of the deployed classes (:class:`~models.learners.exp3.Exp3`,
:class:`~models.learners.meta_policy.MetaPolicyLearner`,
:class:`~models.learners.bayes.BayesLearner`; a test checks each batch learner against its class),
so 20 000 participants take seconds, not minutes.

Numpy only: the same code runs inside meta-training's validation and from the command line.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from models.checkpoints import Checkpoint
from models.feedback import FeedbackModel, acceptable_sets, draw_other
from models.learners.belief import BatchBelief
from models.learners.exp3 import check_gamma
from models.learners.mlp_policy import (
    Params,
    hidden_and_logits,
    init_params,
    probabilities,
    retain,
    softmax,
    update_params,
)
from models.replies import DEFAULT_THRESHOLDS, LEVEL_NAMES
from models.tasks import TaskDistribution

TARGET = 0.95
"""The probability at which a learner counts as having identified a question."""

LEARNERS: tuple[str, ...] = ("exp3", "meta", "random_init", "bayes")
"""The learners ``trustlab simulate adaptation`` compares, in its output order."""


class BatchLearner(Protocol):
    """Many independent learners of one kind, one row per participant."""

    def probabilities(self) -> np.ndarray:
        """(n, K) probabilities of asking each question."""
        ...

    def update(self, actions: np.ndarray, rewards: np.ndarray) -> None:
        """Learn from one answer per participant."""
        ...


class BatchExp3:
    """Exp3 for ``n`` participants at once (same arithmetic as :class:`Exp3`)."""

    def __init__(self, n: int, n_arms: int, gamma: float) -> None:
        self.gamma = check_gamma(gamma)
        self.n_arms = n_arms
        self.weights = np.full((n, n_arms), 1.0 / n_arms)

    def probabilities(self) -> np.ndarray:
        """``(1 − γ) w/Σw + γ/K`` per row."""
        w = self.weights
        return (1.0 - self.gamma) * (w / w.sum(axis=1, keepdims=True)) + self.gamma / self.n_arms

    def update(self, actions: np.ndarray, rewards: np.ndarray) -> None:
        """``w_a ← w_a · exp(γ x̂ / K)`` with clipped rewards, then renormalise."""
        rows = np.arange(len(actions))
        x = np.clip(rewards, 0.0, 1.0)
        x_hat = x / self.probabilities()[rows, actions]
        weights = self.weights.copy()
        weights[rows, actions] *= np.exp(self.gamma * x_hat / self.n_arms)
        self.weights = weights / weights.sum(axis=1, keepdims=True)


class BatchBayes:
    """The exact posterior over the preferred question for ``n`` participants at once."""

    def __init__(self, n: int, tasks: TaskDistribution) -> None:
        self.tasks = tasks
        with np.errstate(divide="ignore"):
            self.log_posterior = np.tile(np.log(tasks.prior), (n, 1))

    def probabilities(self) -> np.ndarray:
        """The posterior, which posterior sampling also uses to choose."""
        z = np.exp(self.log_posterior - self.log_posterior.max(axis=1, keepdims=True))
        return z / z.sum(axis=1, keepdims=True)

    def update(self, actions: np.ndarray, rewards: np.ndarray) -> None:
        """Add each hypothesis's Gaussian log-likelihood of the reward."""
        t = self.tasks
        r = rewards[:, None]
        hit = actions[:, None] == np.arange(t.n_arms)
        mean = np.where(hit, t.mu_preferred, t.mu_other)
        posterior = self.log_posterior - (r - mean) ** 2 / (2 * t.variance)
        self.log_posterior = posterior - posterior.max(axis=1, keepdims=True)


class BatchMetaPolicy:
    """The meta-policy's network and one-answer update for ``n`` participants at once.

    ``params`` are either one network (shared start, broadcast on the first update) or already
    batched (``random_init``: one draw per participant).
    """

    def __init__(self, checkpoint: Checkpoint, params: Params | None = None) -> None:
        self.checkpoint = checkpoint
        self.initial: Params = dict(checkpoint.params if params is None else params)
        self.params: Params = dict(self.initial)
        # One anchor per participant when each has its own start (random ones: uniform).
        self.random_init = params is not None
        self.offset = checkpoint.offset_for(self.initial, random_init=self.random_init)
        self.answers = 0
        self.memory: np.ndarray | float = 0.0
        self.trace: np.ndarray = np.zeros(checkpoint.n_arms)  # broadcast to (n, K) on update

    def probabilities(self) -> np.ndarray:
        """π for every participant (a single row while all still share the start), calibrated
        by the checkpoint's temperature, as :meth:`MetaPolicyLearner.probabilities` is."""
        return np.atleast_2d(softmax(self.logits()))

    def logits(self) -> np.ndarray:
        """The logits the learner asks with: the policy's, calibrated by the checkpoint's
        temperature (:meth:`Checkpoint.calibrate`)."""
        c = self.checkpoint
        logits = hidden_and_logits(self.params, c.observation, self.offset)[1]
        return c.calibrate(logits, c.anchor_prior(random_init=self.random_init))

    def policy(self) -> np.ndarray:
        """The trained policy, untempered (its update and gates use it)."""
        return np.atleast_2d(probabilities(self.params, self.checkpoint.observation, self.offset))

    def update(self, actions: np.ndarray, rewards: np.ndarray) -> None:
        """The checkpoint's update rule with the step size and baseline of this answer."""
        c = self.checkpoint
        index = min(self.answers, c.horizon - 1)
        p_asked: np.ndarray | float = 1.0  # only surprise gates need it
        if c.gates is not None:
            p_asked = np.take_along_axis(
                np.broadcast_to(self.policy(), (len(actions), c.n_arms)),
                np.asarray(actions)[:, None],
                axis=1,
            )[:, 0]
        parts: tuple[np.ndarray | float, np.ndarray | float] = (0.0, 0.0)
        if c.traces:
            self.trace = np.broadcast_to(self.trace, (len(actions), c.n_arms))
            parts = c.trace_parts(self.trace, actions)
        step, retention = c.step_and_retention(self.answers, p_asked, rewards, self.memory, parts)
        self.memory = c.memory_after(self.memory, p_asked, rewards, retention)
        self.trace = c.trace_after(self.trace, actions, p_asked, rewards, retention)
        if self.params["b2"].ndim == 1:
            self.params = {
                k: np.broadcast_to(v, (len(actions), *v.shape)) for k, v in self.params.items()
            }
        self.params = update_params(
            self.params,
            c.observation,
            actions,
            rewards,
            step_size=step,
            baseline=float(c.baselines[index]),
            damping=c.damping,
            rule=c.rule,
            offset=self.offset,
        )
        if np.any(retention != 1.0):
            self.params = retain(self.params, self.initial, retention)
        self.answers += 1


def random_init_params(checkpoint: Checkpoint, n: int, rng: np.random.Generator) -> Params:
    """``n`` independent random initialisations, as :meth:`MetaPolicyLearner.random_init` draws."""
    draws = [
        init_params(rng, checkpoint.observation.shape[0], checkpoint.hidden, checkpoint.n_arms)
        for _ in range(n)
    ]
    return {name: np.stack([d[name] for d in draws]) for name in draws[0]}


def sample_actions(probs: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """One action per row by inverse CDF with one uniform per row (as ``sample_index`` does)."""
    cumulative = np.cumsum(probs, axis=1)
    u = rng.random((probs.shape[0], 1)) * cumulative[:, -1:]
    return np.minimum((cumulative <= u).sum(axis=1), probs.shape[1] - 1)


@dataclass(frozen=True)
class Trajectories:
    """What a simulation recorded.

    Attributes
    ----------
    preferred
        (n,) each participant's preferred question.
    p_preferred
        (n, T + 1) probability of the preferred question after 0..T answers.
    p_other_max
        (n, T + 1) largest probability of any other question after 0..T answers.
    p_asked
        (n, T) probability of the question asked at each answer (which sets the robot's reply
        level), or None.
    """

    preferred: np.ndarray
    p_preferred: np.ndarray
    p_other_max: np.ndarray
    p_asked: np.ndarray | None = None


@dataclass(frozen=True)
class Scenario:
    """How the simulated participants answer, beyond the task distribution.

    Attributes
    ----------
    feedback
        The feedback model (None: the task distribution's Gaussian rewards, the paper's).
    change_after
        After this many answers each participant's preferred question changes, to another drawn
        by the prior (None: only the feedback model's hazard changes it).
    acceptable
        How many questions each participant says yes to (drawn by the prior: models.feedback.
        acceptable_sets); their "preferred question" is then that set, and its probability the
        sum over the set.
    assumed
        The model the reference assumes, when it is not the participants' own: e.g. the model a
        deployed C2 was trained for, to compare C2 with the exact filter that knows no more than
        it does (None: the reference knows how the participants answer).
    """

    feedback: FeedbackModel | None = None
    change_after: int | None = None
    acceptable: int = 1
    assumed: FeedbackModel | None = None

    def __post_init__(self) -> None:
        if self.change_after is not None and self.change_after < 1:
            raise ValueError(f"--change-after must be at least 1, got {self.change_after}")
        if self.acceptable < 1:
            raise ValueError(f"--acceptable must be at least 1, got {self.acceptable}")
        if self.acceptable > 1 and self.feedback is None:
            raise ValueError("several acceptable questions need a feedback model (--feedback)")
        if self.assumed is not None and self.feedback is None:
            raise ValueError("a reference's assumed model needs the participants' model too")

    @property
    def reference_model(self) -> FeedbackModel | None:
        """The model the exact reference filters with."""
        return self.assumed if self.assumed is not None else self.feedback

    @property
    def needs_filter(self) -> bool:
        """Whether the plain Bayes posterior (Gaussian rewards, one preference) is not the
        exact reference here: yes/no answers, slips, changes or several acceptable questions."""
        model = self.reference_model
        return self.acceptable > 1 or (
            model is not None and (model.kind == "binary" or model.has_slips_or_changes)
        )

    def describe(self) -> str:
        """One line for the output: who the participants are and what the reference assumes."""
        if self.feedback is None:
            model = "Gaussian feedback (the task distribution's), one preference"
        else:
            model = self.feedback.describe()
        change = (
            f"; preference changes after answer {self.change_after}" if self.change_after else ""
        )
        accepts = f"; {self.acceptable} questions answered yes" if self.acceptable > 1 else ""
        return model + change + accepts


def run(
    learner: BatchLearner,
    tasks: TaskDistribution,
    preferred: np.ndarray,
    iterations: int,
    rng: np.random.Generator,
    scenario: Scenario | None = None,
) -> Trajectories:
    """Let ``learner`` ask each participant ``iterations`` questions and record its beliefs (of
    the question each participant prefers *now*, when their preference changes)."""
    scenario = scenario or Scenario()
    feedback = scenario.feedback
    members, set_prior = acceptable_sets(tasks.prior, scenario.acceptable)
    n = len(preferred)
    rows = np.arange(n)
    p_pref = np.empty((n, iterations + 1))
    p_other = np.empty((n, iterations + 1))
    p_asked = np.empty((n, iterations))
    current = np.asarray(preferred).copy()  # a question, or a set of acceptable ones
    slips = feedback.sample_slips(rng, n) if feedback is not None else None
    for t in range(iterations + 1):
        probs = np.broadcast_to(learner.probabilities(), (n, tasks.n_arms))
        accepted = members[current]
        p_pref[:, t] = np.where(accepted, probs, 0.0).sum(axis=1)
        p_other[:, t] = np.where(accepted, -1.0, probs).max(axis=1)
        if t == iterations:
            break
        actions = sample_actions(probs, rng)
        p_asked[:, t] = probs[rows, actions]
        if feedback is None or slips is None:
            rewards = tasks.rewards(rng, current, actions)
        else:
            rewards = feedback.rewards(rng, accepted[rows, actions], slips)
        learner.update(actions, rewards)
        if feedback is not None:
            current = feedback.change_preference(rng, current, set_prior)
        if scenario.change_after == t + 1:
            current = draw_other(rng, current, set_prior)
    return Trajectories(preferred, p_pref, p_other, p_asked)


def summarise(trajectories: Trajectories, target: float = TARGET) -> dict[str, Any]:
    """The issue's figures for one learner.

    ``iterations_to_95`` is the mean number of answers until the preferred question's probability
    first reaches ``target`` (T + 1 when it never does); ``reached_95`` the share that reached it;
    ``wrong_95`` the share where *another* question reached it at some point (a confidently wrong
    robot).
    """
    p = trajectories.p_preferred
    horizon = p.shape[1] - 1
    reached = p >= target
    first = np.where(reached.any(axis=1), reached.argmax(axis=1), horizon + 1)
    summary: dict[str, Any] = {
        "p_correct": [float(v) for v in p.mean(axis=0)],
        "iterations_to_95": float(first.mean()),
        "reached_95": float(reached.any(axis=1).mean()),
        "wrong_95": float((trajectories.p_other_max >= target).any(axis=1).mean()),
    }
    if trajectories.p_asked is not None:
        summary["reply_levels"] = reply_level_shares(trajectories.p_asked)
    return summary


def reply_level_shares(
    p_asked: np.ndarray, thresholds: tuple[float, ...] = DEFAULT_THRESHOLDS
) -> dict[str, float]:
    """The share of answers the robot replied to at each level of the default protocol (a
    probability equal to a threshold belongs to the higher level, as
    :func:`models.replies.confidence_level` says)."""
    levels = np.searchsorted(np.asarray(thresholds), p_asked, side="right")
    counts = np.bincount(levels.ravel(), minlength=len(LEVEL_NAMES))
    return {name: float(c / levels.size) for name, c in zip(LEVEL_NAMES, counts, strict=True)}


def summarise_change(
    trajectories: Trajectories, change_after: int, target: float = TARGET
) -> dict[str, Any]:
    """For a preference changed after answer ``change_after``: ``recovered``, the share whose
    probability of the new preferred question reached ``target`` by the last answer, and
    ``p_new_final``, its mean after the last answer."""
    after = trajectories.p_preferred[:, change_after + 1 :]
    return {
        "recovered": float((after >= target).any(axis=1).mean()),
        "p_new_final": float(trajectories.p_preferred[:, -1].mean()),
    }


def mean_p_correct(summary: dict[str, Any]) -> float:
    """Mean of ``p_correct[1..T]``: the average belief in the right question after each answer."""
    values = summary["p_correct"][1:]
    return float(sum(values) / len(values))


def simulate_learner(
    kind: str,
    tasks: TaskDistribution,
    *,
    participants: int,
    iterations: int,
    seed: int,
    checkpoint: Checkpoint | None = None,
    gamma: float | None = None,
    scenario: Scenario | None = None,
) -> Trajectories:
    """Simulate one learner ``kind`` (see :data:`LEARNERS`) on ``participants`` participants.

    Every learner sees the same preferred questions for a given seed (drawn first), so their
    figures are paired comparisons.

    Raises
    ------
    ValueError
        For an unknown kind, a meta learner without a checkpoint, Exp3 without γ, a checkpoint for
        another K, or fewer than one participant or iteration.
    """
    if participants < 1 or iterations < 1:
        raise ValueError("participants and iterations must both be at least 1")
    rng = np.random.default_rng(seed)
    acceptable = scenario.acceptable if scenario is not None else 1
    if acceptable == 1:
        preferred = tasks.sample_preferred(rng, participants)
    else:  # each participant's set of acceptable questions, by its index
        set_prior = acceptable_sets(tasks.prior, acceptable)[1]
        preferred = rng.choice(set_prior.size, size=participants, p=set_prior)
    learner: BatchLearner
    if kind == "exp3":
        if gamma is None:
            raise ValueError("exp3 needs gamma")
        learner = BatchExp3(participants, tasks.n_arms, gamma)
    elif kind == "bayes" and scenario is not None and scenario.needs_filter:
        assert scenario.reference_model is not None
        learner = BatchBelief(
            participants, tasks.n_arms, scenario.reference_model, tasks.prior, scenario.acceptable
        )
    elif kind == "bayes":
        learner = BatchBayes(participants, tasks)
    elif kind in ("meta", "random_init"):
        if checkpoint is None:
            raise ValueError(f"{kind} needs a checkpoint")
        if checkpoint.n_arms != tasks.n_arms:
            raise ValueError(
                f"checkpoint {checkpoint.path} is for {checkpoint.n_arms} questions, "
                f"the simulation has {tasks.n_arms}"
            )
        params = None
        if kind == "random_init":
            params = random_init_params(checkpoint, participants, np.random.default_rng(seed + 1))
        learner = BatchMetaPolicy(checkpoint, params)
    else:
        raise ValueError(f"unknown learner {kind!r}: use one of {', '.join(LEARNERS)}")
    return run(learner, tasks, preferred, iterations, np.random.default_rng([seed, 7]), scenario)


def _reference_name(scenario: Scenario) -> str:
    if not scenario.needs_filter:
        return "Bayes posterior"
    if scenario.assumed is not None:
        return f"forward filter assuming {scenario.assumed.describe()}"
    return "forward filter over slips and changes"


def simulate_adaptation(
    tasks: TaskDistribution,
    *,
    participants: int,
    iterations: int,
    seed: int,
    checkpoint: Checkpoint,
    gamma: float,
    learners: tuple[str, ...] = LEARNERS,
    scenario: Scenario | None = None,
) -> dict[str, Any]:
    """The ``trustlab simulate adaptation --json`` object for the given learners."""
    scenario = scenario or Scenario()
    result: dict[str, Any] = {
        "arms": tasks.n_arms,
        "iterations": iterations,
        "participants": participants,
        "participants_answer": scenario.describe(),
        "reference": _reference_name(scenario),
        "learners": {},
    }
    for kind in learners:
        trajectories = simulate_learner(
            kind,
            tasks,
            participants=participants,
            iterations=iterations,
            seed=seed,
            checkpoint=checkpoint,
            gamma=gamma,
            scenario=scenario,
        )
        summary = summarise(trajectories)
        if scenario.change_after is not None and scenario.change_after < iterations:
            summary |= summarise_change(trajectories, scenario.change_after)
        result["learners"][kind] = summary
    return result
