"""Meta-policy checkpoints: writing, loading with integrity checks, and finding the shipped ones.

A checkpoint is a directory of four files::

    weights.json     everything a learner needs: the network, the observation, the update rule
                     and its meta-learned step sizes, baselines and damping (hashed)
    weights.sha256   "<hex digest>  weights.json", as ``sha256sum`` writes it
    config.json      the training arguments (provenance; not needed to run the learner)
    metrics.json     what training measured (validation figures, wall time)

The weights are JSON, not ``.npz``: Python writes every float64 as the shortest text that reads back
to the same bits, so a checkpoint loads exactly, and the file's bytes depend only on the numbers —
``np.savez`` stamps the current time into its zip entries, which would make every rerun's hash
differ. Only ``weights.json`` is hashed: ``metrics.json`` records wall-clock times, which no rerun
reproduces. A learner's state records the hash, so a participant's learner can never silently
continue under different weights.

Loading uses numpy only: the web app loads checkpoints on its request path and must not import
torch.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from models.feedback import FeedbackModel
from models.learners.mlp_policy import (
    PARAM_NAMES,
    UPDATE_RULES,
    Params,
    UpdateRule,
    anchor_offset,
    param_shapes,
    surprise,
)
from models.tasks import DEFAULT_VARIANCE

Mode = Literal["online", "paper"]
MODES: tuple[Mode, Mode] = ("online", "paper")

WEIGHTS_FILE = "weights.json"
HASH_FILE = "weights.sha256"
CONFIG_FILE = "config.json"
METRICS_FILE = "metrics.json"
FORMAT = "trustlab-meta-policy"
FORMAT_VERSION = 1

PRETRAINED_DIR = Path(__file__).resolve().parent / "pretrained"
"""Where the shipped checkpoints live: ``<mode>/<category>-k<K>/`` and ``<mode>/generic-k<K>/``."""

REPLICATION_DIR = PRETRAINED_DIR / "replication"
"""The online set meta-trained for the seed paper's Gaussian feedback (σ² = .1), the replication
setting: a protocol whose ``[learners.feedback]`` is the paper's model gets its C2 from here
(:func:`shipped_set`). Same layout as :data:`PRETRAINED_DIR`. These are the checkpoints the
default set was before issue 19, unchanged, so studies enrolled with them go on."""

RETIRED_DIR = PRETRAINED_DIR / "retired"
"""Checkpoints that shipped once and were replaced by better ones. They stay so that learners
enrolled with them (which record the checkpoint's SHA-256) can still be restored and verified:
see :func:`find_by_sha256`. Nothing new is ever built from them."""

GENERIC = "generic"
"""The category name of checkpoints trained for any category with K questions."""

OBSERVATION_DIM = 8
"""Length of the fixed per-category observation vector."""


def observation_for(category: str, dim: int = OBSERVATION_DIM) -> np.ndarray:
    """The fixed observation of ``category``: standard normal entries seeded by its name.

    Derived from the SHA-256 of the name, so the same category always gets the same vector on every
    machine and Python version (``hash()`` is salted per process and would not). It is non-zero and
    not constant, so with ``tanh`` units every first-layer weight receives gradient.
    """
    if not category:
        raise ValueError("observation: the category name must not be empty")
    seed = int.from_bytes(hashlib.sha256(category.encode("utf-8")).digest()[:8], "little")
    return np.random.default_rng(seed).standard_normal(dim)


TRACE_GATES: tuple[str, str, str, str] = ("step", "retention", "others_step", "others_retention")
"""The per-answer coefficients of a per-question surprise trace (:class:`SurpriseGates`)."""
TRACE_KINDS: tuple[str, str] = ("surprise", "contradiction")
"""What a per-question trace adds up (:class:`SurpriseGates`): every surprise, or contradictions
net of confirmations."""


@dataclass(frozen=True)
class SurpriseGates:
    """How an answer's surprise (:func:`models.learners.mlp_policy.surprise`) changes the step it
    gets and the forgetting after it, per answer ``t``::

        α_t(u) = α_t · exp(v_t u)        ρ_t(u) = σ(logit ρ_t + w_t u)

    An exact filter over slip rates does this implicitly: an answer that contradicts the belief
    raises its estimate of how often this participant slips, so all the evidence counts for less.
    ``yes``/``no`` are the rewards of the two answers (to measure the surprise), ``step`` is
    ``v`` and ``retention`` is ``w``.

    With a *memory* (checkpoints trained since issue 36), the step also sees ``m``, the
    surprises of the answers before this one, each forgotten since as the policy was
    (:meth:`Checkpoint.memory_after`), kept in the learner's state::

        α_t(u, m) = α_t · exp(v_t u + v'_t m)

    One surprise alone cannot tell a slip from a change of mind; the filter weighs each answer
    by its belief about this participant's slip rate, which every contradiction so far raises:
    after a slip or two, a new answer counts for less. That belief sets how much evidence an
    answer carries, not how fast a preference changes (the hazard), so the memory scales the
    step only: scaling the forgetting too lowered how sure C2 could become after any surprise,
    and with it how often it recovered from a change of mind (docs/engine.md, issue 36).
    ``memory_step`` is ``v'``; None: no memory, exactly the gates before it.

    With a *per-question trace* (``trace``, issue 36), the learner keeps one trace per question,
    ``q_k ← ρ (q_k + u [k = asked])`` (:meth:`Checkpoint.trace_after`), and the gates see the
    asked question's trace ``q_a`` — through ``u q_a``, a surprise on a question that surprised
    before — and the trace of the *other* questions, ``o = Σ_{k≠a} q_k``::

        α_t = α_t · exp(v_t u + … + x_t u q_a + y_t o)
        ρ_t = σ(logit ρ_t + w_t u + x'_t u q_a + y'_t o)

    A sum of surprises cannot tell scattered slips from repeated contradictions of one question;
    the filter can, because a run of "no"s to the question it was sure of after a consistent
    history is better explained by a change of mind than by slips. ``u q_a`` is that run,
    ``o`` the scattered surprises. ``trace`` holds ``x, x', y, y'`` under ``step``,
    ``retention``, ``others_step`` and ``others_retention``; all zero: exactly the gates
    without a trace. None: no trace.

    ``trace_kind`` ``"contradiction"`` keeps, instead of every surprise, how far each question
    has been contradicted: with the signed surprise ``d = (r − r̂)/(yes − no)`` (below 0 for an
    unexpected no), ``q_a ← ρ max(0, q_a − d)``. The yeses that first found the favourite then
    leave no trace on it (they would make its first "no" look repeated), and a yes to a question
    after a "no" to it takes the "no" back, as the filter's belief in a slip does.
    """

    yes: float
    no: float
    step: np.ndarray
    retention: np.ndarray
    memory_step: np.ndarray | None = None
    trace: dict[str, np.ndarray] | None = None
    trace_kind: str = "surprise"

    @property
    def remembers(self) -> bool:
        """Whether the gates see the surprises before the current answer."""
        return self.memory_step is not None

    @property
    def traces(self) -> bool:
        """Whether the gates see a per-question trace of the surprises before."""
        return self.trace is not None

    def of(self, p_asked: np.ndarray | float, reward: np.ndarray | float) -> np.ndarray:
        """The surprise of ``reward`` for a question the policy asked with ``p_asked``."""
        return surprise(p_asked, reward, self.yes, self.no)


@dataclass(frozen=True)
class Checkpoint:
    """A loaded, verified meta-policy checkpoint.

    Attributes
    ----------
    path
        The checkpoint directory.
    sha256
        Hex SHA-256 of ``weights.json``: the identity of these weights.
    n_arms, category, mode, rule
        K, the category it was trained for (``"generic"`` for any), ``online`` or ``paper``, and the
        update rule (one of ``models.learners.mlp_policy.UPDATE_RULES``).
    observation
        The fixed observation vector the network reads.
    params
        The network's weights (read-only arrays).
    step_sizes, baselines
        The step size and reward baseline of the 1st, 2nd, … answer's update; answers beyond the
        trained horizon reuse the last entry.
    damping
        λ of the natural-gradient step.
    prior
        The task prior the policy is anchored at (its logits are ``log prior + f_θ(x) −
        f_θ₀(x)``, :func:`models.learners.mlp_policy.anchor_offset`); None for checkpoints from
        before issue 19, whose logits are the network's own.
    retention
        ρ of the forgetting step after the 1st, 2nd, … answer
        (:func:`models.learners.mlp_policy.retain`); None: no forgetting.
    gates
        How the surprise of an answer scales its step and forgetting (:class:`SurpriseGates`);
        None: they depend on the answer's number only.
    temperature
        A calibration of the policy's output, chosen after training: a learner asks with, and
        reports, the policy with its logits' departure from the prior divided by the
        temperature (:meth:`calibrate`); its update (and every surprise gate) is the trained
        one, on the untempered policy. 1: the trained policy as it is (a checkpoint without
        the field, :func:`with_temperature`).
    config, metrics
        The training arguments and the figures training measured.
    """

    path: Path
    sha256: str
    n_arms: int
    category: str
    mode: str
    rule: UpdateRule
    observation: np.ndarray
    params: Params
    step_sizes: np.ndarray
    baselines: np.ndarray
    damping: float
    prior: np.ndarray | None = None
    retention: np.ndarray | None = None
    gates: SurpriseGates | None = None
    temperature: float = 1.0
    config: dict[str, Any] = field(default_factory=dict)
    metrics: dict[str, Any] = field(default_factory=dict)

    def offset_for(self, initial: Params, *, random_init: bool = False) -> np.ndarray | None:
        """The logit offset of a learner that starts at ``initial`` (None if not anchored).

        A random initialisation is anchored at the uniform prior, not the checkpoint's: the prior
        is part of what meta-training learned from its tasks (a population's, issue 20), and
        the Appendix's comparison asks what the update rule does without it. For a checkpoint
        trained on the uniform prior the two are the same."""
        prior = self.anchor_prior(random_init=random_init)
        return None if prior is None else anchor_offset(prior, initial, self.observation)

    def anchor_prior(self, *, random_init: bool = False) -> np.ndarray | None:
        """The prior a learner's policy is anchored at (:meth:`offset_for`; None: not
        anchored)."""
        if self.prior is None:
            return None
        return np.full(self.n_arms, 1.0 / self.n_arms) if random_init else self.prior

    def calibrate(self, logits: np.ndarray, prior: np.ndarray | None) -> np.ndarray:
        """``logits`` (…, K) calibrated by the temperature: ``log p + (logits − log p) / T``
        for a policy anchored at the prior ``p`` (:meth:`anchor_prior`), so the temperature
        scales what the learner has learned and the start stays the prior exactly, or
        ``logits / T`` for one that is not anchored. ``logits`` themselves when ``T`` is 1, to
        the last bit."""
        if self.temperature == 1.0:
            return logits
        if prior is None:
            return logits / self.temperature
        log_prior = np.log(prior)
        return log_prior + (logits - log_prior) / self.temperature

    def retention_after(self, answer_index: int) -> float:
        """ρ of the forgetting step after answer number ``answer_index`` (0-based; 1: none),
        before any surprise gate."""
        if self.retention is None:
            return 1.0
        return float(self.retention[min(answer_index, self.retention.shape[0] - 1)])

    def step_and_retention(
        self,
        answer_index: int,
        p_asked: np.ndarray | float,
        reward: np.ndarray | float,
        memory: np.ndarray | float = 0.0,
        trace: tuple[np.ndarray | float, np.ndarray | float] = (0.0, 0.0),
    ) -> tuple[np.ndarray | float, np.ndarray | float]:
        """The step size and forgetting ρ for answer ``answer_index`` (0-based) with this reward
        to a question asked with probability ``p_asked``, with the surprise ``memory`` of the
        answers before and ``trace``, the asked question's trace and the others' sum
        (:meth:`trace_parts`) (arrays: one per batch row; only gates that remember or trace read
        them)."""
        index = min(answer_index, self.horizon - 1)
        step: np.ndarray | float = float(self.step_sizes[index])
        rho: np.ndarray | float = self.retention_after(answer_index)
        gates = self.gates
        if gates is None:
            return step, rho
        u = gates.of(p_asked, reward)
        step_exponent = gates.step[index] * u
        retention_shift = gates.retention[index] * u
        if gates.memory_step is not None:
            step_exponent = step_exponent + gates.memory_step[index] * memory
        if gates.trace is not None:
            repeated, others = u * trace[0], trace[1]
            step_exponent = (
                step_exponent
                + gates.trace["step"][index] * repeated
                + gates.trace["others_step"][index] * others
            )
            retention_shift = (
                retention_shift
                + gates.trace["retention"][index] * repeated
                + gates.trace["others_retention"][index] * others
            )
        step = step * np.exp(step_exponent)
        with np.errstate(divide="ignore"):
            logit = np.log(rho) - np.log1p(-rho)
        rho = 1.0 / (1.0 + np.exp(-(logit + retention_shift)))
        return step, rho

    def memory_after(
        self,
        memory: np.ndarray | float,
        p_asked: np.ndarray | float,
        reward: np.ndarray | float,
        retention: np.ndarray | float,
    ) -> np.ndarray | float:
        """The surprise memory after this answer, ``ρ (m + u)``, for gates that remember (else
        ``memory`` unchanged: 0, such learners keep none). It is forgotten as the policy is, by
        the answer's own ρ: a surprise the learner answered by forgetting (a change of mind)
        leaves little trace, one it answered by holding on (a slip) stays."""
        if self.gates is None or not self.gates.remembers:
            return memory
        return retention * (memory + self.gates.of(p_asked, reward))

    @staticmethod
    def trace_parts(trace: np.ndarray, action: np.ndarray | int) -> tuple[np.ndarray, np.ndarray]:
        """The asked question's trace ``q_a`` and the sum of the others' ``Σ_{k≠a} q_k``, from
        a trace (…, K) and the asked question (one per batch row)."""
        values = np.asarray(trace, dtype=np.float64)
        asked = np.take_along_axis(values, np.asarray(action)[..., None], axis=-1)[..., 0]
        return asked, values.sum(axis=-1) - asked

    def trace_after(
        self,
        trace: np.ndarray,
        action: np.ndarray | int,
        p_asked: np.ndarray | float,
        reward: np.ndarray | float,
        retention: np.ndarray | float,
    ) -> np.ndarray:
        """The per-question surprise trace after this answer, ``ρ (q + u e_a)`` (or, for a
        contradiction trace, ``ρ max(0, q_a − d)`` on the asked question), for gates that trace
        (else ``trace`` unchanged). Forgotten by the answer's own ρ, as the memory is."""
        gates = self.gates
        if gates is None or not gates.traces:
            return trace
        values = np.asarray(trace, dtype=np.float64)
        onehot = np.asarray(action)[..., None] == np.arange(self.n_arms)
        rho = np.asarray(retention, dtype=np.float64)
        rho = rho[..., None] if rho.ndim else rho
        if gates.trace_kind == "contradiction":
            expected = gates.no + np.asarray(p_asked, dtype=np.float64) * (gates.yes - gates.no)
            signed = (np.asarray(reward, dtype=np.float64) - expected) / (gates.yes - gates.no)
            return rho * np.where(onehot, np.maximum(values - signed[..., None], 0.0), values)
        u = np.asarray(gates.of(p_asked, reward), dtype=np.float64)[..., None]
        return rho * (values + u * onehot)

    @property
    def remembers(self) -> bool:
        """Whether learners on this checkpoint keep a surprise memory in their state."""
        return self.gates is not None and self.gates.remembers

    @property
    def traces(self) -> bool:
        """Whether learners on this checkpoint keep a per-question surprise trace in their
        state."""
        return self.gates is not None and self.gates.traces

    @property
    def hidden(self) -> int:
        """Number of hidden units."""
        return int(self.params["b1"].shape[0])

    @property
    def horizon(self) -> int:
        """How many answers the step sizes were meta-learned for."""
        return int(self.step_sizes.shape[0])


def _digest(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _dump(obj: Any) -> bytes:
    return (json.dumps(obj, sort_keys=True, separators=(",", ":"), allow_nan=False) + "\n").encode()


def write_checkpoint(
    directory: Path,
    *,
    n_arms: int,
    category: str,
    mode: str,
    rule: UpdateRule,
    observation: np.ndarray,
    params: Params,
    step_sizes: np.ndarray,
    baselines: np.ndarray,
    damping: float,
    config: dict[str, Any],
    metrics: dict[str, Any],
    prior: np.ndarray | None = None,
    retention: np.ndarray | None = None,
    gates: SurpriseGates | None = None,
    temperature: float | None = None,
) -> Checkpoint:
    """Write a checkpoint directory (created if needed) and return it loaded back and verified.

    ``prior``, ``retention``, ``gates`` and ``temperature`` are written only when given, so a
    checkpoint without them has the same bytes (and hash) as before they existed."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    weights: dict[str, Any] = {
        "format": FORMAT,
        "version": FORMAT_VERSION,
        "n_arms": int(n_arms),
        "category": category,
        "mode": mode,
        "rule": rule,
        "observation": np.asarray(observation, dtype=np.float64).tolist(),
        "step_sizes": np.asarray(step_sizes, dtype=np.float64).tolist(),
        "baselines": np.asarray(baselines, dtype=np.float64).tolist(),
        "damping": float(damping),
    }
    for name in PARAM_NAMES:
        weights[name] = np.asarray(params[name], dtype=np.float64).tolist()
    if prior is not None:
        weights["prior"] = np.asarray(prior, dtype=np.float64).tolist()
    if retention is not None:
        weights["retention"] = np.asarray(retention, dtype=np.float64).tolist()
    if gates is not None:
        weights["surprise"] = {
            "yes": float(gates.yes),
            "no": float(gates.no),
            "step": np.asarray(gates.step, dtype=np.float64).tolist(),
            "retention": np.asarray(gates.retention, dtype=np.float64).tolist(),
        }
        if gates.memory_step is not None:
            weights["surprise"]["memory_step"] = np.asarray(gates.memory_step).tolist()
        if gates.trace is not None:
            weights["surprise"]["trace"] = {
                name: np.asarray(gates.trace[name], dtype=np.float64).tolist()
                for name in TRACE_GATES
            }
            if gates.trace_kind != "surprise":  # absent: the first kind, so its hashes stay
                weights["surprise"]["trace_kind"] = gates.trace_kind
    if temperature is not None:
        weights["temperature"] = _check_temperature(temperature, directory / WEIGHTS_FILE)
    data = _dump(weights)
    (directory / WEIGHTS_FILE).write_bytes(data)
    (directory / HASH_FILE).write_text(f"{_digest(data)}  {WEIGHTS_FILE}\n")
    (directory / CONFIG_FILE).write_text(json.dumps(config, indent=2, sort_keys=True) + "\n")
    (directory / METRICS_FILE).write_text(json.dumps(metrics, indent=2, sort_keys=True) + "\n")
    return load_checkpoint(directory, expected_arms=n_arms)


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ValueError(f"checkpoint file {path} is missing") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"checkpoint file {path} is not valid JSON: {exc}") from None


def _array(weights: dict[str, Any], key: str, shape: tuple[int, ...], where: Path) -> np.ndarray:
    try:
        value = np.asarray(weights[key], dtype=np.float64)
    except KeyError:
        raise ValueError(f"checkpoint {where} has no {key!r}") from None
    except (TypeError, ValueError):
        raise ValueError(f"checkpoint {where}: {key!r} is not an array of numbers") from None
    if value.shape != shape:
        raise ValueError(f"checkpoint {where}: {key!r} has shape {value.shape}, expected {shape}")
    if not np.all(np.isfinite(value)):
        raise ValueError(f"checkpoint {where}: {key!r} contains NaN or infinite numbers")
    value.setflags(write=False)
    return value


def _int(weights: dict[str, Any], key: str, where: Path) -> int:
    value = weights.get(key)
    if isinstance(value, bool) or not isinstance(value, int):
        raise ValueError(f"checkpoint {where}: {key!r} must be an integer, got {value!r}")
    return value


def load_checkpoint(path: Path | str, expected_arms: int | None = None) -> Checkpoint:
    """Load and verify the checkpoint in directory ``path`` (or its ``weights.json``).

    Raises
    ------
    ValueError
        Naming the offending file, if a file is missing or unreadable, the hash does not match,
        an array has the wrong shape or a non-finite number, or the checkpoint is for another K than
        ``expected_arms``.
    """
    path = Path(path)
    directory = path.parent if path.name == WEIGHTS_FILE else path
    if not directory.is_dir():
        raise ValueError(f"checkpoint {directory} does not exist or is not a directory")
    weights_path = directory / WEIGHTS_FILE
    hash_path = directory / HASH_FILE
    try:
        data = weights_path.read_bytes()
    except OSError:
        raise ValueError(f"checkpoint file {weights_path} is missing or unreadable") from None
    try:
        recorded = hash_path.read_text(encoding="utf-8").split()
    except (OSError, UnicodeDecodeError):
        raise ValueError(f"checkpoint hash file {hash_path} is missing or unreadable") from None
    if not recorded or len(recorded[0]) != 64:
        raise ValueError(f"checkpoint hash file {hash_path} does not hold a SHA-256 digest")
    digest = _digest(data)
    if digest != recorded[0].lower():
        raise ValueError(
            f"checkpoint file {weights_path} does not match its hash in {hash_path} "
            f"(sha256 {digest[:12]}…, recorded {recorded[0][:12]}…): corrupted or edited"
        )
    try:
        weights = json.loads(data)
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"checkpoint file {weights_path} is not valid JSON: {exc}") from None
    if not isinstance(weights, dict) or weights.get("format") != FORMAT:
        raise ValueError(f"checkpoint file {weights_path} is not a {FORMAT} file")
    if weights.get("version") != FORMAT_VERSION:
        raise ValueError(
            f"checkpoint file {weights_path} has format version {weights.get('version')!r}, "
            f"this code reads version {FORMAT_VERSION}"
        )
    n_arms = _int(weights, "n_arms", weights_path)
    if n_arms < 2:
        raise ValueError(f"checkpoint {weights_path}: n_arms must be at least 2, got {n_arms}")
    if expected_arms is not None and n_arms != expected_arms:
        raise ValueError(
            f"checkpoint {weights_path} is for {n_arms} questions, but this category has "
            f"{expected_arms}"
        )
    rule = weights.get("rule")
    if rule not in UPDATE_RULES:
        raise ValueError(f"checkpoint {weights_path}: unknown update rule {rule!r}")
    mode = weights.get("mode")
    if mode not in MODES:
        raise ValueError(f"checkpoint {weights_path}: unknown mode {mode!r}")
    category = weights.get("category")
    if not isinstance(category, str) or not category:
        raise ValueError(f"checkpoint {weights_path}: missing category name")
    try:
        obs_dim = len(weights["observation"])
        hidden = len(weights["b1"])
        horizon = len(weights["step_sizes"])
    except (KeyError, TypeError):
        raise ValueError(f"checkpoint {weights_path} lacks observation, b1 or step_sizes") from None
    if horizon < 1:
        raise ValueError(f"checkpoint {weights_path}: step_sizes is empty")
    observation = _array(weights, "observation", (obs_dim,), weights_path)
    params = {
        name: _array(weights, name, shape, weights_path)
        for name, shape in param_shapes(obs_dim, hidden, n_arms).items()
    }
    step_sizes = _array(weights, "step_sizes", (horizon,), weights_path)
    baselines = _array(weights, "baselines", (horizon,), weights_path)
    if np.any(step_sizes <= 0):
        raise ValueError(f"checkpoint {weights_path}: step sizes must be positive")
    damping = weights.get("damping")
    if (
        isinstance(damping, bool)
        or not isinstance(damping, int | float)
        or not math.isfinite(damping)
        or damping <= 0
    ):
        raise ValueError(f"checkpoint {weights_path}: damping must be a positive number")
    prior = _array(weights, "prior", (n_arms,), weights_path) if "prior" in weights else None
    if prior is not None and (np.any(prior <= 0) or not math.isclose(prior.sum(), 1.0)):
        raise ValueError(f"checkpoint {weights_path}: 'prior' must be positive and sum to 1")
    retention = None
    if "retention" in weights:
        retention = _array(weights, "retention", (horizon,), weights_path)
        if np.any(retention <= 0) or np.any(retention > 1):
            raise ValueError(f"checkpoint {weights_path}: 'retention' must lie in (0, 1]")
    gates = _gates(weights.get("surprise"), horizon, weights_path, retention is not None)
    temperature = (
        _check_temperature(weights["temperature"], weights_path)
        if "temperature" in weights
        else 1.0
    )
    config = _read_json(directory / CONFIG_FILE)
    metrics = _read_json(directory / METRICS_FILE)
    if not isinstance(config, dict) or not isinstance(metrics, dict):
        raise ValueError(f"checkpoint {directory}: config.json and metrics.json must hold objects")
    return Checkpoint(
        path=directory,
        sha256=digest,
        n_arms=n_arms,
        category=category,
        mode=mode,
        rule=rule,
        observation=observation,
        params=params,
        step_sizes=step_sizes,
        baselines=baselines,
        damping=float(damping),
        prior=prior,
        retention=retention,
        gates=gates,
        temperature=temperature,
        config=config,
        metrics=metrics,
    )


TEMPERATURE_RANGE = (0.5, 2.0)
"""The temperatures a checkpoint may hold: a calibration of a trained policy moves it a few
per cent (the shipped cognition checkpoint's 1.02); outside this range it would be a different
policy, not a calibrated one."""


def _check_temperature(value: Any, where: Path) -> float:
    """``value`` as a checkpoint's temperature, or a ValueError naming ``where``."""
    low, high = TEMPERATURE_RANGE
    if (
        isinstance(value, bool)
        or not isinstance(value, int | float)
        or not math.isfinite(value)
        or not low <= value <= high
    ):
        raise ValueError(
            f"checkpoint {where}: 'temperature' must be a number from {low:g} to {high:g}, "
            f"got {value!r}"
        )
    return float(value)


def _gates(value: Any, horizon: int, where: Path, forgets: bool) -> SurpriseGates | None:
    if value is None:
        return None
    if not isinstance(value, dict) or not forgets:
        raise ValueError(f"checkpoint {where}: 'surprise' must be an object, with 'retention' set")
    yes, no = value.get("yes"), value.get("no")
    if not all(isinstance(v, int | float) and math.isfinite(v) for v in (yes, no)) or yes == no:
        raise ValueError(f"checkpoint {where}: 'surprise' needs two different rewards yes and no")
    return SurpriseGates(
        yes=float(yes),  # type: ignore[arg-type]
        no=float(no),  # type: ignore[arg-type]
        step=_array(value, "step", (horizon,), where),
        retention=_array(value, "retention", (horizon,), where),
        memory_step=(
            _array(value, "memory_step", (horizon,), where) if "memory_step" in value else None
        ),
        trace=_trace(value.get("trace"), horizon, where),
        trace_kind=_trace_kind(value, where),
    )


def _trace_kind(value: dict[str, Any], where: Path) -> str:
    kind = value.get("trace_kind", "surprise")
    if kind not in TRACE_KINDS or ("trace" not in value and "trace_kind" in value):
        raise ValueError(
            f"checkpoint {where}: 'surprise.trace_kind' must be one of {', '.join(TRACE_KINDS)}, "
            "with a 'trace'"
        )
    return str(kind)


def _trace(value: Any, horizon: int, where: Path) -> dict[str, np.ndarray] | None:
    if value is None:
        return None
    if not isinstance(value, dict) or set(value) != set(TRACE_GATES):
        raise ValueError(
            f"checkpoint {where}: 'surprise.trace' must be an object with {', '.join(TRACE_GATES)}"
        )
    return {name: _array(value, name, (horizon,), where) for name in TRACE_GATES}


def with_temperature(
    checkpoint: Checkpoint, temperature: float, directory: Path, *, note: dict[str, Any]
) -> Checkpoint:
    """Write a copy of ``checkpoint`` to ``directory`` with ``temperature`` (hashed with the
    weights, so the copy is a checkpoint of its own) and return it loaded back and verified.

    Its config is the original's (the training that made the weights); its metrics are the
    original's plus ``temperature``: ``note`` (how the temperature was chosen) and the original's
    hash, so the copy names what it calibrates.
    """
    if checkpoint.temperature != 1.0:
        raise ValueError(f"checkpoint {checkpoint.path} is calibrated already")
    metrics = {
        **checkpoint.metrics,
        "temperature": {**note, "value": float(temperature), "calibrates": checkpoint.sha256},
    }
    return rewrite_checkpoint(checkpoint, directory, metrics=metrics, temperature=temperature)


def rewrite_checkpoint(checkpoint: Checkpoint, directory: Path, **changes: Any) -> Checkpoint:
    """Write ``checkpoint`` again to ``directory`` with ``changes`` to what
    :func:`write_checkpoint` is given (say ``metrics`` or ``temperature``), and return it loaded
    back and verified. Unchanged, the copy has the original's weights bytes and hash."""
    fields: dict[str, Any] = {
        "n_arms": checkpoint.n_arms,
        "category": checkpoint.category,
        "mode": checkpoint.mode,
        "rule": checkpoint.rule,
        "observation": checkpoint.observation,
        "params": checkpoint.params,
        "step_sizes": checkpoint.step_sizes,
        "baselines": checkpoint.baselines,
        "damping": checkpoint.damping,
        "config": checkpoint.config,
        "metrics": checkpoint.metrics,
        "prior": checkpoint.prior,
        "retention": checkpoint.retention,
        "gates": checkpoint.gates,
        "temperature": None if checkpoint.temperature == 1.0 else checkpoint.temperature,
    }
    return write_checkpoint(directory, **{**fields, **changes})


def find_by_sha256(sha256: str, roots: Sequence[Path]) -> Path | None:
    """The checkpoint directory under any of ``roots`` whose hash file records ``sha256``.

    Only the hash file is read here; :func:`load_checkpoint` then verifies the weights themselves,
    so a directory whose weights were edited is still refused.
    """
    wanted = sha256.lower()
    for root in roots:
        for hash_file in sorted(Path(root).rglob(HASH_FILE)):
            try:
                recorded = hash_file.read_text(encoding="utf-8").split()
            except (OSError, UnicodeDecodeError):
                continue
            if recorded and recorded[0].lower() == wanted:
                return hash_file.parent
    return None


def checkpoint_name(category: str, arms: int) -> str:
    """The directory name of a checkpoint: ``<category>-k<K>``."""
    return f"{category}-k{arms}"


def available_arms(mode: str = "online", directory: Path | None = None) -> list[int]:
    """The K for which a generic checkpoint of ``mode`` ships (sorted)."""
    root = (PRETRAINED_DIR if directory is None else Path(directory)) / mode
    found = []
    for candidate in root.glob(f"{GENERIC}-k*"):
        suffix = candidate.name.removeprefix(f"{GENERIC}-k")
        if suffix.isdigit() and (candidate / WEIGHTS_FILE).is_file():
            found.append(int(suffix))
    return sorted(found)


def shipped_checkpoint(
    arms: int,
    category: str | None = None,
    mode: str = "online",
    directory: Path | None = None,
) -> Path:
    """The checkpoint directory to use for ``category`` with ``arms`` questions.

    The category's own checkpoint when one ships for that K (its questions' meta-training), else
    the generic checkpoint for K. ``directory`` replaces the shipped ``models/pretrained`` (a lab's
    own retrained set, same layout).

    Raises
    ------
    ValueError
        If ``mode`` is unknown or no checkpoint exists for this K (the message lists those that do).
    """
    if mode not in MODES:
        raise ValueError(f"unknown checkpoint mode {mode!r}: use 'online' or 'paper'")
    root = (PRETRAINED_DIR if directory is None else Path(directory)) / mode
    names = [checkpoint_name(category, arms)] if category else []
    names.append(checkpoint_name(GENERIC, arms))
    for name in names:
        if (root / name / WEIGHTS_FILE).is_file():
            return root / name
    known = available_arms(mode, directory)
    listing = ", ".join(str(k) for k in known) if known else "none"
    raise ValueError(
        f"no {mode} meta-policy checkpoint for {arms} questions"
        + (f" (category {category!r})" if category else "")
        + f" in {root}; generic checkpoints exist for K = {listing}. "
        "Train one with `trustlab pretrain` and set the protocol's checkpoint path."
    )


def shipped_set(feedback: FeedbackModel) -> Path:
    """The shipped set trained for ``feedback``: :data:`REPLICATION_DIR` for the paper's
    Gaussian model, the default set (yes/no answers with slips and a hazard) otherwise. A
    protocol's model that neither was trained for is refused where the learner is built, with
    the difference in words (app/services/sessions/learners.py)."""
    return REPLICATION_DIR if feedback.kind == "gaussian" else PRETRAINED_DIR


def trained_feedback(checkpoint: Checkpoint) -> FeedbackModel:
    """The feedback model a checkpoint was meta-trained for: recorded in its config as
    ``feedback``; checkpoints from before issue 19 were trained on the paper's Gaussian model
    with their config's ``variance``."""
    recorded = checkpoint.config.get("feedback")
    if isinstance(recorded, dict):
        try:
            return FeedbackModel.from_json(recorded)
        except ValueError as exc:
            raise ValueError(f"checkpoint {checkpoint.path}: config.json feedback: {exc}") from None
    variance = checkpoint.config.get("variance", DEFAULT_VARIANCE)
    return FeedbackModel.paper(float(variance))
