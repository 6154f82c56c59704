"""Does a participant's trust follow how well the robot adapted to them? (the paper's H2/H4)

The ANOVA compares conditions; this module asks the mechanism question directly. For every
participant × session it summarises the step log — how confident the robot sounded, how likely
the learner thought the questions the participant said yes to, how often each reply level was
heard, how many answers the learner needed to be 95 % sure of the preferred question — joins that
to the session's trust ratings, and fits a linear mixed model of trust on each measure with the
measure split by person-mean centring (Enders & Tofighi 2007; Curran & Bauer 2011):

* ``<measure>_within``: the session's value minus the participant's own mean — does trust rise in
  the sessions where *this* participant's robot was more confident than usual for them?
* ``<measure>_between``: the participant's mean minus the grand mean — do participants whose
  robot was more confident overall trust it more?

Without the split the two questions are mixed into one uninterpretable slope.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd

from analysis._checks import json_records, require_columns, to_python
from analysis.adaptation import probability_matrix, validate_steps
from analysis.errors import AnalysisError, CannotComputeError, InvalidInputError

if TYPE_CHECKING:
    from analysis.lmm import MixedModelFit

__all__ = [
    "EFFECT_COLUMNS",
    "MEASURES",
    "MEASURE_COLUMNS",
    "TARGET",
    "AdaptationTrust",
    "adaptation_trust",
    "session_adaptation",
]

TARGET = 0.95
"""The preferred question's probability that counts as "learned" (the paper's objective measure)."""

MEASURES: dict[str, str] = {
    "confidence": "the robot's confidence (probability behind its reply)",
    "p_accepted": "probability of the questions answered yes",
    "share_top": "share of replies at the most confident level",
    "answers_to_95": "answers until the preferred question reached .95",
}
"""Measures modelled, with the words readers see. ``answers_to_95`` is a property of the
participant (it does not vary by session), so only its between part is modelled."""

MEASURE_COLUMNS = (
    "participant",
    "condition",
    "session",
    "n_answers",
    "confidence",
    "p_accepted",
    "answers_to_95",
)
"""Columns of :func:`session_adaptation` before the reply-level shares."""

EFFECT_COLUMNS = (
    "measure",
    "part",
    "estimate",
    "se",
    "df",
    "t",
    "p",
    "ci_low",
    "ci_high",
    "n_obs",
    "n_subjects",
    "status",
)
"""Columns of :attr:`AdaptationTrust.effects`: one row per measure × part (within/between)."""


def session_adaptation(
    steps: pd.DataFrame,
    preferred_arms: Mapping[str, int],
    *,
    reply_levels: Sequence[str] | None = None,
    target: float = TARGET,
) -> pd.DataFrame:
    """Per participant × session adaptation measures from the step log.

    Parameters
    ----------
    steps : pandas.DataFrame
        Step log (:data:`analysis.adaptation.STEP_COLUMNS`); optional columns
        ``reply_probability`` (the probability the reply was chosen by) and ``reply_level`` (its
        level index) as the server recorded them.
    preferred_arms : mapping
        Preferred arm of each category.
    reply_levels : sequence of str, optional
        Names of the reply levels in order (low … high); with ``reply_level`` in ``steps``, one
        ``share_<name>`` column each, and ``share_top`` for the last.
    target : float
        Probability of the preferred question that counts as learned.

    Returns
    -------
    pandas.DataFrame
        ``participant``, ``condition``, ``session``, ``n_answers``, ``confidence`` (mean reply
        probability; without ``reply_probability`` the probability the asked question had before
        the answer, the protocol's default basis), ``p_accepted`` (mean probability of the asked
        questions answered yes; NaN in a session without a yes), ``answers_to_95`` (per
        participant: mean over categories of the answers until the preferred question's
        probability first reached ``target``; answers + 1 when it never did), and the shares.

    Notes
    -----
    Familiarisation steps are not in the step log (they do not adapt), so they never count.
    """
    steps = validate_steps(steps, preferred_arms)
    if steps.empty:
        return pd.DataFrame(columns=list(MEASURE_COLUMNS))
    actions = steps["action"].to_numpy(dtype=np.int64)
    asked = np.empty(len(steps))
    for category in pd.unique(steps["category"]):
        rows = np.flatnonzero(steps["category"].to_numpy() == category)
        before = probability_matrix(steps["probs_before"].to_numpy()[rows], "probs_before")
        asked[rows] = before[np.arange(len(rows)), actions[rows]]
    if "reply_probability" in steps.columns and steps["reply_probability"].notna().all():
        confidence = steps["reply_probability"].to_numpy(float)
    else:
        confidence = asked
    yes = steps["answer"].astype(bool).to_numpy()
    frame = pd.DataFrame(
        {
            "participant": steps["participant"].to_numpy(),
            "condition": steps["condition"].to_numpy(),
            "session": steps["session"].to_numpy(),
            "confidence": confidence,
            "accepted": np.where(yes, asked, np.nan),
        }
    )
    keys = ["participant", "condition", "session"]
    grouped = frame.groupby(keys, sort=True)
    out = grouped.agg(
        n_answers=("confidence", "size"),
        confidence=("confidence", "mean"),
        p_accepted=("accepted", "mean"),
    ).reset_index()
    if reply_levels and "reply_level" in steps.columns:
        level = pd.to_numeric(steps["reply_level"], errors="coerce").to_numpy(float)
        for index, name in enumerate(reply_levels):
            frame[f"share_{name}"] = (level == index).astype(float)
        shares = frame.groupby(keys, sort=True)[[f"share_{n}" for n in reply_levels]].mean()
        out = out.merge(shares.reset_index(), on=keys)
        out["share_top"] = out[f"share_{reply_levels[-1]}"]
    learned = _answers_to_target(steps, preferred_arms, target)
    out["answers_to_95"] = out["participant"].map(learned).to_numpy(float)
    return out


def _answers_to_target(
    steps: pd.DataFrame, preferred_arms: Mapping[str, int], target: float
) -> pd.Series:
    """Per participant: mean over categories of the first answer after which the preferred
    question's probability was ≥ target (the number of answers + 1 when never)."""
    values = []
    for (participant, category), rows in steps.groupby(["participant", "category"], sort=False):
        after = probability_matrix(rows["probs_after"].to_numpy(), "probs_after")
        p = after[:, preferred_arms[category]]
        hit = np.flatnonzero(p >= target)
        values.append((participant, float(hit[0] + 1) if len(hit) else float(len(p) + 1)))
    frame = pd.DataFrame(values, columns=["participant", "answers"])
    return frame.groupby("participant")["answers"].mean()


@dataclass(frozen=True)
class AdaptationTrust:
    """Result of :func:`adaptation_trust` for one trust measure.

    Attributes
    ----------
    dv : str
        The trust measure (item key or scale name).
    data : pandas.DataFrame
        The joined per participant × session rows: ``participant``, ``condition``, ``session``,
        the trust value ``dv``, the measures and their ``_within`` / ``_between`` parts.
    effects : pandas.DataFrame
        :data:`EFFECT_COLUMNS`: the within and between slopes of every measure (per unit of the
        measure: a probability from 0 to 1, a share, or one answer), Satterthwaite df.
    fits : dict
        Measure → the :class:`analysis.lmm.MixedModelFit` it came from.
    problems : dict
        Measure → why it has no model (too little variation, no convergence…).
    """

    dv: str
    data: pd.DataFrame
    effects: pd.DataFrame
    fits: dict[str, MixedModelFit]
    problems: dict[str, str]

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready (NaN → None)."""
        return {
            "dv": self.dv,
            "effects": json_records(self.effects),
            "problems": dict(self.problems),
        }


def adaptation_trust(
    measures: pd.DataFrame,
    trust: pd.DataFrame,
    *,
    dv: str,
    confidence: float = 0.95,
) -> AdaptationTrust:
    """Mixed models of a trust measure on each adaptation measure, within and between.

    Parameters
    ----------
    measures : pandas.DataFrame
        :func:`session_adaptation` output.
    trust : pandas.DataFrame
        ``participant``, ``condition``, ``session`` and the rating column ``dv``.
    dv : str
        The trust column.
    confidence : float
        Coverage of the CIs.

    Returns
    -------
    AdaptationTrust

    Notes
    -----
    Model per measure ``x``: ``dv ~ condition + session + x_within + x_between + (1 |
    participant)`` with ``session`` a factor, so the slopes are not confounded with the learning
    that happens over sessions in both conditions. Only rows with both a rating and the measure
    are used; a participant with one such session contributes to the between part only.
    """
    require_columns(trust, ["participant", "condition", "session", dv], "trust")
    require_columns(measures, ["participant", "session"], "adaptation measures")
    if dv in measures.columns:
        raise InvalidInputError(f"the trust column {dv!r} clashes with an adaptation measure")
    keys = ["participant", "session"]
    joined = trust[["participant", "condition", "session", dv]].merge(
        measures.drop(columns=["condition"], errors="ignore"), on=keys, how="inner"
    )
    joined = joined[joined[dv].notna()].reset_index(drop=True)
    effects: list[dict[str, Any]] = []
    fits: dict[str, MixedModelFit] = {}
    problems: dict[str, str] = {}
    for measure in MEASURES:
        if measure not in joined.columns:
            continue
        rows = joined[joined[measure].notna()].copy()
        person_mean = rows.groupby("participant")[measure].transform("mean")
        rows[f"{measure}_within"] = rows[measure] - person_mean
        rows[f"{measure}_between"] = person_mean - person_mean.mean()
        joined.loc[rows.index, f"{measure}_within"] = rows[f"{measure}_within"]
        joined.loc[rows.index, f"{measure}_between"] = rows[f"{measure}_between"]
        parts = [p for p in ("within", "between") if rows[f"{measure}_{p}"].std() > 1e-12]
        if measure == "answers_to_95":
            parts = [p for p in parts if p == "between"]
        try:
            if not parts:
                raise CannotComputeError(
                    f"the model of {dv} on {measure}", "the measure does not vary"
                )
            fit = _fit(rows, dv, measure, parts, confidence)
        except AnalysisError as error:
            problems[measure] = str(error)
            continue
        fits[measure] = fit
        if not fit.converged:
            problems[measure] = fit.problem
            continue
        fixed = fit.fixed.set_index("term")
        for part in parts:
            row = fixed.loc[f"{measure}_{part}"]
            effects.append(
                {
                    "measure": measure,
                    "part": part,
                    **{c: row[c] for c in ("estimate", "se", "df", "t", "p", "ci_low", "ci_high")},
                    "n_obs": fit.n_obs,
                    "n_subjects": fit.n_subjects,
                    "status": fit.status,
                }
            )
    return AdaptationTrust(
        dv=dv,
        data=joined,
        effects=pd.DataFrame(effects, columns=list(EFFECT_COLUMNS)),
        fits=fits,
        problems=problems,
    )


def _fit(
    rows: pd.DataFrame, dv: str, measure: str, parts: list[str], confidence: float
) -> MixedModelFit:
    # The mixed model (SciPy, statsmodels) on first use: the adaptation export's tables import
    # this module and fit nothing (trustlab export, issue 49).
    from analysis.lmm import fit_mixed_model

    frame = pd.DataFrame(
        {
            "y": rows[dv].to_numpy(float),
            "participant": rows["participant"].map(to_python).astype(str).to_numpy(),
            "condition": rows["condition"].astype(str).to_numpy(),
            "session": rows["session"].astype(str).to_numpy(),
            **{f"{measure}_{p}": rows[f"{measure}_{p}"].to_numpy(float) for p in parts},
        }
    )
    # (patsy term, what readers see), factors with sum-to-zero coding
    terms = [
        *([("C(condition, Sum)", "condition")] if frame["condition"].nunique() > 1 else []),
        *([("C(session, Sum)", "session")] if frame["session"].nunique() > 1 else []),
        *[(f"{measure}_{p}", f"{measure}_{p}") for p in parts],
    ]
    shown = " + ".join(name for _, name in terms)
    return fit_mixed_model(
        frame,
        formula="y ~ " + " + ".join(term for term, _ in terms),
        subject="participant",
        name=measure,
        display=f"{dv} ~ {shown} + (1 | participant)",
        confidence=confidence,
    )
