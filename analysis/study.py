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
from analysis.design import EXCLUSION_COLUMNS, prepare_mixed_design
from analysis.errors import AnalysisError, InvalidInputError
from analysis.figures import condition_colors
from analysis.posthoc import pairwise_comparisons_from_design
from analysis.scoring import score_responses, score_scales

__all__ = [
    "ALL_ANALYSES",
    "EXCLUSION_LIST_COLUMNS",
    "FLAG_REASON",
    "NO_DATA_REASON",
    "OutcomeAnalysis",
    "StudyAnalysis",
    "analyse_study",
]

EXCLUSION_LIST_COLUMNS = ("participant", "condition", "analysis", "reason")
"""Columns of :meth:`StudyAnalysis.exclusions`."""

ALL_ANALYSES = "all"
"""The ``analysis`` of an exclusion from every analysis (by status, or for having no data)."""

FLAG_REASON = "data quality (protocol's exclusion rule): "
"""How an exclusion by a data-quality flag begins (app/quality.py; the flags follow)."""

NO_DATA_REASON = "no data: no rating in any session and no answer to the robot"
"""Why an enrolled participant with no per-session rating is left out of every analysis (and
of N analysed): there is nothing of theirs to analyse, and counting them would make N say
more people were studied than any table holds."""


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
    excluded : pandas.DataFrame
        ``subject``, ``between``, ``reason`` of every analysed participant the ANOVA of this
        outcome leaves out as incomplete (one with no value of it at all included), whether or
        not the ANOVA could be computed: the report's note, the ANOVA's own count and the
        exclusion list are this one frame.
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
    excluded: pd.DataFrame
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
        Participants analysed: status not excluded, no excluding data-quality flag, and at
        least one per-session rating (when the protocol has per-session measures).
        ``sample["n"]`` ("N analysed") counts them.
    status_exclusions : pandas.DataFrame
        ``participant``, ``condition``, ``status``, ``reason`` of those left out of everything
        by status or by a data-quality flag the protocol excludes (:data:`FLAG_REASON`).
    excluded : pandas.DataFrame
        The one list of exclusions (:data:`EXCLUSION_LIST_COLUMNS`), as :meth:`exclusions`
        gives it.
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
    excluded: pd.DataFrame
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
        """Every exclusion, one row per participant and analysis: from every analysis
        (``analysis`` = :data:`ALL_ANALYSES`: by status, or with no data) and from one outcome's
        ANOVA (incomplete data). The report's methods, its exclusions section, each ANOVA's note
        and N analysed all read this list, so they cannot disagree."""
        return self.excluded


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
    everything, and so are those with a flag in ``dataset.excluded_flags`` and those without a
    single per-session rating or answer to the robot (:data:`NO_DATA_REASON`; when the protocol
    has per-session measures); for each outcome, participants without a value for every session
    (1..``protocol["sessions"]``) are left out of that outcome's ANOVA, with the reason. All of
    them are in :meth:`StudyAnalysis.exclusions`.
    Every ANOVA p value is computed from its F and degrees of freedom.
    """
    if ss_type not in (2, 3):
        raise InvalidInputError(f"ss_type must be 2 or 3, got {ss_type!r}")
    if not 0 < confidence < 1:
        raise InvalidInputError(f"confidence must be between 0 and 1, got {confidence!r}")
    participants = dataset.participants
    by_status = participants["status"].isin(dataset.excluded_statuses).to_numpy()
    flagged = dataset.flagged()
    by_flag = (flagged != "").to_numpy() & ~by_status
    excluded_mask = by_status | by_flag
    status_exclusions = pd.DataFrame(
        {
            "participant": participants.loc[excluded_mask, "participant"].to_numpy(),
            "condition": participants.loc[excluded_mask, "condition"].to_numpy(),
            "status": participants.loc[excluded_mask, "status"].to_numpy(),
            "reason": np.where(
                by_status[excluded_mask],
                "status: " + participants.loc[excluded_mask, "status"].astype(str),
                FLAG_REASON + flagged[excluded_mask].str.replace(";", ", "),
            ),
        }
    )
    analysed = participants.loc[~excluded_mask].reset_index(drop=True)

    # Factorise the repeated string keys once; every later groupby then works on codes.
    responses = _as_categories(dataset.responses, ("participant", "instrument", "item"))
    responses = responses[responses["participant"].isin(set(analysed["participant"]))]
    scored = score_responses(responses, dataset.instruments)
    rated = _with_data(dataset, scored)
    no_data = analysed[~analysed["participant"].isin(rated)] if rated is not None else None
    if no_data is not None and len(no_data):
        analysed = analysed[analysed["participant"].isin(rated)].reset_index(drop=True)
        responses = responses[responses["participant"].isin(rated)]
        scored = scored[scored["participant"].isin(rated)].reset_index(drop=True)
    condition_of = pd.Series(
        analysed["condition"].to_numpy(), index=analysed["participant"].to_numpy()
    )
    scored["condition"] = scored["participant"].map(condition_of).to_numpy()
    scale_scores = score_scales(responses, dataset.scales)
    scale_scores["condition"] = scale_scores["participant"].map(condition_of).to_numpy()

    sessions = list(range(1, dataset.protocol["sessions"] + 1))
    outcomes = [
        *_item_outcomes(dataset, scored, sessions, ss_type, confidence, condition_of),
        *_scale_outcomes(dataset, scale_scores, sessions, ss_type, confidence, condition_of),
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
        excluded=_exclusion_list(status_exclusions, no_data, outcomes),
        scored=scored,
        scale_scores=scale_scores,
        outcomes=tuple(outcomes),
        person_scores=person_scores,
        person_summary=person_summary,
        adaptation=curves,
        adaptation_problem=adaptation_problem,
        sample=_sample(dataset, analysed, scored),
    )


def _with_data(dataset: StudyDataset, scored: pd.DataFrame) -> set[Any] | None:
    """The participants with at least one per-session rating (a value of a Likert or numeric
    item of a per-session instrument) or one answer to the robot (a step: the adaptation curves
    use it), or None when the protocol has no per-session measure (then having no rating says
    nothing about a participant)."""
    measures = {
        item.key
        for spec in dataset.instruments
        if spec.per_session
        for item in spec.items
        if item.is_measure
    }
    if not measures:
        return None
    rows = scored[
        scored["session"].notna() & scored["item"].isin(measures) & scored["scored"].notna()
    ]
    answered = set() if dataset.steps_withheld else set(dataset.steps["participant"])
    return set(rows["participant"]) | answered


def _exclusion_list(
    status: pd.DataFrame, no_data: pd.DataFrame | None, outcomes: list[OutcomeAnalysis]
) -> pd.DataFrame:
    """The one exclusion list (:meth:`StudyAnalysis.exclusions`): status, no data, then each
    outcome's incomplete participants (whether or not its ANOVA could be computed)."""
    frames = []
    if len(status):
        frames.append(status.assign(analysis=ALL_ANALYSES)[list(EXCLUSION_LIST_COLUMNS)])
    if no_data is not None and len(no_data):
        frames.append(
            pd.DataFrame(
                {
                    "participant": no_data["participant"].to_numpy(),
                    "condition": no_data["condition"].to_numpy(),
                    "analysis": ALL_ANALYSES,
                    "reason": NO_DATA_REASON,
                }
            )
        )
    for outcome in outcomes:
        if len(outcome.excluded):
            frames.append(
                pd.DataFrame(
                    {
                        "participant": outcome.excluded["subject"].to_numpy(),
                        "condition": outcome.excluded["between"].to_numpy(),
                        "analysis": outcome.key,
                        "reason": outcome.excluded["reason"].to_numpy(),
                    }
                )
            )
    if not frames:
        return pd.DataFrame(columns=list(EXCLUSION_LIST_COLUMNS))
    return pd.concat(frames, ignore_index=True)


def _item_outcomes(
    dataset: StudyDataset,
    scored: pd.DataFrame,
    sessions: list[int],
    ss_type: SSType,
    confidence: float,
    condition_of: pd.Series,
) -> list[OutcomeAnalysis]:
    out = []
    per_session = scored[scored["session"].notna()]
    by_item = dict(tuple(per_session.groupby("item", sort=False)))
    for spec in dataset.instruments:
        if not spec.per_session:
            continue
        for item in spec.items:
            if not item.is_measure:
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
                    condition_of=condition_of,
                )
            )
    return out


def _scale_outcomes(
    dataset: StudyDataset,
    scale_scores: pd.DataFrame,
    sessions: list[int],
    ss_type: SSType,
    confidence: float,
    condition_of: pd.Series,
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
                condition_of=condition_of,
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
    condition_of: pd.Series,
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
    excluded = pd.DataFrame(columns=list(EXCLUSION_COLUMNS))
    try:
        design = prepare_mixed_design(
            _with_absent(frame, dv, condition_of, sessions[0]),
            **kw,
            subject="participant",
            within_levels=sessions,
        )
        excluded = design.excluded
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
        excluded=excluded,
        **extras,
    )


def _with_absent(
    frame: pd.DataFrame, dv: str, condition_of: pd.Series, session: int
) -> pd.DataFrame:
    """``frame`` with one missing value for each analysed participant who has no value of
    this outcome at all, so the design lists them as incomplete with the sessions they lack
    (and the ANOVA's own count of the incomplete agrees with the exclusion list)."""
    absent = condition_of[~condition_of.index.isin(set(frame["participant"]))]
    if absent.empty:
        return frame
    missing = pd.DataFrame(
        {
            "participant": absent.index.to_numpy(),
            "condition": absent.to_numpy(),
            "session": session,
            dv: np.nan,
        }
    )
    rows = frame.assign(participant=frame["participant"].astype(object))
    return pd.concat([rows, missing], ignore_index=True)


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
