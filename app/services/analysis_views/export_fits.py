"""The fitted analyses an export is made of (``mixed_models.json``, the report), as the pages
fit and keep them (issue 49: fitted once per data version and settings).

One function, used by the download route (app.web.analysis_pages) and by ``trustlab export``
(app.cli.exports), so both ask app.services.analysis_views.fit_runner for the same keys: a
report downloaded from the page and one exported from the command line after it fit nothing
twice, and what the command line fits is stored for the pages.
"""

from __future__ import annotations

from analysis.exports.files import FittedAnalyses
from app.services.analysis_views import fitted
from app.services.analysis_views.fit_runner import StudyFits

__all__ = ["fitted_analyses"]


def fitted_analyses(fits: StudyFits) -> FittedAnalyses | None:
    """The study's ANOVAs and every measure's mixed models (with the slope), as the pages fit
    and keep them: waited for, each measure's fit started before the first is awaited. None
    when the ANOVAs cannot be computed (the export then says why itself)."""
    result = fits.result("study")
    if isinstance(result, fitted.Failed):
        return None
    keys = [outcome.key for outcome in result.outcomes]
    for key in keys:
        fits.start("mixed", measure=key, slope=True)
    measures = [fits.result("mixed", measure=key, slope=True) for key in keys]
    if any(isinstance(models, fitted.Failed) for models in measures):
        return None
    study_result = fitted.attached(result, fits.dataset)
    return FittedAnalyses(study_result, fitted.combined(study_result, measures))
