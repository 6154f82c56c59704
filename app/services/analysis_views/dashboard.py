"""The live study dashboard's data: trust by session and adaptation curves, aggregated in SQL.

Both figures need only per-cell counts, means and standard deviations, so the database computes
them (``COUNT``, ``SUM(x)``, ``SUM(x²)``) and this module turns them into t intervals and Plotly
payloads with the analysis package — the same builders the PI's report uses, so the dashboard and
the report can never disagree. Cost grows with the number of cells, not of participants.

Withdrawn and pilot participants are left out; in a blinded study, roles that may not see
conditions get the neutral group labels, and the cells are listed by those labels (the condition
ids, or rows in their order, would give the mapping away). Until a blinded study is unblinded
nobody gets the adaptation curves (C1 starts at exactly 1/K and C2 does not:
app.services.blinding).

Live dashboards ask for this several times a second while robots answer in the same process, so
the computation is kept lean: what depends only on the protocol and the labels (items, titles,
axis ranges, the SQL statements) is worked out once per study and label set (:class:`Plan`); the
cells go from SQL rows to plain columns without DataFrames (the builders take either); one query
gives the adaptation curves' iteration 0 and later iterations together; and :func:`encode` turns
the result into the response body once for every dashboard that shares it (app/web/dashboard.py).
"""

from __future__ import annotations

import math
import threading
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any, TypeAlias

import numpy as np
import pydantic_core
from sqlalchemy import Float, Select, and_, case, cast, func, select, true
from sqlalchemy.orm import Session

from analysis.descriptives import t_interval
from analysis.figures import (
    adaptation_payload_from_curves,
    condition_colors,
    mean_ci_payload_from_cells,
)
from app.protocol import ItemKind, ItemSpec, Protocol
from app.services.audit import Actor
from app.services.blinding import LEARNERS_SEALED, condition_labels, shows_learners
from app.services.studies import protocol_of
from app.tables import (
    Allocation,
    Answer,
    Participant,
    ParticipantStatus,
    Prompt,
    Response,
    Study,
)

CONFIDENCE = 0.95
GROUP = "group"
Query: TypeAlias = Select[*tuple[Any, ...]]
CELL_COLUMNS = ("n", "mean", "sd", "se", "ci_low", "ci_high")
"""What every cell carries after its factors (as :data:`analysis.descriptives.CELL_COLUMNS`)."""


@dataclass(frozen=True)
class SessionItem:
    """A Likert item asked after every session, with what its scale and key say."""

    instrument: str
    item: ItemSpec
    minimum: int
    maximum: int


def session_items(protocol: Protocol) -> list[SessionItem]:
    """Every Likert item of the per-session instruments, in protocol order."""
    found = []
    for instrument in protocol.instruments_at("session"):
        for item in instrument.items:
            if item.kind is ItemKind.LIKERT and item.scale is not None:
                scale = protocol.scale(item.scale)
                found.append(SessionItem(instrument.key, item, scale.minimum, scale.maximum))
    return found


@dataclass(frozen=True)
class Measure:
    """One trust figure: its item and the texts and axis that do not depend on the data."""

    key: str
    title: str
    y_label: str
    y_range: tuple[float, float]
    flip: int | None
    """``minimum + maximum`` of a reverse-keyed item (scored as flip − x), else None."""


@dataclass(frozen=True)
class Plan:
    """Everything a computation needs besides the data, fixed for a study and a label set."""

    study_id: int
    study_name: str
    labels: dict[str, str]
    """Condition id → what the actor may see of it."""
    measures: tuple[Measure, ...]
    categories: tuple[str, ...]
    """Categories with a preferred question (the ones with an adaptation curve), in order."""
    trust_query: Query
    adaptation_query: Query
    learners: bool = True
    """Whether the adaptation curves may be drawn (False while the study is blinded)."""
    sites: tuple[str, ...] | None = None
    """The only sites whose participants are counted (app.services.privacy.sites); None: all."""

    @property
    def key(self) -> PlanKey:
        """What the result depends on besides the data (see :func:`data_key`)."""
        return self.study_id, tuple(sorted(self.labels.items())), self.learners, self.sites


PlanKey: TypeAlias = tuple[int, tuple[tuple[str, str], ...], bool, tuple[str, ...] | None]
_plans: dict[
    tuple[int, str, str, tuple[tuple[str, str], ...], bool, tuple[str, ...] | None], Plan
] = {}
_plans_guard = threading.Lock()
MAX_PLANS = 256


def plan_for(study: Study, actor: Actor) -> Plan:
    """The study's :class:`Plan` for what ``actor`` may see (made once per protocol version)."""
    protocol = protocol_of(study)
    labels = condition_labels(study, actor)
    learners = shows_learners(study)
    sites = None if actor.sites is None else tuple(sorted(actor.sites))
    cache_key = (
        study.id,
        study.protocol_sha256,
        study.name,
        tuple(labels.items()),
        learners,
        sites,
    )
    plan = _plans.get(cache_key)
    if plan is None:
        plan = _make_plan(study.id, study.name, protocol, labels, learners=learners, sites=sites)
        with _plans_guard:
            if len(_plans) >= MAX_PLANS:
                _plans.clear()
            _plans[cache_key] = plan
    return plan


def _make_plan(
    study_id: int,
    name: str,
    protocol: Protocol,
    labels: dict[str, str],
    *,
    learners: bool,
    sites: tuple[str, ...] | None = None,
) -> Plan:
    items = session_items(protocol)
    measures = tuple(
        Measure(
            key=spec.item.key,
            title=spec.item.text + (" (reverse-scored)" if spec.item.reverse else ""),
            y_label=f"Mean ({spec.minimum}–{spec.maximum}) ± 95 % CI",
            y_range=(spec.minimum - 0.2, spec.maximum + 0.2),
            flip=spec.minimum + spec.maximum if spec.item.reverse else None,
        )
        for spec in items
    )
    return Plan(
        study_id=study_id,
        study_name=name,
        labels=dict(labels),
        measures=measures,
        categories=tuple(c.name for c in protocol.categories if c.preferred is not None),
        trust_query=_trust_query(study_id, items, sites),
        adaptation_query=_adaptation_query(study_id, sites),
        learners=learners,
        sites=sites,
    )


def data_key(study: Study, actor: Actor) -> PlanKey:
    """What :func:`dashboard_data` depends on besides the data: the study, the labels the
    actor may see (blinded roles get neutral ones), whether the learners may be shown and the
    sites counted."""
    return plan_for(study, actor).key


# ------------------------------------------------------------------------------------ SQL


def _participants(study_id: int, sites: tuple[str, ...] | None) -> Any:
    """The participants the curves show: not withdrawn, not pilots
    (app.services.design.study_phases), of the reader's sites."""
    return and_(
        Participant.study_id == study_id,
        Participant.status != ParticipantStatus.WITHDRAWN,
        Participant.pilot.is_(False),
        true() if sites is None else Participant.site.in_(sites),
    )


def _trust_query(
    study_id: int, items: Sequence[SessionItem], sites: tuple[str, ...] | None
) -> Query:
    """condition, session, item, count, sum and sum of squares of every session item's raw
    answers."""
    value = cast(Response.value, Float)
    return (
        select(
            Allocation.condition,
            Response.session,
            Response.item,
            func.count(),
            func.sum(value),
            func.sum(value * value),
        )
        .join(Participant, Participant.id == Response.participant_id)
        .join(Allocation, Allocation.participant_id == Participant.id)
        .where(
            _participants(study_id, sites),
            Response.session.is_not(None),
            Response.item.in_([i.item.key for i in items]),
            Response.instrument.in_(sorted({i.instrument for i in items})),
        )
        .group_by(Allocation.condition, Response.session, Response.item)
    )


def _adaptation_query(study_id: int, sites: tuple[str, ...] | None) -> Query:
    """Per condition × category × learner version after an answer: count, sum and sum of squares
    of p(preferred) after the answer, and of p(preferred) before it when the answer was the
    learner's first (iteration 0), in one pass over the answered adapting prompts."""
    before = case((Prompt.learner_version == 0, Prompt.p_preferred))
    return (
        select(
            Allocation.condition,
            Prompt.category,
            Answer.learner_version,
            func.count(Answer.p_preferred),
            func.sum(Answer.p_preferred),
            func.sum(Answer.p_preferred * Answer.p_preferred),
            func.count(before),
            func.sum(before),
            func.sum(before * before),
        )
        .join(Prompt, Prompt.id == Answer.prompt_id)
        .join(Participant, Participant.id == Answer.participant_id)
        .join(Allocation, Allocation.participant_id == Participant.id)
        .where(_participants(study_id, sites), Prompt.adapts.is_(True))
        .group_by(Allocation.condition, Prompt.category, Answer.learner_version)
    )


# ------------------------------------------------------------------------------------ cells

Moments = dict[tuple[Any, ...], list[Any]]
"""Cell factors → [count, sum, sum of squares]."""


def _add(moments: Moments, key: tuple[Any, ...], n: int, total: float, squares: float) -> None:
    """Count values into a cell. Conditions sharing a label (a protocol may give two the same
    neutral label) are pooled, as the figure shows them as one group anyway."""
    cell = moments.get(key)
    if cell is None:
        moments[key] = [n, total, squares]
    else:
        cell[0] += n
        cell[1] += total
        cell[2] += squares


def _cells(
    factors: list[tuple[Any, ...]], n: list[int], mean: list[float], mean_sq: list[float]
) -> list[tuple[Any, ...]]:
    """Rows of factors + :data:`CELL_COLUMNS`, from n, mean and mean of squares (sample SD, NaN
    for n = 1; the t interval of the analysis package)."""
    if not factors:
        return []
    counts = np.asarray(n, dtype=float)
    means = np.asarray(mean, dtype=float)
    with np.errstate(invalid="ignore", divide="ignore"):
        variance = (
            np.maximum(np.asarray(mean_sq, dtype=float) - means**2, 0.0) * counts / (counts - 1)
        )
        sd = np.where(counts > 1, np.sqrt(variance), np.nan)
        se = sd / np.sqrt(counts)
    low, high = t_interval(means, se, counts - 1, CONFIDENCE)
    stats = zip(
        n, means.tolist(), sd.tolist(), se.tolist(), low.tolist(), high.tolist(), strict=True
    )
    return [(*f, *s) for f, s in zip(factors, stats, strict=True)]


def _columns(names: Sequence[str], rows: Iterable[tuple[Any, ...]]) -> dict[str, list[Any]]:
    """Rows as plain columns, the form the analysis builders take without a DataFrame."""
    listed = list(rows)
    return {name: [row[i] for row in listed] for i, name in enumerate(names)}


def trust_cells(db: Session, plan: Plan) -> list[tuple[Any, ...]]:
    """(group, session, item, n, mean, sd, se, ci_low, ci_high) per group × session × item, on
    the scored (reverse-keyed) scale, in label, session and item order."""
    moments: Moments = {}
    for condition, session, item, n, total, squares in db.execute(plan.trust_query):
        _add(moments, (plan.labels[condition], session, item), n, total, squares)
    flips = {m.key: m.flip for m in plan.measures}
    keys = sorted(moments)
    counts, means, squares_means = [], [], []
    for key in keys:
        n, total, squares = moments[key]
        mean, mean_sq = total / n, squares / n
        flip = flips.get(key[2])
        if flip is not None:  # reverse-keyed: x → min + max − x (SD unchanged)
            mean_sq = flip**2 - 2 * flip * mean + mean_sq
            mean = flip - mean
        counts.append(n)
        means.append(mean)
        squares_means.append(mean_sq)
    return _cells(keys, counts, means, squares_means)


def adaptation_cells(db: Session, plan: Plan) -> list[tuple[Any, ...]]:
    """(group, category, iteration, n, mean, sd, se, ci_low, ci_high) per group × category ×
    iteration (0 = before the first answer) of p(preferred), in that order."""
    moments: Moments = {}
    for condition, category, version, n, total, squares, n0, total0, squares0 in db.execute(
        plan.adaptation_query
    ):
        group = plan.labels[condition]
        if n:
            _add(moments, (group, category, version), n, total, squares)
        if n0:  # answers to a learner's first prompt: its p(preferred) before them
            _add(moments, (group, category, 0), n0, total0, squares0)
    keys = sorted(moments)
    cells = [moments[k] for k in keys]
    return _cells(
        keys, [c[0] for c in cells], [c[1] / c[0] for c in cells], [c[2] / c[0] for c in cells]
    )


# ------------------------------------------------------------------------------------ payload


def json_safe(value: Any) -> Any:
    """Plotly payloads as strict JSON (NaN → null)."""
    if isinstance(value, float):
        return None if math.isnan(value) or math.isinf(value) else value
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [json_safe(v) for v in value]
    return value


def compute(db: Session, plan: Plan) -> dict[str, Any]:
    """Everything the live dashboard draws, as JSON-able payloads (NaN already null)."""
    trust = trust_cells(db, plan)
    # Each condition's colour by its place in the protocol (neutral labels: by their own order,
    # which tells nothing about the conditions: app.services.blinding.condition_labels).
    colors = condition_colors(list(plan.labels.values()))
    measures = []
    for measure in plan.measures:
        cells = _columns(
            (GROUP, "session", "item", *CELL_COLUMNS), (r for r in trust if r[2] == measure.key)
        )
        payload = mean_ci_payload_from_cells(
            cells,
            dv="mean",
            within="session",
            between=GROUP,
            title=measure.title,
            y_label=measure.y_label,
            y_range=measure.y_range,
            within_label="Session",
            style="point",
            colors=colors,
        )
        measures.append({"item": measure.key, "title": measure.title, "payload": payload})
    curves = adaptation_cells(db, plan)
    categories = set(plan.categories)
    adaptation = adaptation_payload_from_curves(
        _columns(
            ("condition", "category", "iteration", *CELL_COLUMNS),
            (r for r in curves if r[1] in categories),
        ),
        plan.categories,
        confidence=CONFIDENCE,
        colors=colors,
    )
    return {
        "study": plan.study_name,
        "measures": measures,
        "adaptation": adaptation if plan.learners else None,
        "learners_hidden": None if plan.learners else LEARNERS_SEALED,
        "answers": sum(r[3] for r in curves if r[2] > 0),
        "questionnaires": sum(r[3] for r in trust),
    }


def dashboard_data(db: Session, *, study: Study, actor: Actor) -> dict[str, Any]:
    """Everything the live dashboard draws for ``actor``, as JSON-able payloads."""
    return compute(db, plan_for(study, actor))


def encode(data: dict[str, Any]) -> bytes:
    """The response body: compact UTF-8 JSON, NaN as null (made once, sent to every sharer).

    pydantic's serialiser, as FastAPI's own responses use, is several times faster than
    :func:`json.dumps` on these 40 kB payloads."""
    return pydantic_core.to_json(data, inf_nan_mode="null")
