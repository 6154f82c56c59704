"""Statistics, scoring, figures, exports and reports for trustlab studies.

Pure data in, data out: this package takes pandas DataFrames (and the small dataclasses of
:mod:`analysis.dataset`, :mod:`analysis.instruments` and :mod:`analysis.scoring`) and never
touches the web layer or the database.

The statistics core is importable from here; figures (:mod:`analysis.figures`), the report
(:mod:`analysis.report`) and the export formats (:mod:`analysis.exports`) live in their own
modules so that importing the statistics does not load Plotly or pyreadstat.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from analysis.anova import MixedAnovaResult, Sphericity, mixed_anova
    from analysis.apa import anova_sentences, format_p, sentence_f, sentence_t
    from analysis.descriptives import cell_descriptives, marginal_means
    from analysis.design import MixedDesign, prepare_mixed_design
    from analysis.errors import (
        AnalysisError,
        CannotComputeError,
        DuplicateObservationError,
        InvalidInputError,
    )
    from analysis.instruments import DEFAULT_INSTRUMENTS, InstrumentSpec, ItemSpec
    from analysis.posthoc import pairwise_comparisons
    from analysis.scoring import DEFAULT_SCALES, ScaleSpec, score_responses, score_scales

_HOMES = {
    **dict.fromkeys(("MixedAnovaResult", "Sphericity", "mixed_anova"), "anova"),
    "anova_sentences": "apa",
    **dict.fromkeys(("format_p", "sentence_f", "sentence_t"), "apa_numbers"),
    **dict.fromkeys(("cell_descriptives", "marginal_means"), "descriptives"),
    **dict.fromkeys(("MixedDesign", "prepare_mixed_design"), "design"),
    **dict.fromkeys(
        ("AnalysisError", "CannotComputeError", "DuplicateObservationError", "InvalidInputError"),
        "errors",
    ),
    **dict.fromkeys(("DEFAULT_INSTRUMENTS", "InstrumentSpec", "ItemSpec"), "instruments"),
    "pairwise_comparisons": "posthoc",
    **dict.fromkeys(("DEFAULT_SCALES", "ScaleSpec", "score_responses", "score_scales"), "scoring"),
}
"""Where each name of the statistics core lives. They are imported on first use (PEP 562), not
with the package: ``import analysis.power`` would otherwise load SciPy's statistics and pandas
for a command that needs neither (docs/development.md, "What a command may import")."""


def __getattr__(name: str) -> Any:
    home = _HOMES.get(name)
    if home is None:
        raise AttributeError(f"module 'analysis' has no attribute {name!r}")
    return getattr(importlib.import_module(f"analysis.{home}"), name)


__all__ = [
    "DEFAULT_INSTRUMENTS",
    "DEFAULT_SCALES",
    "AnalysisError",
    "CannotComputeError",
    "DuplicateObservationError",
    "InstrumentSpec",
    "InvalidInputError",
    "ItemSpec",
    "MixedAnovaResult",
    "MixedDesign",
    "ScaleSpec",
    "Sphericity",
    "anova_sentences",
    "cell_descriptives",
    "format_p",
    "marginal_means",
    "mixed_anova",
    "pairwise_comparisons",
    "prepare_mixed_design",
    "score_responses",
    "score_scales",
    "sentence_f",
    "sentence_t",
]
