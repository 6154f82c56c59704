"""The PI's pages: the analysis of a study in the browser, and the export downloads."""

from __future__ import annotations

import tempfile
from pathlib import Path

from fastapi import Request
from fastapi.responses import Response
from starlette.background import BackgroundTask
from starlette.responses import FileResponse

from analysis.exports import EXPORT_FORMATS, sha256_file, write_export
from app.deps import AnalystUser, OneHopRouter, ReaderScope, SessionDep, SiteFilter
from app.errors import Conflict, InvalidInput, NotFound
from app.inputs import Count
from app.services import audit, blinding, studies
from app.services.analysis_views import fitted, study_data
from app.services.analysis_views.analysis_view import analysis_view
from app.services.analysis_views.export_fits import fitted_analyses
from app.services.analysis_views.fit_runner import FitRunner, Fitting
from app.services.analysis_views.mixed_view import mixed_view
from app.services.analysis_views.power_view import PlanForm, plan_view
from app.services.audit import Actor
from app.services.design import study_phases
from app.services.privacy import pseudonyms, sites
from app.web.templating import is_htmx, render

router = OneHopRouter(tags=["pages"], include_in_schema=False)

STEP_LOG_EXPORTS = frozenset({"steps-csv", "adaptation-csv"})
"""The exports made of the learners' step log (refused while the study is blinded)."""


def _fits(request: Request) -> FitRunner:
    runner: FitRunner = request.app.state.analysis_fits
    return runner


@router.get("/studies/{name}/analysis")
def analysis_page(
    request: Request,
    db: SessionDep,
    user: AnalystUser,
    scope: ReaderScope,
    name: str,
    ss: Count = 3,
    site: SiteFilter = "",
) -> Response:
    """The mixed ANOVA of every per-session measure, fitted once per data version
    (``?site=``: one site's participants only); "fitting…" while a fit takes longer (htmx polls
    the results block)."""
    if ss not in (2, 3):
        raise InvalidInput("ss: the sums of squares are of type 3 (default) or 2")
    study = studies.get_study(db, name)
    dataset = study_data.load_dataset(
        db, study=study, for_staff=True, scope=scope.narrowed(site, study)
    )
    fits = _fits(request).for_study(db, study_id=study.id, dataset=dataset)
    fits.start("pilot")
    result = fits.get("study", ss=ss)
    pilot = fits.get("pilot")
    view, error, fitting = None, "", None
    if isinstance(result, Fitting):
        fitting = result
    elif isinstance(result, fitted.Failed):
        error = result.message
    else:
        view = analysis_view(fitted.attached(result, dataset))
    if isinstance(pilot, Fitting):
        fitting = fitting or pilot
        plan = None
    else:
        plan = plan_view(*pilot)
    return render(
        request,
        "analysis.html",
        {
            "study": study,
            "view": view,
            "error": error,
            "fitting": fitting,
            "plan": plan,
            "formats": EXPORT_FORMATS.values(),
            "manifest": dataset.manifest,
            "step_logs": STEP_LOG_EXPORTS,
            "steps_withheld": dataset.steps_withheld,
            "pseudonyms": request.app.state.settings.pseudonym_key is not None,
            "site": site.strip(),
            "site_choices": sites.choices(studies.protocol_of(study), Actor.of_user(user)),
            "study_sites": sites.names(studies.protocol_of(study)),
            "pilots": study_phases.pilot_count(db, study),
        },
        block="results",
    )


@router.get("/studies/{name}/analysis/mixed")
def mixed_models_page(
    request: Request,
    db: SessionDep,
    user: AnalystUser,
    scope: ReaderScope,
    name: str,
    measure: str = "",
    slope: bool = False,
    site: SiteFilter = "",
) -> Response:
    """One measure's mixed models, fitted once per data version: the whole page, or its
    section for htmx ("fitting…" while the fit runs; the section polls until it is done)."""
    study = studies.get_study(db, name)
    dataset = study_data.load_dataset(
        db, study=study, for_staff=True, scope=scope.narrowed(site, study)
    )
    fits = _fits(request).for_study(db, study_id=study.id, dataset=dataset)
    view, error, fitting = None, "", None
    result = fits.get("study")
    if isinstance(result, Fitting):
        fitting = result
    elif isinstance(result, fitted.Failed):
        error = result.message
    elif not result.outcomes:
        error = (
            "Nothing to model yet: the mixed models of each trust measure appear here once "
            "participants have answered the questionnaire after their sessions."
        )
    else:
        key = measure or result.outcomes[0].key
        keys = [o.key for o in result.outcomes]
        if key not in keys:
            raise InvalidInput(
                f"measure: no per-session measure {key!r}; choose one of {', '.join(keys)}"
            )
        models = fits.get("mixed", measure=key, slope=slope)
        if isinstance(models, Fitting):
            fitting = models
        elif isinstance(models, fitted.Failed):
            error = models.message
        else:
            study_result = fitted.attached(result, dataset)
            view = mixed_view(study_result, models.outcomes[0], random_slope=slope)
    return render(
        request,
        "analysis_mixed.html",
        {
            "study": study,
            "view": view,
            "error": error,
            "fitting": fitting,
            "measure": measure,
            "slope": slope,
            "site": site.strip(),
        },
        block="mixed_models",
    )


@router.get("/studies/{name}/analysis/power")
def power_plan_page(
    request: Request, db: SessionDep, user: AnalystUser, scope: ReaderScope, name: str
) -> Response:
    """Power, N or detectable effect for the next study: the page, or its answer for htmx
    (prefilled from the participants the account may see, estimated once per data version)."""
    # The fields are read from the query as text by the view, so a bad one is refused in one
    # line naming it (422, the page showing the words), never pydantic's list of errors.
    study = studies.get_study(db, name)
    form = PlanForm.from_query(request.query_params)
    basis, fitting = "", None
    if form is None or not is_htmx(request):  # the whole page says where its values came from
        dataset = study_data.load_dataset(db, study=study, for_staff=True, scope=scope)
        pilot = _fits(request).for_study(db, study_id=study.id, dataset=dataset).get("pilot")
        if isinstance(pilot, Fitting):
            fitting = pilot
            initial = PlanForm()
        else:
            initial, basis = pilot
        form = form or initial
    plan = plan_view(form, basis)
    return render(
        request,
        "analysis_power.html",
        {"study": study, "plan": plan, "error": plan.error, "fitting": fitting},
        block="power_plan",
        status_code=422 if plan.error else 200,
    )


@router.get("/studies/{name}/exports/{export}")
def download(
    request: Request,
    db: SessionDep,
    user: AnalystUser,
    scope: ReaderScope,
    name: str,
    export: str,
    site: SiteFilter = "",
) -> Response:
    """One export file, built now from the stored data (the download is audited); only the
    participants of the sites the user sees (``?site=``: of that one); ``?pilot=1``: the pilot
    participants' instead of the study's (app.services.design.study_phases)."""
    spec = EXPORT_FORMATS.get(export)
    if spec is None:
        raise NotFound(f"no export {export!r}; choose one of {', '.join(EXPORT_FORMATS)}")
    study = studies.get_study(db, name)
    scope = scope.narrowed(site, study)
    if export in STEP_LOG_EXPORTS and not blinding.shows_learners(study):
        raise Conflict(f"no step log yet: {blinding.LEARNERS_SEALED}")  # before reading it all
    pseudonymise = request.query_params.get("pseudonymise") in ("1", "true", "yes")
    key = None
    if pseudonymise:
        configured = request.app.state.settings.pseudonym_key
        key = pseudonyms.require_key(configured.get_secret_value() if configured else None)
    pilot = request.query_params.get("pilot") in ("1", "true", "yes")
    dataset = study_data.load_dataset(db, study=study, for_staff=True, scope=scope, pilot=pilot)
    if key is not None:
        dataset = pseudonyms.pseudonymised(dataset, key=key, study=study.name)
    analyses = None
    if spec.write_fitted is not None:  # made of the fitted analyses: the cached ones
        analyses = fitted_analyses(_fits(request).for_study(db, study_id=study.id, dataset=dataset))
    folder = Path(tempfile.mkdtemp(prefix="trustlab-export-"))
    path = write_export(dataset, export, folder / spec.filename, fitted=analyses)
    digest = sha256_file(path)
    with request.app.state.database.write_session() as writer:
        audit.record(
            writer,
            actor=Actor.of_user(user),
            action="export.downloaded",
            study_id=study.id,
            subject=export,
            details={
                "sha256": digest,
                "data_sha256": dataset.manifest["data_sha256"],
                "pseudonymised": key is not None,
                "sites": None if scope.sites is None else sorted(scope.sites),
            }
            | ({"pilot": True} if pilot else {}),
        )
        writer.commit()

    def cleanup() -> None:
        path.unlink(missing_ok=True)
        folder.rmdir()

    return FileResponse(
        path,
        media_type=spec.media_type,
        filename=f"{study.name}-{'pilot-' if pilot else ''}{spec.filename}",
        headers={"X-Content-SHA256": digest, "Cache-Control": "no-store"},
        background=BackgroundTask(cleanup),
    )
