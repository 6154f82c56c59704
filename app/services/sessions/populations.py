"""A protocol's population (issue 20): C2 meta-trained for earlier participants' prior.

A protocol's ``[learners.population]`` names a population file (``trustlab population fit``) and
the checkpoints ``trustlab pretrain --population`` trained for it. Everything that can be wrong
with that pairing is refused when the study is created, in one line naming the key path: a file
edited after its hash was recorded, a category whose questions differ from the ones the
population was fitted on, a checkpoint trained for another population (or none), and a source
study still enrolling participants. The last one matters for between-subjects designs: a prior
fitted on participants of a study while it runs, used for the conditions of a study that runs
beside it (or the same one), lets one condition's participants shape the other's learner. A lab
that has a reason (a pilot study left open by mistake, say) records it as ``enrolling_reason``.
Study creation (:func:`app.services.studies.check_population_use`) puts these checks together
with the learners' checkpoint loading, which builds on this module (never the other way round).
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import TYPE_CHECKING, Any

from sqlalchemy import select
from sqlalchemy.orm import Session

from app.errors import Conflict, InvalidInput
from app.protocol import CategorySpec, Protocol
from app.tables import Study, StudyStatus

if TYPE_CHECKING:  # the analysis (pandas) and the models (numpy): only where they are used
    from analysis.population import Population
    from models.checkpoints import Checkpoint

KEY = "learners.population"


@functools.lru_cache(maxsize=16)
def _verified(path: str, modified_ns: int, size: int) -> Population:
    """Read and hash-check a population file once per process (again if the file changes)."""
    # Here, not at the top: the analysis stack (pandas, Plotly) is for studies with a population
    # file, and every command that merely opens a study imports this module.
    from analysis.population import read_population

    return read_population(Path(path))


def population_of(protocol: Protocol) -> Population | None:
    """The protocol's verified population, or None when it names none.

    Raises
    ------
    InvalidInput
        If the file is missing, unreadable, or edited after its hash was recorded.
    """
    settings = protocol.learners.population
    if settings is None:
        return None
    path = Path(settings.file)
    try:
        stat = path.stat()
    except OSError as exc:
        raise InvalidInput(f"{KEY}.file: {path} cannot be read ({exc.strerror})") from None
    try:
        return _verified(str(path), stat.st_mtime_ns, stat.st_size)
    except ValueError as exc:
        raise InvalidInput(f"{KEY}.file: {exc}") from None


def checkpoint_path(protocol: Protocol, category: CategorySpec) -> Path:
    """Where the population's checkpoint for ``category`` is: ``checkpoints/<category>-k<K>``."""
    settings = protocol.learners.population
    assert settings is not None  # callers ask only when the protocol names a population
    from models.checkpoints import checkpoint_name

    return Path(settings.checkpoints) / checkpoint_name(category.name, len(category.questions))


def check_trained_for(
    checkpoint: Checkpoint, population: Population, category: CategorySpec
) -> None:
    """Refuse a checkpoint that was not meta-trained for ``population``'s ``category`` with
    these questions.

    Raises
    ------
    Conflict
        Naming the population the checkpoint records (or that it records none).
    InvalidInput
        When the questions it was trained for differ from the category's, or nobody recorded
        them (a population fitted from a steps CSV, trained without the protocol).
    """
    name = category.name
    recorded = checkpoint.config.get("population")
    if not isinstance(recorded, dict):
        raise Conflict(
            f"{KEY}.checkpoints: {checkpoint.path} was not trained for a population: train it "
            f"with trustlab pretrain --population {KEY}.file --category {name}"
        )
    if recorded.get("sha256") != population.sha256 or recorded.get("category") != name:
        raise Conflict(
            f"{KEY}.checkpoints: {checkpoint.path} was trained for population "
            f"{str(recorded.get('sha256'))[:12]}… ({recorded.get('category')}), the protocol "
            f"names {population.sha256[:12]}… ({name}): retrain it for this population"
        )
    source = recorded.get("source") or {}
    questions = recorded.get("questions") or source.get("questions", {}).get(name)
    if questions is None:
        raise InvalidInput(
            f"{KEY}.checkpoints: neither {checkpoint.path} nor its population records the "
            f"questions of {name!r}, so they cannot be compared with this protocol's: train it "
            "with trustlab pretrain --population FILE --protocol THIS_PROTOCOL"
        )
    if list(questions) != list(category.questions):
        raise InvalidInput(
            f"{KEY}.checkpoints: {checkpoint.path} was trained for other questions of {name!r} "
            "than this protocol asks: the questions differ"
        )


def check_sources(db: Session, protocol: Protocol, population: Population) -> dict[str, Any]:
    """Refuse a population fitted from a study that is still enrolling, unless the protocol
    records why; what the audit log records of the population.

    Raises
    ------
    Conflict
        For a source study still enrolling without ``enrolling_reason``.
    """
    settings = protocol.learners.population
    assert settings is not None  # callers ask only when the protocol names a population
    sources = [str(name) for name in population.content["source"].get("studies", [])]
    enrolling = list(
        db.scalars(
            select(Study.name).where(Study.name.in_(sources), Study.status == StudyStatus.OPEN)
        )
    )
    if enrolling and settings.enrolling_reason is None:
        raise Conflict(
            f"{KEY}: the population was fitted from {', '.join(sorted(enrolling))}, which is "
            "still enrolling: a prior fitted on a running study's participants confounds the "
            "conditions; close its enrolment first, or record why in "
            f"{KEY}.enrolling_reason"
        )
    return {
        "population_sha256": population.sha256,
        "population_source": population.source_label,
        "enrolling_sources": sorted(enrolling),
        "enrolling_reason": settings.enrolling_reason if enrolling else None,
    }
