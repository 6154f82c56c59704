"""The export tables: long answers, one row per participant, and the step log.

Each builder returns a DataFrame; :mod:`analysis.exports.files` writes them. The wide table's
column names are valid in SPSS, JASP and R, and its repeated measures follow the
``<item>_s<session>`` convention (``trust_1_s1`` … ``trust_1_s4``) that JASP's repeated-measures
ANOVA dialog and SPSS's GLM expect.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import pandas as pd

from analysis.adaptation import probability_matrix
from analysis.adaptation_trust import MEASURE_COLUMNS, session_adaptation
from analysis.dataset import PARTICIPANT_COLUMNS, StudyDataset
from analysis.exports.names import session_column, spss_name
from analysis.scoring import score_responses, score_scales

__all__ = [
    "ADAPTATION_BASE_COLUMNS",
    "LONG_COLUMNS",
    "STEP_EXPORT_BASE_COLUMNS",
    "WideColumn",
    "adaptation_trust_table",
    "long_table",
    "steps_columns",
    "steps_table",
    "wide_columns",
    "wide_table",
    "with_attributes",
]

LONG_COLUMNS = ("participant", "condition", "instrument", "session", "item", "value", "scored")
"""Columns of :func:`long_table`."""

STEP_EXPORT_BASE_COLUMNS = (
    "participant",
    "condition",
    "category",
    "session",
    "run",
    "iteration",
    "action",
    "answer",
    "reward",
    "preferred_arm",
    "p_preferred_before",
    "p_preferred_after",
)
"""Columns of :func:`steps_table` before the per-arm probabilities ``p_before_<arm>`` /
``p_after_<arm>`` (0-based arm index, like ``action``)."""

ANSWER_COLUMNS = ("modality", "transcript", "transcript_confidence", "transcript_engine")
"""How each answer was given, when the step log has it (trustlab's does; a step log from
elsewhere may not): ``key``, ``button``, ``speech`` or ``wizard``; for spoken answers the words
the recogniser heard, its confidence and which recogniser it was. They follow the probabilities
of the preferred question in the steps table."""

LANGUAGE = "language"
SITE = "site"
ROW_ATTRIBUTES = (LANGUAGE, SITE)
"""Participant attributes that also go into every long and steps row, right after the
condition, when the dataset has them: the language (trustlab's exports always have it: a
multi-language study is analysed by language, and a row should say which words the participant
was given) and the site of a multi-site study (analysed by site, or filtered to one)."""


def steps_columns(dataset: StudyDataset) -> tuple[str, ...]:
    """The steps table's columns before the per-arm probabilities, for this dataset."""
    base = with_attributes(STEP_EXPORT_BASE_COLUMNS, dataset)
    if all(column in dataset.steps.columns for column in ANSWER_COLUMNS):
        base = (*base, *ANSWER_COLUMNS)
    return base


def with_attributes(columns: tuple[str, ...], dataset: StudyDataset) -> tuple[str, ...]:
    """``columns`` with ``language`` and ``site`` after ``condition``, each when the
    participants carry it (:data:`ROW_ATTRIBUTES`)."""
    present = tuple(a for a in ROW_ATTRIBUTES if a in dataset.attribute_columns)
    at = columns.index("condition") + 1
    return (*columns[:at], *present, *columns[at:])


def _per_participant(dataset: StudyDataset, column: str) -> pd.Series:
    return pd.Series(
        dataset.participants[column].to_numpy(),
        index=dataset.participants["participant"].to_numpy(),
    )


ADAPTATION_BASE_COLUMNS = MEASURE_COLUMNS
"""Columns of :func:`adaptation_trust_table` before the reply-level shares and the ratings."""


@dataclass(frozen=True)
class WideColumn:
    """What one column of the wide table holds (the codebook is generated from these).

    ``source`` is ``"participant"`` (code, condition, status, attributes), ``"raw"`` (an
    answer), ``"reversed"`` (a reverse-keyed answer after scoring), or ``"scale"`` (a score).
    """

    name: str
    source: Literal["participant", "raw", "reversed", "scale"]
    key: str
    instrument: str = ""
    session: int | None = None


def _sessions(dataset: StudyDataset) -> list[int]:
    declared = set(range(1, dataset.protocol["sessions"] + 1))
    observed = {int(s) for s in dataset.responses["session"].dropna().unique()}
    return sorted(declared | observed)


def _attribute_names(dataset: StudyDataset) -> dict[str, str]:
    """Each participant attribute's column name: SPSS-safe, and never one of the answers' or
    scores' columns (a stratification factor ``gender`` beside the item ``gender`` becomes
    ``gender_2``, rather than one of the two being lost)."""
    taken = set(PARTICIPANT_COLUMNS) | {column.name for column in _measure_columns(dataset)}
    names = {}
    for column in dataset.attribute_columns:
        name = spss_name(str(column), taken)
        taken.add(name)
        names[column] = name
    return names


def wide_columns(dataset: StudyDataset) -> list[WideColumn]:
    """The wide table's columns in order, with what each holds."""
    columns = [WideColumn(c, "participant", c) for c in PARTICIPANT_COLUMNS]
    columns += [WideColumn(n, "participant", c) for c, n in _attribute_names(dataset).items()]
    return columns + _measure_columns(dataset)


def _measure_columns(dataset: StudyDataset) -> list[WideColumn]:
    """The wide table's answer and score columns, in order."""
    columns: list[WideColumn] = []
    sessions = _sessions(dataset)
    for spec in dataset.instruments:
        for source in ("raw", "reversed"):
            for item in spec.items:
                if source == "reversed" and not item.reverse:
                    continue
                base = item.key if source == "raw" else f"{item.key}_r"
                if spec.per_session:
                    columns += [
                        WideColumn(session_column(base, s), source, item.key, spec.name, s)
                        for s in sessions
                    ]
                else:
                    columns.append(WideColumn(base, source, item.key, spec.name))
    per_session = {i.name for i in dataset.instruments if i.per_session}
    for scale in dataset.scales:
        if scale.instrument in per_session:
            columns += [
                WideColumn(session_column(scale.name, s), "scale", scale.name, scale.instrument, s)
                for s in sessions
            ]
        else:
            columns.append(WideColumn(scale.name, "scale", scale.name, scale.instrument))
    return columns


def long_table(dataset: StudyDataset) -> pd.DataFrame:
    """Every stored answer, raw and scored: one row per participant × instrument × session × item.

    Columns :data:`LONG_COLUMNS` (with ``language`` after ``condition`` when the participants
    have one: :func:`with_attributes`). ``scored`` applies the reverse key (e.g. ``trust_5``: 6 − x)
    and is empty for categorical and free-text items. Rows are ordered by participant (as in
    the participants table), then session (once-only instruments first), then instrument and
    item in questionnaire order.
    """
    scored = score_responses(dataset.responses, dataset.instruments)
    condition = pd.Series(
        dataset.participants["condition"].to_numpy(),
        index=dataset.participants["participant"].to_numpy(),
    )
    order_keys = {
        (spec.name, item.key): (i, j)
        for i, spec in enumerate(dataset.instruments)
        for j, item in enumerate(spec.items)
    }
    rank = pd.Series(
        [order_keys[(i, k)][0] * 10_000 + order_keys[(i, k)][1] for i, k in order_keys],
        index=pd.MultiIndex.from_tuples(list(order_keys)),
    )
    item_rank = rank.reindex(pd.MultiIndex.from_arrays([scored["instrument"], scored["item"]]))
    participant_rank = pd.Index(dataset.participants["participant"]).get_indexer(
        scored["participant"]
    )
    session = scored["session"].to_numpy(dtype="float64", na_value=-1.0)
    order = np.lexsort((item_rank.to_numpy(), session, participant_rank))
    out = scored.iloc[order].reset_index(drop=True)
    out["condition"] = out["participant"].map(condition).to_numpy()
    columns = with_attributes(LONG_COLUMNS, dataset)
    for attribute in ROW_ATTRIBUTES:
        if attribute in columns:
            out[attribute] = out["participant"].map(_per_participant(dataset, attribute)).to_numpy()
    return out[list(columns)]


def wide_table(dataset: StudyDataset) -> pd.DataFrame:
    """One row per participant: attributes, every answer, reverse-keyed answers and scores.

    Column names (see :func:`wide_columns`): ``participant``, ``condition``, ``status``,
    participant attributes (SPSS-safe names), once-only answers by item key (``tipi_1``),
    per-session answers as ``<item>_s<session>`` (``trust_1_s1``), reverse-keyed answers after
    scoring as ``<item>_r`` / ``<item>_r_s<session>`` (``trust_5_r_s1``), and scale scores by
    scale name (``tipi_extraversion``, ``nars_s1_sum``). Every declared item and session has a
    column even when nobody answered it, so files of the same protocol line up.
    """
    participants = dataset.participants.reset_index(drop=True)
    attributes = _attribute_names(dataset)
    columns = wide_columns(dataset)
    n = len(participants)
    scored = score_responses(dataset.responses, dataset.instruments)
    row = pd.Index(participants["participant"]).get_indexer(scored["participant"])
    session = scored["session"].to_numpy(dtype="float64", na_value=0.0).astype(np.int64)

    cells: dict[tuple[str, str, int], np.ndarray] = {}
    key_codes, keys = pd.factorize(scored["item"])
    combo = key_codes.astype(np.int64) * 10_000 + session
    order = np.argsort(combo, kind="stable")
    uniq, starts = np.unique(combo[order], return_index=True)
    raw = scored["value"].to_numpy(dtype=object)
    scored_values = scored["scored"].to_numpy(dtype=float)
    members = np.split(order, starts[1:]) if len(order) else []  # no answers yet: no groups
    for code, member in zip(uniq, members, strict=True):
        key, sess = str(keys[code // 10_000]), int(code % 10_000)
        cells[("raw", key, sess)] = _column(n, row[member], raw[member])
        cells[("reversed", key, sess)] = _column(n, row[member], scored_values[member])

    scores = score_scales(dataset.responses, dataset.scales)
    score_row = pd.Index(participants["participant"]).get_indexer(scores["participant"])
    score_session = scores["session"].to_numpy(dtype="float64", na_value=0.0).astype(np.int64)
    for (name, sess), idx in scores.groupby(
        [scores["scale"].to_numpy(), score_session], sort=False
    ).indices.items():
        cells[("scale", str(name), int(sess))] = _column(
            n, score_row[idx], scores["score"].to_numpy(float)[idx]
        )

    kinds = {
        (spec.name, item.key): item.kind for spec in dataset.instruments for item in spec.items
    }
    data: dict[str, Any] = {}
    for column in columns:
        if column.source == "participant":
            source = next((c for c, name in attributes.items() if name == column.name), column.key)
            data[column.name] = participants[source].to_numpy()
            continue
        values = cells.get((column.source, column.key, column.session or 0))
        kind = "numeric" if column.source != "raw" else kinds[(column.instrument, column.key)]
        if values is None:
            values = np.full(n, None, dtype=object)
        data[column.name] = _as_column(values, kind)
    return pd.DataFrame(data)


def _column(n: int, rows: np.ndarray, values: np.ndarray) -> np.ndarray:
    out = np.full(n, None, dtype=object) if values.dtype == object else np.full(n, np.nan)
    out[rows] = values
    return out


def _as_column(values: np.ndarray, kind: str) -> Any:
    """Numbers for numeric items and scores, codes as numbers when they all are, text as str."""
    series = pd.Series(values, dtype=object)
    if kind in ("likert", "numeric"):
        return pd.to_numeric(series, errors="coerce").to_numpy(float)
    if kind == "categorical":
        converted = pd.to_numeric(series, errors="coerce")
        if converted.notna().sum() == series.notna().sum():
            return converted.to_numpy(float)
    return np.array([None if pd.isna(v) else str(v) for v in values], dtype=object)


def steps_table(dataset: StudyDataset) -> pd.DataFrame:
    """The adaptation step log with one column per arm probability.

    Columns :data:`STEP_EXPORT_BASE_COLUMNS` (with ``language`` after ``condition`` when the
    participants have one, and :data:`ANSWER_COLUMNS` at their end when the log has them),
    then ``p_before_0`` … ``p_before_<K−1>`` and
    ``p_after_0`` … (K = the largest number of arms; categories with fewer arms leave the rest
    empty). ``preferred_arm`` is the protocol's preferred question of the row's category and
    ``p_preferred_before/after`` its probability. Rows are ordered by participant (as in the
    participants table), category (protocol order) and iteration; ``condition`` is taken from
    the participants table.
    """
    steps = dataset.steps
    preferred = dataset.protocol["preferred_arms"]
    base = steps_columns(dataset)
    if steps.empty:
        return pd.DataFrame(columns=list(base))
    participant_rank = pd.Index(dataset.participants["participant"]).get_indexer(
        steps["participant"]
    )
    category_rank = pd.Index(list(preferred)).get_indexer(steps["category"])
    order = np.lexsort((steps["iteration"].to_numpy(), category_rank, participant_rank))
    steps = steps.iloc[order].reset_index(drop=True)
    condition = pd.Series(
        dataset.participants["condition"].to_numpy(),
        index=dataset.participants["participant"].to_numpy(),
    )
    out = pd.DataFrame(
        {
            "participant": steps["participant"].to_numpy(),
            "condition": steps["participant"].map(condition).to_numpy(),
            "category": steps["category"].to_numpy(),
            "session": steps["session"].to_numpy(),
            "run": steps["run"].to_numpy(),
            "iteration": steps["iteration"].to_numpy(),
            "action": steps["action"].to_numpy(),
            "answer": steps["answer"].astype(bool).astype(int).to_numpy(),
            "reward": steps["reward"].to_numpy(),
            "preferred_arm": steps["category"].map(preferred).to_numpy(),
        }
    )
    blocks = []
    categories = steps["category"].to_numpy()
    for category in pd.unique(categories):
        rows = np.flatnonzero(categories == category)
        before = probability_matrix(steps["probs_before"].to_numpy()[rows], "probs_before")
        after = probability_matrix(steps["probs_after"].to_numpy()[rows], "probs_after")
        blocks.append((rows, before, after))
    n_arms = max(before.shape[1] for _, before, _ in blocks)
    at = 2
    for attribute in ROW_ATTRIBUTES:
        if attribute in base:
            per = _per_participant(dataset, attribute)
            out.insert(at, attribute, steps["participant"].map(per))
            at += 1
    p_before = np.full((len(steps), n_arms), np.nan)
    p_after = np.full((len(steps), n_arms), np.nan)
    for rows, before, after in blocks:
        p_before[rows, : before.shape[1]] = before
        p_after[rows, : after.shape[1]] = after
    arm = out["preferred_arm"].to_numpy(dtype=np.int64)
    out["p_preferred_before"] = p_before[np.arange(len(steps)), arm]
    out["p_preferred_after"] = p_after[np.arange(len(steps)), arm]
    for column in ANSWER_COLUMNS if ANSWER_COLUMNS[0] in base else ():
        out[column] = steps[column].to_numpy()
    for j in range(n_arms):
        out[f"p_before_{j}"] = p_before[:, j]
    for j in range(n_arms):
        out[f"p_after_{j}"] = p_after[:, j]
    return out


def adaptation_trust_table(dataset: StudyDataset) -> pd.DataFrame:
    """Per participant × session: the adaptation measures and that session's trust ratings.

    The data of the adaptation-and-trust models (:mod:`analysis.adaptation_trust`), for
    re-analysis elsewhere: :data:`ADAPTATION_BASE_COLUMNS`, ``share_<level>`` per reply level,
    then every per-session item (scored: reverse keys applied) and per-session scale. One row
    per participant × session with adaptation steps; empty (with its base columns) when the step
    log is empty or withheld.
    """
    steps = dataset.steps
    if steps.empty:
        return pd.DataFrame(columns=list(ADAPTATION_BASE_COLUMNS))
    condition = pd.Series(
        dataset.participants["condition"].to_numpy(),
        index=dataset.participants["participant"].to_numpy(),
    )
    steps = steps.assign(condition=steps["participant"].map(condition).to_numpy())
    table = session_adaptation(
        steps, dataset.protocol["preferred_arms"], reply_levels=dataset.protocol.get("reply_levels")
    )
    shares = [f"share_{level}" for level in dataset.protocol.get("reply_levels", [])]
    table = table[[*ADAPTATION_BASE_COLUMNS, *[c for c in shares if c in table.columns]]]
    per_session = [spec for spec in dataset.instruments if spec.per_session]
    names = {spec.name for spec in per_session}
    responses = dataset.responses[dataset.responses["instrument"].isin(names)]
    ratings = []
    if len(responses):
        scored = score_responses(responses, per_session)
        numeric = scored[scored["scored"].notna() & scored["session"].notna()]
        ratings.append(
            numeric.pivot_table(
                index=["participant", "session"], columns="item", values="scored", aggfunc="first"
            )
        )
        scales = [s for s in dataset.scales if s.instrument in names]
        if scales:
            scores = score_scales(responses, scales)
            ratings.append(
                scores.pivot_table(
                    index=["participant", "session"],
                    columns="scale",
                    values="score",
                    aggfunc="first",
                )
            )
    if ratings:
        wide = pd.concat(ratings, axis=1).reset_index()
        wide["session"] = wide["session"].astype("int64")
        wide.columns = [str(c) for c in wide.columns]
        keys = [item.key for spec in per_session for item in spec.items]
        keys += [s.name for s in dataset.scales if s.instrument in names]
        wide = wide[["participant", "session", *[k for k in keys if k in wide.columns]]]
        table = table.merge(wide, on=["participant", "session"], how="left")
    order = pd.Index(dataset.participants["participant"]).get_indexer(table["participant"])
    return table.iloc[np.lexsort((table["session"].to_numpy(), order))].reset_index(drop=True)
