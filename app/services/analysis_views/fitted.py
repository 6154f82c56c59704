"""What the analysis pages fit: each kind of result, computed from a dataset by a function that a
worker process can run (app.services.analysis_views.fit_runner) and whose result can be stored
(app.services.analysis_views.fit_cache).

Three kinds, each the unit a page, an export or the report asks for:

- ``study``: :func:`analysis.study.analyse_study` (every measure's mixed ANOVA, descriptives,
  scores, adaptation curves) for one type of sums of squares;
- ``mixed``: one measure's mixed models (linear, ordinal, adaptation and trust), with or without
  the random slope. ``mixed_models.json`` and the report use every measure's, with the slope, so
  the mixed models page of a measure and the exports share them;
- ``pilot``: the power page's estimates from the study's first measure (ρ, ε, each effect's f).

An analysis that cannot be computed from these data (an :class:`analysis.errors.AnalysisError`)
is a result like another: :class:`Failed`, with its one line, stored and shown as it is.

A stored ``study`` result leaves its dataset out (:func:`detached`): the key holds the data's
version, and the request that reads it has just loaded that very dataset, which it attaches
again (with its own manifest: when it was read, the software that reads it).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any, Literal, cast

from analysis.dataset import StudyDataset
from analysis.errors import AnalysisError
from analysis.mixed_models import StudyMixedModels, analyse_mixed_models
from analysis.study import StudyAnalysis, analyse_study
from app.services.analysis_views.power_view import prefilled

Kind = Literal["study", "mixed", "pilot"]
KINDS: tuple[Kind, ...] = ("study", "mixed", "pilot")


@dataclass(frozen=True)
class Failed:
    """An analysis these data do not allow, with why (the page shows it)."""

    message: str


def settings_of(kind: Kind, **settings: Any) -> dict[str, Any]:
    """The settings of ``kind`` with every default filled in, so that two requests asking for
    the same result name it the same way (the cache key is made of them)."""
    if kind == "study":
        return {"ss": int(settings.get("ss", 3))}
    if kind == "mixed":
        return {"measure": str(settings["measure"]), "slope": bool(settings.get("slope", True))}
    return {}


def fit(kind: Kind, dataset: StudyDataset, settings: Mapping[str, Any]) -> Any:
    """The result of ``kind`` for ``dataset`` (:class:`Failed` when the data do not allow it)."""
    if kind == "pilot":
        try:
            return prefilled(analyse_study(dataset))
        except AnalysisError as exc:
            return prefilled(None, str(exc))
    try:
        if kind == "study":
            return detached(analyse_study(dataset, ss_type=settings["ss"]))
        result = analyse_study(dataset)
        return analyse_mixed_models(
            result, keys=[settings["measure"]], random_slope=settings["slope"]
        )
    except AnalysisError as exc:
        return Failed(str(exc))


def detached(result: StudyAnalysis) -> StudyAnalysis:
    """The analysis without its dataset (for storing: the reader attaches its own)."""
    return replace(result, dataset=cast(StudyDataset, None))


def attached(result: StudyAnalysis, dataset: StudyDataset) -> StudyAnalysis:
    """A stored analysis with the dataset of the request that read it."""
    return replace(result, dataset=dataset)


def combined(result: StudyAnalysis, measures: Sequence[StudyMixedModels]) -> StudyMixedModels:
    """Every measure's mixed models, each fitted on its own (with the slope), as
    :func:`analysis.mixed_models.analyse_mixed_models` gives them in one call: what
    ``mixed_models.json`` and the report show."""
    if not measures:  # nothing to fit: the adaptation measures alone, computed now
        return analyse_mixed_models(result)
    return StudyMixedModels(
        outcomes=tuple(models.outcomes[0] for models in measures),
        measures=measures[0].measures,
        measures_problem=measures[0].measures_problem,
        random_slope=True,
    )
