"""How participants answer: the feedback model that simulations, the reference and meta-training
share (issue 19).

The paper's simulated participants give Gaussian rewards around 1 for the preferred question and
0 for the others, with one preference for all answers. Real participants answer yes or no (the
protocol's reward map turns the answer into a reward), sometimes say the opposite of what they mean
(a *slip*: a misheard question, speech recognition, a moment's doubt) and sometimes change their
mind (a *hazard*: after each answer the preferred question changes with this probability, to one
of the others drawn by the prior). A model fixes:

- ``kind``: ``"binary"`` (the reward is ``yes`` or ``no``) or ``"gaussian"`` (the paper's: the
  reward is the meant answer's value plus N(0, σ²) noise);
- the slip rate, as a prior over a few values (``slips`` and their ``slip_weights``; one value
  is a known rate). A participant's slip rate is drawn once and kept;
- ``hazard``: the per-answer probability that the preference changes.

The likelihood of a reward ``r`` for a question that is (``hit``) or is not the preferred one,
with slip rate ``s``: the participant meant "yes" for a hit and "no" otherwise and said the opposite
with probability ``s``; for the Gaussian kind the meant value is blurred by N(0, σ²).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

FeedbackKind = Literal["binary", "gaussian"]
MAX_SLIP = 0.5
"""A slip rate of one half or more would make answers carry no information, or the opposite one."""


def _check_slips(slips: Sequence[float], weights: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    values = np.asarray(slips, dtype=np.float64)
    mass = np.asarray(weights, dtype=np.float64)
    if values.ndim != 1 or values.size == 0 or mass.shape != values.shape:
        raise ValueError("the slip prior needs as many weights as slip values, at least one")
    if not np.all(np.isfinite(values)) or np.any(values < 0) or np.any(values >= MAX_SLIP):
        raise ValueError(f"slip rates must lie in [0, {MAX_SLIP}), got {list(slips)}")
    if not np.all(np.isfinite(mass)) or np.any(mass < 0) or not math.isclose(mass.sum(), 1.0):
        raise ValueError(f"slip weights must be non-negative and sum to 1, got {list(weights)}")
    return values, mass


@dataclass(frozen=True)
class FeedbackModel:
    """How simulated (and, for the reference, real) participants answer.

    Attributes
    ----------
    kind
        ``"binary"`` or ``"gaussian"``.
    slips, slip_weights
        The slip rates a participant may have and their prior probabilities.
    hazard
        Probability, after each answer, that the preferred question changes.
    yes, no
        The rewards of the two answers (the protocol's reward map).
    variance
        σ² of the Gaussian kind's noise (unused for binary answers).
    """

    kind: FeedbackKind = "binary"
    slips: tuple[float, ...] = (0.0,)
    slip_weights: tuple[float, ...] = (1.0,)
    hazard: float = 0.0
    yes: float = 1.0
    no: float = 0.0
    variance: float = 0.1

    def __post_init__(self) -> None:
        if self.kind not in ("binary", "gaussian"):
            raise ValueError(f"feedback kind must be 'binary' or 'gaussian', got {self.kind!r}")
        _check_slips(self.slips, self.slip_weights)
        if not (math.isfinite(self.hazard) and 0.0 <= self.hazard < 1.0):
            raise ValueError(f"the hazard must lie in [0, 1), got {self.hazard!r}")
        if not (math.isfinite(self.yes) and math.isfinite(self.no) and self.yes != self.no):
            raise ValueError(
                f"the rewards of yes and no must be two numbers, got {self.yes}, {self.no}"
            )
        if not (math.isfinite(self.variance) and self.variance > 0):
            raise ValueError(f"the Gaussian variance must be positive, got {self.variance!r}")

    @classmethod
    def paper(cls, variance: float = 0.1) -> FeedbackModel:
        """The seed paper's simulated participants: Gaussian, no slips, one preference."""
        return cls(kind="gaussian", variance=variance)

    @classmethod
    def with_uniform_slips(
        cls, low: float, high: float, *, points: int = 16, **rest: object
    ) -> FeedbackModel:
        """A slip rate uniform on [low, high], as ``points`` equally weighted grid values."""
        if points < 1:
            raise ValueError("a slip prior needs at least one point")
        grid = tuple(float(v) for v in np.linspace(low, high, points))
        return cls(slips=grid, slip_weights=(1.0 / points,) * points, **rest)  # type: ignore[arg-type]

    def describe(self) -> str:
        """In words, for messages: ``binary answers, slips 0/0.05/0.1 equally likely, hazard
        0.02``; precise enough that two different models never read the same (a long grid reads
        ``slips 0–0.15 (16 values)``, weighted ones give each weight)."""
        values = [f"{v:g}" for v in self.slips]
        uniform = bool(np.allclose(self.slip_prior, 1.0 / len(self.slips)))
        if len(self.slips) == 1:
            slips = f"slip {values[0]}"
        elif len(self.slips) > 6:
            weighting = "" if uniform else ", weighted"
            slips = (
                f"slips {min(self.slips):g}–{max(self.slips):g} ({len(values)} values{weighting})"
            )
        elif uniform:
            slips = f"slips {'/'.join(values)} equally likely"
        else:
            slips = "slips " + "/".join(
                f"{v} (p {w:g})" for v, w in zip(values, self.slip_weights, strict=True)
            )
        kind = (
            f"gaussian answers (σ² {self.variance:g})"
            if self.kind == "gaussian"
            else "binary answers"
        )
        return f"{kind}, {slips}, hazard {self.hazard:g}"

    def same_as(self, other: FeedbackModel) -> bool:
        """Whether two models describe the same participants (σ² matters for Gaussian only)."""
        if self.kind != other.kind or len(self.slips) != len(other.slips):
            return False
        if self.kind == "gaussian" and not math.isclose(self.variance, other.variance):
            return False
        return (
            bool(np.allclose(self.slips, other.slips))
            and bool(np.allclose(self.slip_weights, other.slip_weights))
            and math.isclose(self.hazard, other.hazard)
            and (self.yes, self.no) == (other.yes, other.no)
        )

    def to_json(self) -> dict[str, object]:
        """Plain JSON, as checkpoints record the model they were trained for."""
        return {
            "kind": self.kind,
            "slips": list(self.slips),
            "slip_weights": list(self.slip_weights),
            "hazard": self.hazard,
            "yes": self.yes,
            "no": self.no,
            "variance": self.variance,
        }

    @classmethod
    def from_json(cls, value: dict[str, object]) -> FeedbackModel:
        """The model :meth:`to_json` wrote (ValueError when it is not one)."""
        try:
            return cls(
                kind=value["kind"],  # type: ignore[arg-type]
                slips=tuple(float(v) for v in value["slips"]),  # type: ignore[attr-defined]
                slip_weights=tuple(float(v) for v in value["slip_weights"]),  # type: ignore[attr-defined]
                hazard=float(value["hazard"]),  # type: ignore[arg-type]
                yes=float(value["yes"]),  # type: ignore[arg-type]
                no=float(value["no"]),  # type: ignore[arg-type]
                variance=float(value["variance"]),  # type: ignore[arg-type]
            )
        except (KeyError, TypeError) as exc:
            raise ValueError(f"not a feedback model: {exc}") from None

    @property
    def slip_values(self) -> np.ndarray:
        """The slip rates, as an array (J,)."""
        return np.asarray(self.slips, dtype=np.float64)

    @property
    def slip_prior(self) -> np.ndarray:
        """Their prior probabilities (J,)."""
        return np.asarray(self.slip_weights, dtype=np.float64)

    @property
    def mean_slip(self) -> float:
        """The expected slip rate under the prior: the share of answers a participant drawn from
        this model says the opposite of what they mean (the robot's replies predict with it)."""
        return float(self.slip_values @ self.slip_prior)

    @property
    def has_slips_or_changes(self) -> bool:
        """Whether the plain Bayes reference (no slips, one preference) would be wrong for it."""
        return bool(np.any(self.slip_values > 0)) or self.hazard > 0

    def likelihood(self, reward: np.ndarray, hit: np.ndarray, slip: np.ndarray) -> np.ndarray:
        """P(reward | the question asked is (``hit``) or is not the preferred one, slip rate),
        broadcast over the three arrays (a density for the Gaussian kind)."""
        reward, hit, slip = np.broadcast_arrays(
            np.asarray(reward, np.float64), np.asarray(hit, bool), np.asarray(slip, np.float64)
        )
        if self.kind == "binary":
            said_yes = np.abs(reward - self.yes) < np.abs(reward - self.no)
            meant_yes = hit
            return np.where(said_yes == meant_yes, 1.0 - slip, slip)
        meant = np.where(hit, self.yes, self.no)
        other = np.where(hit, self.no, self.yes)
        scale = 1.0 / math.sqrt(2 * math.pi * self.variance)
        density = scale * np.exp(-((reward - meant) ** 2) / (2 * self.variance))
        flipped = scale * np.exp(-((reward - other) ** 2) / (2 * self.variance))
        return (1.0 - slip) * density + slip * flipped

    def sample_slips(self, rng: np.random.Generator, size: int) -> np.ndarray:
        """Each participant's slip rate, drawn from the prior."""
        return self.slip_values[rng.choice(len(self.slips), size=size, p=self.slip_prior)]

    def rewards(self, rng: np.random.Generator, hit: np.ndarray, slips: np.ndarray) -> np.ndarray:
        """The rewards of participants asked a question they accept (``hit``) or not, who slip
        at rates ``slips`` (one uniform per answer for the slip, one normal for Gaussian noise)."""
        hit = np.asarray(hit, dtype=bool)
        slipped = rng.random(hit.shape) < slips
        says_yes = hit != slipped
        value = np.where(says_yes, self.yes, self.no)
        if self.kind == "gaussian":
            value = value + math.sqrt(self.variance) * rng.standard_normal(hit.shape)
        return value

    def change_preference(
        self, rng: np.random.Generator, preferred: np.ndarray, prior: np.ndarray
    ) -> np.ndarray:
        """After an answer: each participant's preference changes with probability ``hazard``,
        to one of the other questions drawn by ``prior``."""
        if self.hazard == 0:
            return preferred
        changes = rng.random(preferred.shape) < self.hazard
        return np.where(changes, draw_other(rng, preferred, prior), preferred)


def draw_other(rng: np.random.Generator, current: np.ndarray, prior: np.ndarray) -> np.ndarray:
    """For each participant, a question other than ``current``, drawn by ``prior`` (renormalised
    over the others; uniform among them where they all have prior 0)."""
    k = prior.size
    weights = np.tile(prior, (current.size, 1))
    weights[np.arange(current.size), current] = 0.0
    total = weights.sum(axis=1, keepdims=True)
    uniform = np.where(np.arange(k) == current[:, None], 0.0, 1.0 / (k - 1))
    weights = np.where(total > 0, weights / np.where(total > 0, total, 1.0), uniform)
    cumulative = weights.cumsum(axis=1)
    draws = rng.random((current.size, 1)) * cumulative[:, -1:]
    return np.minimum((draws >= cumulative).sum(axis=1), k - 1)


def switch_matrix(prior: np.ndarray, hazard: float) -> np.ndarray:
    """T[i, j] = P(preferred j at the next answer | preferred i now): stay with 1 − hazard, else
    move to another question by the prior over the others (as :func:`draw_other`)."""
    k = prior.size
    others = np.tile(prior, (k, 1))
    np.fill_diagonal(others, 0.0)
    total = others.sum(axis=1, keepdims=True)
    uniform = (1.0 - np.eye(k)) / (k - 1)
    others = np.where(total > 0, others / np.where(total > 0, total, 1.0), uniform)
    return (1.0 - hazard) * np.eye(k) + hazard * others


def acceptable_sets(prior: np.ndarray, acceptable: int) -> tuple[np.ndarray, np.ndarray]:
    """Every set of ``acceptable`` questions a participant may say yes to, as a (S, K) boolean
    matrix, with their prior probabilities (S,): proportional to the product of the questions'
    priors (for one acceptable question: the identity and the prior itself, in question order)."""
    k = prior.size
    if not 1 <= acceptable < k:
        raise ValueError(f"--acceptable must be between 1 and {k - 1} for {k} questions")
    sets = list(itertools.combinations(range(k), acceptable))
    members = np.zeros((len(sets), k), dtype=bool)
    for row, chosen in enumerate(sets):
        members[row, list(chosen)] = True
    weights = np.where(members, prior, 1.0).prod(axis=1)
    if weights.sum() <= 0:
        raise ValueError(f"no set of {acceptable} questions has a positive prior")
    return members, weights / weights.sum()
