"""Between the study protocol and the adaptation engine: building, storing and restoring learners.

Each participant gets one learner per category at enrolment: Exp3 for an ``exp3`` condition, the
pre-trained meta-policy for a ``meta`` condition (the checkpoint's SHA-256 is recorded), the exact
filter for the protocol's feedback model for a ``bayes`` condition (:func:`bayes_config`). The row
keeps the initial state, the current state and a version that increments with every update, so
``trustlab verify`` can replay the step log from the initial state and compare bit for bit.

Restoring a learner from JSON on every answer is the hot path: app.services.sessions.learner_cache
keeps live learners between answers, one cache per database.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from app.errors import Conflict
from app.protocol import CategorySpec, LearnerKind, Protocol, feedback_model
from app.services.sessions import populations
from app.tables import LearnerState
from models.checkpoints import (
    PRETRAINED_DIR,
    RETIRED_DIR,
    WEIGHTS_FILE,
    Checkpoint,
    find_by_sha256,
    load_checkpoint,
    shipped_checkpoint,
    shipped_set,
    trained_feedback,
)
from models.feedback import FeedbackModel
from models.learners import meta_policy
from models.learners.base import Learner
from models.learners.exact import exact_learner
from models.learners.exp3 import Exp3
from models.learners.meta_policy import MetaPolicyLearner


@dataclass(frozen=True)
class LearnerSpec:
    """Everything needed to rebuild a learner's structure; its state comes on top."""

    kind: str
    n_arms: int
    config: dict[str, Any]
    checkpoint_sha256: str | None


@functools.lru_cache(maxsize=64)
def _verified_checkpoint(path: str, modified_ns: int, size: int, n_arms: int) -> Checkpoint:
    """A checkpoint loaded and hash-checked once per process (and again if its file changes)."""
    return load_checkpoint(Path(path), expected_arms=n_arms)


def checkpoint_at(path: Path, n_arms: int) -> Checkpoint:
    """The verified checkpoint at ``path``: rebuilding a learner must not re-hash its weights."""
    weights = Path(path) / WEIGHTS_FILE
    try:
        stat = weights.stat()
    except OSError:
        return load_checkpoint(path, expected_arms=n_arms)  # raises the loader's clear error
    return _verified_checkpoint(str(path), stat.st_mtime_ns, stat.st_size, n_arms)


def _checkpoint_path(
    protocol: Protocol, category: CategorySpec, checkpoint_dir: Path | None
) -> Path:
    if protocol.learners.population is not None:
        return populations.checkpoint_path(protocol, category)
    setting = protocol.learners.meta.checkpoint
    if setting != "shipped":
        return Path(setting)
    if checkpoint_dir is None:
        checkpoint_dir = shipped_set(feedback_model(protocol))
    return shipped_checkpoint(
        len(category.questions), category=category.name, directory=checkpoint_dir
    )


def accepted_mismatch(protocol: Protocol, checkpoint: Checkpoint) -> FeedbackModel | None:
    """None when the checkpoint was meta-trained for the protocol's feedback model; the model
    it was trained for when the protocol accepts the mismatch (the learner's config records
    it); otherwise the mismatch is refused."""
    declared, trained = feedback_model(protocol), trained_feedback(checkpoint)
    if declared.same_as(trained):
        return None
    if protocol.learners.feedback.accept_other_checkpoint:
        return trained
    raise Conflict(
        f"checkpoint {checkpoint.path} was meta-trained for {trained.describe()}, but the "
        f"protocol's learners.feedback declares {declared.describe()}: retrain C2 for it "
        "(trustlab pretrain) or set learners.feedback.accept_other_checkpoint = true"
    )


def learner_spec(
    protocol: Protocol, condition_id: str, category: CategorySpec, checkpoint_dir: Path | None
) -> LearnerSpec:
    """What learner a participant of ``condition_id`` gets for ``category``."""
    kind = protocol.condition(condition_id).learner
    n_arms = len(category.questions)
    if kind is LearnerKind.EXP3:
        return LearnerSpec("exp3", n_arms, {"gamma": protocol.learners.exp3.gamma}, None)
    if kind is LearnerKind.BAYES:
        return LearnerSpec("bayes", n_arms, bayes_config(protocol, category), None)
    path = _checkpoint_path(protocol, category, checkpoint_dir)
    checkpoint = checkpoint_at(path, n_arms)
    config: dict[str, Any] = {"checkpoint": str(path)}
    population = populations.population_of(protocol)
    if population is not None:
        populations.check_trained_for(checkpoint, population, category)
        config["population_sha256"] = population.sha256
    mismatch = accepted_mismatch(protocol, checkpoint)
    if mismatch is not None:
        config["trained_for_other_feedback"] = mismatch.to_json()
    if protocol.learners.meta.learning_rate is not None:
        config["learning_rate"] = protocol.learners.meta.learning_rate
    return LearnerSpec("meta", n_arms, config, checkpoint.sha256)


def bayes_config(protocol: Protocol, category: CategorySpec) -> dict[str, Any]:
    """What a ``bayes`` learner is built from, recorded whole so that replay never depends on
    the protocol or a file: the feedback model (with the reward map) and, when the protocol
    names a population, the prior over the preferred question C2 was meta-trained on (the
    population's training prior, :meth:`analysis.population.Population.training_prior`: the
    predictive prior for a new participant given the earlier ones) with the population's hash.
    Without one the prior is uniform, as C2's shipped checkpoints were trained on."""
    config: dict[str, Any] = {"feedback": feedback_model(protocol).to_json()}
    population = populations.population_of(protocol)
    if population is not None:
        questions = list(category.questions)
        prior = population.training_prior(category.name, len(questions), questions)
        config |= {"prior": list(prior), "population_sha256": population.sha256}
    return config


@dataclass(frozen=True)
class PriorInUse:
    """What C2 starts from in one category, for the engine panel (issue 20)."""

    category: CategorySpec
    start: list[float] | None
    """The meta-policy's first probabilities, one per question (None: see ``problem``)."""
    population: dict[str, Any] | None
    """The population its checkpoint records (None: meta-trained on the uniform prior)."""
    problem: str = ""


def priors_in_use(protocol: Protocol, checkpoint_dir: Path | None = None) -> list[PriorInUse]:
    """Per category, where C2's new learners start and which population that came from; empty
    when no condition uses the meta-policy. A checkpoint that cannot be loaded is reported in
    its row, not raised: the panel explains, enrolment refuses."""
    if all(c.learner is not LearnerKind.META for c in protocol.conditions):
        return []
    rows = []
    for category in protocol.categories:
        try:
            path = _checkpoint_path(protocol, category, checkpoint_dir)
            checkpoint = checkpoint_at(path, len(category.questions))
        except ValueError as exc:
            rows.append(PriorInUse(category, None, None, str(exc)))
            continue
        start = probabilities_list(MetaPolicyLearner(checkpoint))
        recorded = checkpoint.config.get("population")
        rows.append(PriorInUse(category, start, recorded if isinstance(recorded, dict) else None))
    return rows


def recorded_checkpoint(spec: LearnerSpec) -> Checkpoint:
    """The exact checkpoint a meta learner was created with.

    Normally the one at the recorded path. If that file has since been replaced (a newer
    trustlab ships better checkpoints; their predecessors move to ``models/pretrained/retired``)
    or the installation moved, the checkpoint is found by its recorded SHA-256 among the shipped
    ones, beside the recorded path and in its set's ``retired`` directory (a lab's own set,
    retired as docs/engine.md says), so a study enrolled before an upgrade carries on with the
    learners it started with.

    Raises
    ------
    ValueError
        If no checkpoint with the recorded hash can be found (the message says which file changed).
    """
    path = Path(spec.config["checkpoint"])
    try:
        checkpoint: Checkpoint | None = checkpoint_at(path, spec.n_arms)
        problem = ""
    except ValueError as error:
        checkpoint, problem = None, str(error)
    wanted = spec.checkpoint_sha256
    if checkpoint is not None and (not wanted or checkpoint.sha256 == wanted):
        return checkpoint
    if wanted:
        found = _checkpoint_with_hash(wanted, _search_roots(path))
        if found is not None:
            return checkpoint_at(found, spec.n_arms)
    if checkpoint is None:
        raise ValueError(problem)
    raise ValueError(
        f"checkpoint {checkpoint.path} has changed since the learner was created "
        f"(sha256 {checkpoint.sha256[:12]}…, recorded {str(wanted)[:12]}…) and no checkpoint "
        f"with the recorded hash is in {', '.join(map(str, _search_roots(path)))}: restore the "
        "original"
    )


def _search_roots(path: Path) -> tuple[Path, ...]:
    """Where a replaced checkpoint may be: the shipped ones, the recorded checkpoint's own
    directory (``<set>/online``) and its set's retired ones (``<set>/retired``). Bounded on
    purpose: never a recursive search of whatever lies above a checkpoint."""
    return (PRETRAINED_DIR, path.parent, path.parent.parent / RETIRED_DIR.name)


_FOUND_BY_HASH: dict[tuple[str, tuple[Path, ...]], Path] = {}


def _checkpoint_with_hash(sha256: str, roots: tuple[Path, ...]) -> Path | None:
    """Search once per process for a hit (checkpoints are read-only data); a miss is searched
    again next time, so restoring the file fixes a running server."""
    key = (sha256, roots)
    if key not in _FOUND_BY_HASH:
        found = find_by_sha256(sha256, [root for root in roots if root.is_dir()])
        if found is None:
            return None
        _FOUND_BY_HASH[key] = found
    return _FOUND_BY_HASH[key]


def build(spec: LearnerSpec) -> Learner:
    """A fresh learner of this spec (the meta-policy's checkpoint is checked against its hash)."""
    if spec.kind == "exp3":
        return Exp3(spec.n_arms, gamma=float(spec.config["gamma"]))
    if spec.kind == "meta":
        return MetaPolicyLearner.from_checkpoint(
            recorded_checkpoint(spec), learning_rate=spec.config.get("learning_rate")
        )
    if spec.kind == "bayes":
        feedback = FeedbackModel.from_json(spec.config["feedback"])
        return exact_learner(spec.n_arms, feedback, spec.config.get("prior"))
    raise ValueError(f"unknown learner kind {spec.kind!r}")


def spec_of(row: LearnerState) -> LearnerSpec:
    """The spec a stored learner was built from."""
    return LearnerSpec(row.kind, row.n_arms, dict(row.config), row.checkpoint_sha256)


def restore(row: LearnerState, *, initial: bool = False) -> Learner:
    """The stored learner (or its initial state) as a live object."""
    learner = build(spec_of(row))
    learner.load_state_dict(row.initial_state if initial else row.state)
    return learner


def plain_state(state: dict[str, Any]) -> dict[str, Any]:
    """A stored state in the one form :func:`app.services.sessions.verify` compares, whatever format
    version wrote it (only the meta-policy has had two; other states come back unchanged)."""
    return meta_policy.plain_state(state) if state.get("kind") == "meta" else state


def probabilities_list(learner: Learner) -> list[float]:
    """Probabilities as plain floats for JSON (float64 → float is exact)."""
    return [float(p) for p in np.asarray(learner.probabilities(), dtype=np.float64)]
