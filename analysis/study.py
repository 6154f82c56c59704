"""The whole analysis of one study: every trust item and scale, scores, adaptation curves.

:func:`analyse_study` is what the report, the benchmark and the dashboard call: it applies the
status exclusions once, scores the raw answers, runs the mixed ANOVA with its descriptives,
marginal means and post-hoc tests for every per-session outcome, summarises the once-only
questionnaires, and computes the adaptation curves. A degenerate outcome does not stop the
others: its :attr:`OutcomeAnalysis.problem` says why it could not be computed.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import pandas as pd

from analysis.adaptation import CURVE_COLUMNS, adaptation_curves
from analysis.anova import MixedAnovaResult, SSType, mixed_anova_from_design
from analysis.apa import anova_sentences
from analysis.dataset import StudyDataset
from analysis.descriptives import CELL_COLUMNS, cell_descriptives, marginal_means_from_design
from analysis.design import prepare_mixed_design
from analysis.errors import AnalysisError, InvalidInputError
from analysis.figures import condition_colors
from analysis.posthoc import pairwise_comparisons_from_design
from analysis.scoring import score_responses, score_scales

__all__ = ["EXCLUSION_LIST_COLUMNS", "OutcomeAnalysis", "StudyAnalysis", "analyse_study"]

EXCLUSION_LIST_COLUMNS = ("participant", "condition", "analysis", "reason")
"""Columns of :meth:`StudyAnalysis.exclusions`."""


@dataclass(frozen=True)
class OutcomeAnalysis:
    """The mixed ANOVA and everything around it for one per-session outcome.

    Attributes
    ----------
    key : str
        Item key (``"trust_1"``) or scale name.
    label : str
        Item text or scale label.
    instrument : str
    kind : {"item", "scale"}
    value_range : (float, float) or None
        Possible range (for figure axes).
    reverse_keyed : bool
        The item is analysed after its reverse key (e.g. ``trust_5``: 6 − x).
    data : pandas.DataFrame
        ``participant``, ``condition``, ``session``, ``value`` (scored) of analysed participants.
    anova : MixedAnovaResult or None
        None when the ANOVA cannot be computed (see ``problem``).
    problem : str
        Empty, or the reason the ANOVA is missing ("… cannot be computed because …").
    descriptives : pandas.DataFrame
        Cell descriptives of the ANOVA's complete cases (of all available values if the ANOVA
        could not be computed).
    marginal_conditions, marginal_sessions, posthoc, sentences : pandas.DataFrame or None
        Estimated marginal means, Holm post-hoc tests and APA sentences (None without ANOVA).
    """

    key: str
    label: str
    instrument: str
    kind: Literal["item", "scale"]
    value_range: tuple[float, float] | None
    reverse_keyed: bool
    data: pd.DataFrame
    anova: MixedAnovaResult | None
    problem: str
    descriptives: pd.DataFrame
    marginal_conditions: pd.DataFrame | None
    marginal_sessions: pd.DataFrame | None
    posthoc: pd.DataFrame | None
    sentences: pd.DataFrame | None


@dataclass(frozen=True)
class StudyAnalysis:
    """Result of :func:`analyse_study`.

    Attributes
    ----------
    dataset : StudyDataset
    ss_type : int
    confidence : float
        Coverage of every confidence interval.
    participants : pandas.DataFrame
        Participants analysed (status not excluded).
    status_exclusions : pandas.DataFrame
        ``participant``, ``condition``, ``status``, ``reason`` of those left out by status.
    scored : pandas.DataFrame
        Scored responses of the analysed participants (with ``condition``; the participant,
        instrument and item columns are categoricals).
    scale_scores : pandas.DataFrame
        Every scale score (with ``condition``).
    outcomes : tuple of OutcomeAnalysis
        Per-session items first (instrument order), then per-session scales.
    person_scores : pandas.DataFrame
        Scores of once-only scales: ``participant``, ``condition``, ``scale``, ``score``.
    person_summary : pandas.DataFrame
        ``scale``, ``condition``, ``n``, ``mean``, ``sd`` of ``person_scores``.
    adaptation : pandas.DataFrame
        Adaptation curves (:data:`analysis.adaptation.CURVE_COLUMNS`); empty without steps.
    adaptation_problem : str
        Why the curves are missing, if the step log could not be used.
    sample : dict
        ``n``, ``by_condition``, and where answered ``gender`` counts and ``age`` statistics.
    """

    dataset: StudyDataset
    ss_type: int
    confidence: float
    participants: pd.DataFrame
    status_exclusions: pd.DataFrame
    scored: pd.DataFrame
    scale_scores: pd.DataFrame
    outcomes: tuple[OutcomeAnalysis, ...]
    person_scores: pd.DataFrame
    person_summary: pd.DataFrame
    adaptation: pd.DataFrame
    adaptation_problem: str
    sample: dict[str, Any]

    @property
    def colors(self) -> dict[str, str]:
        """One colour per condition of the protocol, by its place there, so every figure of the
        study (and of any other study with the same conditions) gives a condition the same
        colour, whichever conditions have participants."""
        return condition_colors([c["code"] for c in self.dataset.protocol["conditions"]])

    def outcome(self, key: str) -> OutcomeAnalysis:
        """The outcome with this item key or scale name."""
        for outcome in self.outcomes:
            if outcome.key == key:
                return outcome
        raise InvalidInputError(f"no outcome {key!r}; have {[o.key for o in self.outcomes]}")

    def exclusions(self) -> pd.DataFrame:
        """Every exclusion: by status (``analysis`` = "all") and per outcome (incomplete data)."""
        frames = []
        if len(self.status_exclusions):
            status = self.status_exclusions.assign(analysis="all")
            frames.append(status[list(EXCLUSION_LIST_COLUMNS)])
        for outcome in self.outcomes:
            if outcome.anova is not None and len(outcome.anova.excluded):
                excluded = outcome.anova.excluded
                frames.append(
                    pd.DataFrame(
                        {
                            "participant": excluded["subject"],
                            "condition": excluded["between"],
                            "analysis": outcome.key,
                            "reason": excluded["reason"],
                        }
                    )
                )
        if not frames:
            return pd.DataFrame(columns=list(EXCLUSION_LIST_COLUMNS))
        return pd.concat(frames, ignore_index=True)


def analyse_study(
    dataset: StudyDataset, *, ss_type: SSType = 3, confidence: float = 0.95
) -> StudyAnalysis:
    """Run the complete analysis of a study.

    Parameters
    ----------
    dataset : StudyDataset
    ss_type : {3, 2}
        Sums of squares of every mixed ANOVA (default type III).
    confidence : float
        Coverage of every confidence interval.

    Returns
    -------
    StudyAnalysis

    Raises
    ------
    InvalidInputError
        The responses do not match the instrument specifications (see
        :func:`analysis.scoring.validate_responses`).

    Notes
    -----
    Exclusions: participants whose status is in ``dataset.excluded_statuses`` are left out of
    everything; for each outcome, participants without a value for every session
    (1..``protocol["sessions"]``) are left out of that outcome's ANOVA, with the reason.
    Every ANOVA p value is computed from its F and degrees of freedom.
    """
    if ss_type not in (2, 3):
        raise InvalidInputError(f"ss_type must be 2 or 3, got {ss_type!r}")
    if not 0 < confidence < 1:
        raise InvalidInputError(f"confidence must be between 0 and 1, got {confidence!r}")
    participants = dataset.participants
    excluded_mask = participants["status"].isin(dataset.excluded_statuses).to_numpy()
    status_exclusions = pd.DataFrame(
        {
            "participant": participants.loc[excluded_mask, "participant"].to_numpy(),
            "condition": participants.loc[excluded_mask, "condition"].to_numpy(),
            "status": participants.loc[excluded_mask, "status"].to_numpy(),
        }
    )
    status_exclusions["reason"] = "status: " + status_exclusions["status"].astype(str)
    analysed = participants.loc[~excluded_mask].reset_index(drop=True)
    condition_of = pd.Series(
        analysed["condition"].to_numpy(), index=analysed["participant"].to_numpy()
    )

    # Factorise the repeated string keys once; every later groupby then works on codes.
    responses = _as_categories(dataset.responses, ("participant", "instrument", "item"))
    responses = responses[responses["participant"].isin(condition_of.index)]
    scored = score_responses(responses, dataset.instruments)
    scored["condition"] = scored["participant"].map(condition_of).to_numpy()
    scale_scores = score_scales(responses, dataset.scales)
    scale_scores["condition"] = scale_scores["participant"].map(condition_of).to_numpy()

    sessions = list(range(1, dataset.protocol["sessions"] + 1))
    outcomes = [
        *_item_outcomes(dataset, scored, sessions, ss_type, confidence),
        *_scale_outcomes(dataset, scale_scores, sessions, ss_type, confidence),
    ]

    per_session = {i.name for i in dataset.instruments if i.per_session}
    once = {s.name for s in dataset.scales if s.instrument not in per_session}
    person_scores = scale_scores[scale_scores["scale"].isin(once)][
        ["participant", "condition", "scale", "score"]
    ].reset_index(drop=True)
    person_summary = (
        person_scores.groupby(["scale", "condition"], sort=False)["score"]
        .agg(n="count", mean="mean", sd="std")
        .reset_index()
    )

    curves, adaptation_problem = _adaptation(dataset, condition_of, confidence)
    return StudyAnalysis(
        dataset=dataset,
        ss_type=ss_type,
        confidence=confidence,
        participants=analysed,
        status_exclusions=status_exclusions,
        scored=scored,
        scale_scores=scale_scores,
        outcomes=tuple(outcomes),
        person_scores=person_scores,
        person_summary=person_summary,
        adaptation=curves,
        adaptation_problem=adaptation_problem,
        sample=_sample(dataset, analysed, scored),
    )


def _item_outcomes(
    dataset: StudyDataset,
    scored: pd.DataFrame,
    sessions: list[int],
    ss_type: SSType,
    confidence: float,
) -> list[OutcomeAnalysis]:
    out = []
    per_session = scored[scored["session"].notna()]
    by_item = dict(tuple(per_session.groupby("item", sort=False)))
    for spec in dataset.instruments:
        if not spec.per_session:
            continue
        for item in spec.items:
            if item.kind not in ("likert", "numeric"):
                continue
            rows = by_item.get(item.key)
            if rows is None:
                continue
            data = pd.DataFrame(
                {
                    "participant": rows["participant"].reset_index(drop=True),
                    "condition": rows["condition"].to_numpy(),
                    "session": rows["session"].to_numpy(dtype="int64"),
                    "value": rows["scored"].to_numpy(float),
                }
            )
            value_range = (
                (float(item.minimum), float(item.maximum))
                if item.minimum is not None and item.maximum is not None
                else None
            )
            out.append(
                _outcome(
                    key=item.key,
                    label=item.text,
                    instrument=spec.name,
                    kind="item",
                    value_range=value_range,
                    reverse_keyed=item.reverse,
                    data=data,
                    sessions=sessions,
                    ss_type=ss_type,
                    confidence=confidence,
                )
            )
    return out


def _scale_outcomes(
    dataset: StudyDataset,
    scale_scores: pd.DataFrame,
    sessions: list[int],
    ss_type: SSType,
    confidence: float,
) -> list[OutcomeAnalysis]:
    out = []
    per_session = {i.name for i in dataset.instruments if i.per_session}
    for scale in dataset.scales:
        if scale.instrument not in per_session:
            continue
        rows = scale_scores[scale_scores["scale"] == scale.name]
        if rows.empty:
            continue
        data = pd.DataFrame(
            {
                "participant": rows["participant"].to_numpy(),
                "condition": rows["condition"].to_numpy(),
                "session": rows["session"].to_numpy(dtype="int64"),
                "value": rows["score"].to_numpy(float),
            }
        )
        out.append(
            _outcome(
                key=scale.name,
                label=scale.label or scale.name,
                instrument=scale.instrument,
                kind="scale",
                value_range=scale.score_range,
                reverse_keyed=False,
                data=data,
                sessions=sessions,
                ss_type=ss_type,
                confidence=confidence,
            )
        )
    return out


def _outcome(
    *,
    key: str,
    label: str,
    instrument: str,
    kind: Literal["item", "scale"],
    value_range: tuple[float, float] | None,
    reverse_keyed: bool,
    data: pd.DataFrame,
    sessions: list[int],
    ss_type: SSType,
    confidence: float,
) -> OutcomeAnalysis:
    # Name the dependent variable after the outcome so exclusion reasons and tables say
    # "no trust_1 value for session 3" rather than a generic column name.
    dv = key if key not in ("participant", "condition", "session") else "value"
    frame = data.rename(columns={"value": dv})
    kw = {"dv": dv, "within": "session", "between": "condition"}
    anova = None
    problem = ""
    extras: dict[str, pd.DataFrame | None] = {
        "marginal_conditions": None,
        "marginal_sessions": None,
        "posthoc": None,
        "sentences": None,
    }
    try:
        design = prepare_mixed_design(frame, **kw, subject="participant", within_levels=sessions)
        anova = mixed_anova_from_design(design, ss_type=ss_type)
        descriptives = cell_descriptives(design.long(), **kw, confidence=confidence)
        extras = {
            "marginal_conditions": marginal_means_from_design(design, confidence=confidence),
            "marginal_sessions": marginal_means_from_design(
                design, by="within", confidence=confidence
            ),
            "posthoc": pairwise_comparisons_from_design(design),
            "sentences": anova_sentences(anova),
        }
    except AnalysisError as error:
        problem = str(error)
        try:
            descriptives = cell_descriptives(frame, **kw, confidence=confidence)
        except AnalysisError:
            descriptives = pd.DataFrame(columns=["condition", "session", *CELL_COLUMNS])
    return OutcomeAnalysis(
        key=key,
        label=label,
        instrument=instrument,
        kind=kind,
        value_range=value_range,
        reverse_keyed=reverse_keyed,
        data=data,
        anova=anova,
        problem=problem,
        descriptives=descriptives,
        **extras,
    )


def _as_categories(frame: pd.DataFrame, columns: tuple[str, ...]) -> pd.DataFrame:
    """Copy of ``frame`` with ``columns`` as categoricals (same values, faster grouping)."""
    converted = {c: frame[c].astype("category") for c in columns if c in frame.columns}
    return frame.assign(**converted)


def _adaptation(
    dataset: StudyDataset, condition_of: pd.Series, confidence: float
) -> tuple[pd.DataFrame, str]:
    if dataset.steps_withheld:
        return pd.DataFrame(columns=list(CURVE_COLUMNS)), dataset.steps_withheld
    steps = _as_categories(dataset.steps, ("participant", "category"))
    steps = steps[steps["participant"].isin(condition_of.index)]
    if steps.empty:
        return pd.DataFrame(columns=list(CURVE_COLUMNS)), ""
    steps = steps.assign(condition=steps["participant"].map(condition_of).to_numpy())
    try:
        curves = adaptation_curves(steps, dataset.protocol["preferred_arms"], confidence=confidence)
    except AnalysisError as error:
        return pd.DataFrame(columns=list(CURVE_COLUMNS)), str(error)
    return curves, ""


def _sample(dataset: StudyDataset, analysed: pd.DataFrame, scored: pd.DataFrame) -> dict[str, Any]:
    sample: dict[str, Any] = {
        "n": len(analysed),
        "by_condition": {
            str(k): int(v) for k, v in analysed["condition"].value_counts(sort=False).items()
        },
    }
    demo = scored[scored["instrument"] == "demographics"]
    ages = pd.to_numeric(demo.loc[demo["item"] == "age", "value"], errors="coerce").dropna()
    if len(ages):
        sample["age"] = {
            "n": len(ages),
            "mean": float(ages.mean()),
            "sd": float(ages.std()) if len(ages) > 1 else float("nan"),
            "min": float(ages.min()),
            "max": float(ages.max()),
        }
    genders = demo.loc[demo["item"] == "gender", "value"].dropna()
    if len(genders):
        labels: dict[Any, str] = {}
        for spec in dataset.instruments:
            if spec.name == "demographics" and "gender" in spec.item_keys:
                labels = dict(spec.item("gender").value_labels)
        counts: dict[str, int] = {}
        for value in genders:
            code: Any = value
            if isinstance(value, (float, np.floating)) and float(value).is_integer():
                code = int(value)
            label = labels.get(code, str(value))
            counts[label] = counts.get(label, 0) + 1
        sample["gender"] = counts
    return sample
