"""The live dashboard's data computed as it was before the fast path (commit 39faf53).

Kept as the oracle of tests/app/test_dashboard_data.py: two SQL aggregations read into pandas
frames, moments turned into cells with pandas, and the analysis builders' DataFrame path (the one
the PI's report takes). The fast path in app/services/analysis_views/dashboard.py must give the same
payloads. Not used by the application.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import pandas as pd
from sqlalchemy import Float, Select, and_, cast, func, literal, select, union_all
from sqlalchemy.orm import Session

from analysis.descriptives import t_interval
from analysis.figures import (
    adaptation_payload_from_curves,
    condition_colors,
    mean_ci_payload_from_cells,
)
from app.protocol import Protocol
from app.services.analysis_views.dashboard import SessionItem, session_items
from app.services.audit import Actor
from app.services.blinding import LEARNERS_SEALED, shows_learners
from app.services.participants.enrolment import condition_label
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


def _moments_to_cells(frame: pd.DataFrame) -> pd.DataFrame:
    """n, mean, mean of squares → n, mean, sd, se, t interval (sample SD; NaN for n = 1)."""
    n = frame["n"].to_numpy(float)
    mean = frame["mean"].to_numpy(float)
    with np.errstate(invalid="ignore", divide="ignore"):
        variance = np.maximum(frame["mean_sq"].to_numpy(float) - mean**2, 0.0) * n / (n - 1)
        sd = np.where(n > 1, np.sqrt(variance), np.nan)
        se = sd / np.sqrt(n)
    low, high = t_interval(mean, se, n - 1, CONFIDENCE)
    out = frame.drop(columns=["mean_sq"]).copy()
    out["n"] = out["n"].astype(int)
    out["sd"], out["se"], out["ci_low"], out["ci_high"] = sd, se, low, high
    return out


def _participants(study: Study) -> Any:
    return and_(
        Participant.study_id == study.id,
        Participant.status != ParticipantStatus.WITHDRAWN,
    )


def trust_cells(db: Session, study: Study, items: Sequence[SessionItem]) -> pd.DataFrame:
    """Per condition × session × item: n, mean, sd, se, CI, on the scored (reverse-keyed) scale."""
    value = cast(Response.value, Float)
    rows = db.execute(
        select(
            Allocation.condition,
            Response.session,
            Response.item,
            func.count().label("n"),
            func.avg(value).label("mean"),
            func.avg(value * value).label("mean_sq"),
        )
        .join(Participant, Participant.id == Response.participant_id)
        .join(Allocation, Allocation.participant_id == Participant.id)
        .where(
            _participants(study),
            Response.session.is_not(None),
            Response.item.in_([i.item.key for i in items]),
            Response.instrument.in_({i.instrument for i in items}),
        )
        .group_by(Allocation.condition, Response.session, Response.item)
        .order_by(Allocation.condition, Response.session)
    ).all()
    frame = pd.DataFrame(rows, columns=["condition", "session", "item", "n", "mean", "mean_sq"])
    for spec in items:  # reverse-keyed items: x → min + max − x (SD unchanged)
        if spec.item.reverse:
            mask = frame["item"] == spec.item.key
            flip = spec.minimum + spec.maximum
            frame.loc[mask, "mean_sq"] = (
                flip**2 - 2 * flip * frame.loc[mask, "mean"] + frame.loc[mask, "mean_sq"]
            )
            frame.loc[mask, "mean"] = flip - frame.loc[mask, "mean"]
    return _moments_to_cells(frame)


def _adaptation_query(study: Study) -> Select[Any]:
    initial = (
        select(
            Allocation.condition,
            Prompt.category,
            literal(0).label("iteration"),
            func.count().label("n"),
            func.avg(Prompt.p_preferred).label("mean"),
            func.avg(Prompt.p_preferred * Prompt.p_preferred).label("mean_sq"),
        )
        .join(Answer, Answer.prompt_id == Prompt.id)  # answered prompts only
        .join(Participant, Participant.id == Prompt.participant_id)
        .join(Allocation, Allocation.participant_id == Participant.id)
        .where(
            _participants(study),
            Prompt.adapts.is_(True),
            Prompt.learner_version == 0,
            Prompt.p_preferred.is_not(None),
        )
        .group_by(Allocation.condition, Prompt.category)
    )
    later = (
        select(
            Allocation.condition,
            Prompt.category,
            Answer.learner_version.label("iteration"),
            func.count().label("n"),
            func.avg(Answer.p_preferred).label("mean"),
            func.avg(Answer.p_preferred * Answer.p_preferred).label("mean_sq"),
        )
        .join(Prompt, Prompt.id == Answer.prompt_id)
        .join(Participant, Participant.id == Answer.participant_id)
        .join(Allocation, Allocation.participant_id == Participant.id)
        .where(_participants(study), Prompt.adapts.is_(True), Answer.p_preferred.is_not(None))
        .group_by(Allocation.condition, Prompt.category, Answer.learner_version)
    )
    return union_all(initial, later)  # type: ignore[return-value]


def adaptation_cells(db: Session, study: Study) -> pd.DataFrame:
    """Per condition × category × iteration (0 = before the first answer): p(preferred)."""
    rows = db.execute(_adaptation_query(study)).all()
    frame = pd.DataFrame(
        rows, columns=["condition", "category", "iteration", "n", "mean", "mean_sq"]
    ).sort_values(["condition", "category", "iteration"], kind="stable")
    return _moments_to_cells(frame.reset_index(drop=True))


def _labels(study: Study, protocol: Protocol, actor: Actor) -> dict[str, str]:
    return {c.id: condition_label(study, c.id, actor=actor) for c in protocol.conditions}


def json_safe(value: Any) -> Any:
    """Plotly payloads as strict JSON (NaN → null)."""
    if isinstance(value, float):
        return None if math.isnan(value) or math.isinf(value) else value
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [json_safe(v) for v in value]
    return value


def dashboard_data(db: Session, *, study: Study, actor: Actor) -> dict[str, Any]:
    """Everything the live dashboard draws, as JSON-able payloads."""
    protocol = protocol_of(study)
    labels = _labels(study, protocol, actor)
    items = session_items(protocol)
    # Cells carry the label the actor may see instead of the condition, and are listed in label
    # order: the ids, or rows ordered by them, would tell a blinded experimenter the mapping.
    trust = trust_cells(db, study, items)
    trust.insert(0, GROUP, trust.pop("condition").map(labels))
    trust = trust.sort_values([GROUP, "session", "item"], kind="stable")
    colors = condition_colors(list(labels.values()))  # by the protocol's order
    measures = []
    for spec in items:
        cells = trust[trust["item"] == spec.item.key]
        title = spec.item.text + (" (reverse-scored)" if spec.item.reverse else "")
        measures.append(
            {
                "item": spec.item.key,
                "title": title,
                "payload": mean_ci_payload_from_cells(
                    cells,
                    dv="mean",
                    within="session",
                    between=GROUP,
                    title=title,
                    y_label=f"Mean ({spec.minimum}–{spec.maximum}) ± 95 % CI",
                    y_range=(spec.minimum - 0.2, spec.maximum + 0.2),
                    within_label="Session",
                    style="point",
                    colors=colors,
                ),
            }
        )
    curves = adaptation_cells(db, study)
    curves["condition"] = curves["condition"].map(labels)
    curves = curves.sort_values(["condition", "category", "iteration"], kind="stable")
    categories = [c.name for c in protocol.categories if c.preferred is not None]
    adaptation = adaptation_payload_from_curves(
        curves[curves["category"].isin(categories)],
        categories,
        confidence=CONFIDENCE,
        colors=colors,
    )
    return json_safe(
        {
            "study": study.name,
            "measures": measures,
            # a blinded study shows no curves until it is unblinded (app.services.blinding)
            "adaptation": adaptation if shows_learners(study) else None,
            "learners_hidden": None if shows_learners(study) else LEARNERS_SEALED,
            "answers": int(curves.loc[curves["iteration"] > 0, "n"].sum()) if len(curves) else 0,
            "questionnaires": int(trust["n"].sum()) if len(trust) else 0,
        }
    )
