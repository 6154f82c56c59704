"""From the database to the analysis package: one :class:`analysis.dataset.StudyDataset`.

The protocol's instruments, scales and categories are translated into the analysis package's plain
specifications here, so analysis never sees the database or the protocol model. The manifest says
exactly what produced an export: a SHA-256 of the data, the protocol's hash, the checkpoints'
hashes, a commitment to the (still secret) allocation seed, and the software versions.
"""

from __future__ import annotations

import hashlib
import json
import platform
from importlib import metadata
from typing import Any

import pandas as pd
from sqlalchemy import ColumnElement, select
from sqlalchemy.orm import Session

from analysis.dataset import ProtocolSummary, StudyDataset, empty_steps
from analysis.exports.tables import ANSWER_COLUMNS
from analysis.instruments import InstrumentSpec as AnalysisInstrument
from analysis.instruments import ItemSpec as AnalysisItem
from analysis.population import source_label
from analysis.scoring import ScaleSpec
from app.protocol import SITE_FACTOR, InstrumentSpec, ItemKind, Protocol
from app.services.analysis_views import registrations
from app.services.blinding import LEARNERS_SEALED, shows_learners
from app.services.participants import data_quality, languages
from app.services.participants.questionnaires import CONSENT, DESCRIPTION_SUFFIX
from app.services.privacy.sites import Scope
from app.services.sessions import learners
from app.services.studies import protocol_of
from app.tables import (
    Allocation,
    Answer,
    LearnerState,
    Participant,
    Prompt,
    ProtocolVersion,
    Response,
    Run,
    Study,
    StudySession,
    utcnow,
)

PILOT_COLUMN = "pilot"
"""The participant attribute (1) a pilot's dataset carries in every export row."""
VERSION_COLUMN = "protocol_versions"
"""The participant attribute naming the protocol versions they ran under (``2``, ``1+2``), in a
study whose protocol has more than one version (app.services.design.protocol_versions)."""

SOFTWARE = (
    "trustlab",
    "numpy",
    "pandas",
    "scipy",
    "pingouin",
    "statsmodels",
    "plotly",
    "sqlalchemy",
    "torch",
)


def _items(protocol: Protocol, instrument: InstrumentSpec) -> tuple[AnalysisItem, ...]:
    items: list[AnalysisItem] = []
    for item in instrument.items:
        if item.kind is ItemKind.LIKERT:
            assert item.scale is not None
            scale = protocol.scale(item.scale)
            labels: tuple[tuple[int | str, str], ...] = ()
            if len(scale.labels) == scale.maximum - scale.minimum + 1:
                labels = tuple(
                    zip(range(scale.minimum, scale.maximum + 1), scale.labels, strict=True)
                )
            elif len(scale.labels) == 2:
                labels = ((scale.minimum, scale.labels[0]), (scale.maximum, scale.labels[1]))
            items.append(
                AnalysisItem(
                    item.key,
                    item.text,
                    "likert",
                    scale.minimum,
                    scale.maximum,
                    labels,
                    item.reverse,
                    expected=item.expected,
                )
            )
        elif item.kind is ItemKind.NUMBER:
            items.append(
                AnalysisItem(
                    item.key,
                    item.text,
                    "numeric",
                    item.minimum,
                    item.maximum,
                    expected=item.expected,
                )
            )
        elif item.kind is ItemKind.CHOICE:
            items.append(
                AnalysisItem(
                    item.key,
                    item.text,
                    "categorical",
                    value_labels=tuple((option.value, option.label) for option in item.options),
                    expected=item.expected,
                )
            )
            if any(option.describe for option in item.options):
                items.append(
                    AnalysisItem(item.key + DESCRIPTION_SUFFIX, f"{item.text} (own words)", "text")
                )
        else:
            items.append(AnalysisItem(item.key, item.text, "text"))
    return tuple(items)


def instruments_of(protocol: Protocol) -> tuple[AnalysisInstrument, ...]:
    """The protocol's instruments (and the consent record) as analysis specifications."""
    consent = AnalysisInstrument(
        CONSENT,
        "Consent",
        (
            AnalysisItem(
                "accepted", "Consent given", "categorical", value_labels=(("yes", "yes"),)
            ),
            AnalysisItem(
                "protocol_version",
                "Version of the consent text accepted, as its protocol names it (e.g. 1.0)",
                "text",
            ),
            AnalysisItem("consent_language", "Language of the consent text accepted", "text"),
            AnalysisItem("consent_sha256", "SHA-256 of the exact consent text accepted", "text"),
            AnalysisItem(
                "consent_version",
                "Number of the consent text's version accepted (1: the protocol's own; the "
                "latest, when accepted again after a change)",
                "text",
            ),
        ),
    )
    return (
        consent,
        *(
            AnalysisInstrument(
                instrument.key,
                instrument.title,
                _items(protocol, instrument),
                per_session=instrument.when == "session",
                after_study=instrument.when == "post",
                citation=instrument.citation,
                stem=instrument.instructions,
            )
            for instrument in protocol.questionnaires.instruments
        ),
    )


def scales_of(protocol: Protocol) -> tuple[ScaleSpec, ...]:
    """The protocol's scores as analysis scale specifications (reverse keys from the items)."""
    by_key = {i.key: i for i in protocol.questionnaires.instruments}
    scales = []
    for score in protocol.questionnaires.scores:
        instrument = by_key[score.instrument]
        items = {item.key: item for item in instrument.items}
        first = items[score.items[0]]
        assert first.scale is not None
        scale = protocol.scale(first.scale)
        scales.append(
            ScaleSpec(
                name=score.name,
                instrument=score.instrument,
                items=tuple(score.items),
                reverse=frozenset(key for key in score.items if items[key].reverse),
                scale_min=scale.minimum,
                scale_max=scale.maximum,
                method=score.method,
                label=score.label or score.name,
                citation=instrument.citation,
            )
        )
    return tuple(scales)


def protocol_summary(study: Study, protocol: Protocol) -> ProtocolSummary:
    """What the report's methods paragraph needs to know about the protocol."""
    with_preferred = [c for c in protocol.categories if c.preferred is not None]
    factors = list(protocol.allocation.stratify_by)
    if protocol.sites is not None and protocol.sites.stratify:
        factors.append(SITE_FACTOR)
    summary: ProtocolSummary = {
        # The study's own title, not the protocol's: a pilot and the main study share a protocol.
        "study": study.title,
        "conditions": [{"code": c.id, "label": c.label} for c in protocol.conditions],
        "categories": {c.name: list(c.questions) for c in with_preferred},
        "preferred_arms": {c.name: c.preferred for c in with_preferred},  # type: ignore[misc]
        "sessions": protocol.schedule.sessions,
        "runs_per_session": protocol.schedule.runs_per_session,
        "familiarisation_runs": 1 if protocol.schedule.familiarisation_run else 0,
        "allocation": "permuted blocks of "
        + " and ".join(str(s) for s in protocol.allocation.block_sizes)
        + (f", stratified by {', '.join(factors)}" if factors else ""),
        "feedback": f"yes → {protocol.reward.yes:g}, no → {protocol.reward.no:g}",
        "version": study.protocol_sha256,
        "reply_levels": [level.name for level in protocol.replies.levels],
        # The analysis specification's covariates come from these (analysis.specification).
        "languages": list(protocol.study.languages),
        "sites": list(protocol.sites.names) if protocol.sites is not None else [],
    }
    if protocol.speech.record_audio:
        summary["record_audio"] = True
    rules = protocol.quality_rules()
    if rules is not None:  # registered by trustlab prereg and applied by the analysis
        summary["quality"] = rules.model_dump(mode="json")
    if len(protocol.study.languages) > 1:  # the codebook lists, and the report cites, each one
        summary["translations"] = languages.translation_summary(protocol)
    return summary


def population_used(db: Session, study: Study) -> dict[str, Any] | None:
    """The population C2's learners were meta-trained for, as their checkpoints record it
    (issue 20), or None when none was. Read from the checkpoints the learners were created with
    (found by hash, as ``trustlab verify`` finds them), so it says what was used, not what the
    protocol's file holds today; one learner per category is enough (study creation checked
    that every checkpoint records the protocol's population)."""
    rows = db.execute(
        select(LearnerState.category, LearnerState.n_arms, LearnerState.config)
        .add_columns(LearnerState.checkpoint_sha256)
        .join(Participant, Participant.id == LearnerState.participant_id)
        .where(Participant.study_id == study.id, LearnerState.kind == "meta")
        .order_by(LearnerState.id)
    )
    categories: dict[str, dict[str, Any]] = {}
    summary: dict[str, Any] | None = None
    for category, n_arms, config, digest in rows:
        if category in categories or "population_sha256" not in config:
            continue
        spec = learners.LearnerSpec("meta", n_arms, dict(config), digest)
        try:
            record = learners.recorded_checkpoint(spec).config["population"]
        except (ValueError, KeyError):  # the checkpoint is gone: the hash is all that is known
            record = {"sha256": config["population_sha256"], "source": {}}
        summary = summary or {
            "sha256": record["sha256"],
            "source": source_label(record["source"]),
            "enrolling_reason": record["source"].get("enrolling_reason"),
            "categories": categories,
        }
        categories[category] = {
            key: record[key]
            for key in ("participants", "prior", "prior_ci", "slip", "slip_ci", "hazard")
            if key in record
        }
    return summary


def _of_scope(study: Study, scope: Scope, *, pilot: bool) -> ColumnElement[bool]:
    """The study's participants in ``scope`` (app.services.privacy.sites): its live ones, or
    its pilot's (app.services.design.study_phases)."""
    return (Participant.study_id == study.id) & scope.where() & Participant.pilot.is_(pilot)


def _versions_run_under(db: Session, whom: ColumnElement[bool]) -> dict[str, str]:
    """Participant code → the protocol versions their sessions ran under (``1`` or ``1+2``;
    their enrolment's before any session)."""
    query = select(Participant.code, Participant.protocol_version).where(whom)
    enrolled = dict(db.execute(query).all())
    ran: dict[str, set[int]] = {}
    for code, version in db.execute(
        select(Participant.code, StudySession.protocol_version)
        .join(StudySession, StudySession.participant_id == Participant.id)
        .where(whom, StudySession.protocol_version.is_not(None))
        .distinct()
    ):
        ran.setdefault(code, set()).add(int(version or 1))
    return {
        code: "+".join(str(v) for v in sorted(ran.get(code) or {version or 1}))
        for code, version in enrolled.items()
    }


def _participants(
    db: Session,
    protocol: Protocol,
    whom: ColumnElement[bool],
    *,
    pilot: bool,
    amended: bool,
) -> pd.DataFrame:
    """One row per participant; ``amended``: the study has had more than one protocol version,
    so each row says which its participant ran under (:data:`VERSION_COLUMN`)."""
    rows = db.execute(
        select(
            Participant.id,
            Participant.code,
            Allocation.condition,
            Participant.status,
            Participant.language,
            Participant.site,
            Participant.strata,
        )
        .join(Allocation, Allocation.participant_id == Participant.id)
        .where(whom, Participant.erased_at.is_(None))
        .order_by(Participant.enrolled_at, Participant.id)
    ).all()
    # A multi-site study's site is a participant attribute like the language: the exports put it
    # in every row (analysis.exports.tables), and the mixed models can adjust for it.
    site_column = [SITE_FACTOR] if protocol.sites is not None else []
    # A pilot's data say so in every row of every export made of them (never mixed with live).
    pilot_column = [PILOT_COLUMN] if pilot else []
    version_column = [VERSION_COLUMN] if amended else []
    versions = _versions_run_under(db, whom) if amended else {}
    # With data-quality rules, every row carries its flags and their measures (every export,
    # and the analysis's exclusions by flag: analysis.study).
    quality = data_quality.quality_by_participant(db, protocol, whom)
    quality_columns = list(data_quality.QUALITY_COLUMNS) if protocol.quality_rules() else []
    frame = pd.DataFrame(
        [
            {
                "participant": code,
                "condition": condition,
                "status": status,
                # Not chosen yet (the tablet asks first): the language the study would use.
                "language": language or protocol.default_language,
                **({SITE_FACTOR: site} if site_column else {}),
                **({PILOT_COLUMN: 1} if pilot else {}),
                **({VERSION_COLUMN: versions.get(code, "")} if amended else {}),
                **{factor: strata.get(factor) for factor in protocol.allocation.stratify_by},
                **(quality[participant_id].columns() if quality_columns else {}),
            }
            for participant_id, code, condition, status, language, site, strata in rows
        ],
        columns=[
            "participant",
            "condition",
            "status",
            "language",
            *site_column,
            *pilot_column,
            *version_column,
            *protocol.allocation.stratify_by,
            *quality_columns,
        ],
    )
    return frame


def _responses(
    db: Session, instruments: tuple[AnalysisInstrument, ...], whom: ColumnElement[bool]
) -> pd.DataFrame:
    numeric = {
        (spec.name, item.key)
        for spec in instruments
        for item in spec.items
        if item.kind in ("likert", "numeric")
    }
    rows = db.execute(
        select(
            Participant.code, Response.instrument, Response.session, Response.item, Response.value
        )
        .join(Participant, Participant.id == Response.participant_id)
        .where(whom)
        .order_by(Participant.id, Response.instrument, Response.session, Response.id)
    ).all()
    # Plain tuples: pandas reads SQLAlchemy's Row objects several times slower (0.2 s of the
    # page's time at 100 participants).
    frame = pd.DataFrame(
        [tuple(row) for row in rows],
        columns=["participant", "instrument", "session", "item", "value"],
    )
    frame["session"] = frame["session"].astype("Int64")
    values: list[Any] = [
        float(value) if (instrument, item) in numeric else value
        for instrument, item, value in zip(
            frame["instrument"], frame["item"], frame["value"], strict=True
        )
    ]
    frame["value"] = pd.Series(values, dtype=object)
    return frame


def _steps(db: Session, categories: set[str], whom: ColumnElement[bool]) -> pd.DataFrame:
    rows = db.execute(
        select(
            Participant.code,
            Allocation.condition,
            Prompt.category,
            StudySession.number,
            Run.number,
            Answer.learner_version,
            Prompt.action,
            Prompt.probabilities,
            Answer.probabilities_after,
            Answer.answer,
            Answer.reward,
            Answer.probability,
            Answer.confidence_level,
            Answer.modality,
            Answer.transcript,
            Answer.transcript_confidence,
            Answer.transcript_engine,
        )
        .join(Prompt, Prompt.id == Answer.prompt_id)
        .join(Run, Run.id == Prompt.run_id)
        .join(StudySession, StudySession.id == Run.session_id)
        .join(Participant, Participant.id == Answer.participant_id)
        .join(Allocation, Allocation.participant_id == Participant.id)
        .where(
            whom,
            Prompt.adapts.is_(True),
            Prompt.category.in_(categories),
        )
        .order_by(Participant.id, Prompt.category, Answer.learner_version)
    ).all()
    return pd.DataFrame(
        [tuple(row) for row in rows],
        columns=[
            "participant",
            "condition",
            "category",
            "session",
            "run",
            "iteration",
            "action",
            "probs_before",
            "probs_after",
            "answer",
            "reward",
            "reply_probability",
            "reply_level",
            *ANSWER_COLUMNS,
        ],
    )


def _software() -> dict[str, str]:
    versions = {"python": platform.python_version()}
    for package in SOFTWARE:
        try:
            versions[package] = metadata.version(package)
        except metadata.PackageNotFoundError:
            continue
    return versions


def _data_sha256(*frames: pd.DataFrame) -> str:
    digest = hashlib.sha256()
    for frame in frames:
        digest.update(frame.to_csv(index=False, lineterminator="\n").encode())
    return digest.hexdigest()


def load_dataset(
    db: Session, *, study: Study, scope: Scope, for_staff: bool = False, pilot: bool = False
) -> StudyDataset:
    """The whole study as the analysis package expects it, with real condition ids (exports are
    for analysts and admins). ``for_staff``: for a signed-in person, so while the study is
    blinded the step log is withheld (app.services.blinding); the command line passes False.
    ``scope``: whose participants (a site-limited account's sites, a page's site filter, or
    every site on the command line: app.services.privacy.sites), required, so that no page can
    forget it; the manifest names the sites of a limited one. ``pilot``: the pilot participants'
    data instead of the live ones' (app.services.design.study_phases), to try the analysis and the
    exports on; the analyses, reports and registrations of the study never see them."""
    protocol = protocol_of(study)
    instruments = instruments_of(protocol)
    summary = protocol_summary(study, protocol)
    whom = _of_scope(study, scope, pilot=pilot)
    versions = select(ProtocolVersion.number, ProtocolVersion.sha256).where(
        ProtocolVersion.study_id == study.id
    )
    history: dict[int, str] = {number: sha256 for number, sha256 in db.execute(versions).all()}  # noqa: C416
    participants = _participants(db, protocol, whom, pilot=pilot, amended=len(history) > 1)
    responses = _responses(db, instruments, whom)
    withheld = LEARNERS_SEALED if for_staff and not shows_learners(study) else ""
    steps = empty_steps() if withheld else _steps(db, set(summary["categories"]), whom)
    digests = db.scalars(
        select(LearnerState.checkpoint_sha256)
        .join(Participant, Participant.id == LearnerState.participant_id)
        .where(Participant.study_id == study.id, LearnerState.checkpoint_sha256.is_not(None))
        .distinct()
    )
    checkpoints = sorted(digest for digest in digests if digest)
    # While the step log is withheld (blinded), so is C2's starting point: it tells the learner.
    population = None if withheld else population_used(db, study)
    if population is not None:
        summary["population"] = population
    manifest = {
        "study": study.name,
        "title": study.title,
        "exported_at": utcnow().isoformat(timespec="seconds"),
        "data_sha256": _data_sha256(participants, responses, steps),
        "protocol_sha256": study.protocol_sha256,
        "checkpoints_sha256": checkpoints,
        "population_sha256": None if population is None else population["sha256"],
        "allocation_seed_sha256": hashlib.sha256(study.allocation_seed.encode()).hexdigest(),
        "learners": json.loads(json.dumps(protocol.learners.model_dump(mode="json"))),
        "software": _software(),
    }
    if scope.sites is not None:
        manifest["sites"] = sorted(scope.sites)
    if pilot:
        manifest["participants"] = "pilot"
    if len(history) > 1:
        manifest["protocol_versions"] = {str(n): history[n] for n in sorted(history)}
    registration, registration_source = registrations.latest(db, study)
    return StudyDataset(
        participants=participants,
        responses=responses,
        protocol=summary,
        steps=steps,
        manifest=manifest,
        instruments=instruments,
        scales=scales_of(protocol),
        excluded_flags=frozenset(summary.get("quality", {}).get("exclude", [])),
        steps_withheld=withheld,
        registration=registration,
        registration_source=registration_source,
    )
