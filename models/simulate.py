"""Objective measures: simulated participants answering the four learners (the paper's Results §A).

Each simulated participant prefers one question (drawn from the task prior) and answers with the
paper's Gaussian feedback. A learner asks ``iterations`` questions; after 0, 1, …, ``iterations``
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
from models.learners.exp3 import check_gamma
from models.learners.mlp_policy import Params, init_params, probabilities, update_params
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
        self.params: Params = dict(checkpoint.params if params is None else params)
        self.answers = 0

    def probabilities(self) -> np.ndarray:
        """π for every participant (a single row while all still share the start)."""
        return np.atleast_2d(probabilities(self.params, self.checkpoint.observation))

    def update(self, actions: np.ndarray, rewards: np.ndarray) -> None:
        """The checkpoint's update rule with the step size and baseline of this answer."""
        c = self.checkpoint
        index = min(self.answers, c.horizon - 1)
        if self.params["b2"].ndim == 1:
            self.params = {
                k: np.broadcast_to(v, (len(actions), *v.shape)) for k, v in self.params.items()
            }
        self.params = update_params(
            self.params,
            c.observation,
            actions,
            rewards,
            step_size=float(c.step_sizes[index]),
            baseline=float(c.baselines[index]),
            damping=c.damping,
            rule=c.rule,
        )
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
    """

    preferred: np.ndarray
    p_preferred: np.ndarray
    p_other_max: np.ndarray


def run(
    learner: BatchLearner,
    tasks: TaskDistribution,
    preferred: np.ndarray,
    iterations: int,
    rng: np.random.Generator,
) -> Trajectories:
    """Let ``learner`` ask each participant ``iterations`` questions and record its beliefs."""
    n = len(preferred)
    rows = np.arange(n)
    p_pref = np.empty((n, iterations + 1))
    p_other = np.empty((n, iterations + 1))
    for t in range(iterations + 1):
        probs = np.broadcast_to(learner.probabilities(), (n, tasks.n_arms))
        p_pref[:, t] = probs[rows, preferred]
        others = probs.copy()
        others[rows, preferred] = -1.0
        p_other[:, t] = others.max(axis=1)
        if t == iterations:
            break
        actions = sample_actions(probs, rng)
        learner.update(actions, tasks.rewards(rng, preferred, actions))
    return Trajectories(preferred, p_pref, p_other)


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
    return {
        "p_correct": [float(v) for v in p.mean(axis=0)],
        "iterations_to_95": float(first.mean()),
        "reached_95": float(reached.any(axis=1).mean()),
        "wrong_95": float((trajectories.p_other_max >= target).any(axis=1).mean()),
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
    preferred = tasks.sample_preferred(rng, participants)
    learner: BatchLearner
    if kind == "exp3":
        if gamma is None:
            raise ValueError("exp3 needs gamma")
        learner = BatchExp3(participants, tasks.n_arms, gamma)
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
    return run(learner, tasks, preferred, iterations, np.random.default_rng([seed, 7]))


def simulate_adaptation(
    tasks: TaskDistribution,
    *,
    participants: int,
    iterations: int,
    seed: int,
    checkpoint: Checkpoint,
    gamma: float,
    learners: tuple[str, ...] = LEARNERS,
) -> dict[str, Any]:
    """The ``trustlab simulate adaptation --json`` object for the given learners."""
    result: dict[str, Any] = {
        "arms": tasks.n_arms,
        "iterations": iterations,
        "participants": participants,
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
        )
        result["learners"][kind] = summarise(trajectories)
    return result
