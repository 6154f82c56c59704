"""Scoring questionnaires from the stored raw answers.

Scores are never stored in place of answers: they are recomputed from the long frame of raw
answers every time, with keys given as data (:class:`ScaleSpec`), so a translated or adapted
instrument is scored by changing its specification, not the code.

Long responses frame (what the app builds from its answer table):

============  ===============================================================
participant   participant code (str)
instrument    instrument key, e.g. ``"tipi"``, ``"nars"``, ``"trust"``
session       session number (nullable ``Int64``; NA for once-only instruments)
item          item key, e.g. ``"tipi_1"``, ``"trust_5"``, ``"age"``
value         the raw answer (numeric; categorical items may be codes or strings)
============  ===============================================================
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
import pandas as pd

from analysis._checks import describe_keys, refuse_duplicates, require_columns, to_python
from analysis.errors import InvalidInputError
from analysis.instruments import DEFAULT_INSTRUMENTS, NARS, TIPI, InstrumentSpec

__all__ = [
    "DEFAULT_SCALES",
    "NARS_SUBSCALES",
    "RESPONSE_COLUMNS",
    "SCALE_SCORE_COLUMNS",
    "TIPI_SCALES",
    "ItemKey",
    "ScaleSpec",
    "nars_scales",
    "score_responses",
    "score_scales",
    "validate_responses",
]

ItemKey = str
"""Stored item key, e.g. ``"nars_3"``."""

RESPONSE_COLUMNS = ("participant", "instrument", "session", "item", "value")
"""Columns the long responses frame must have."""

SCALE_SCORE_COLUMNS = (
    "participant",
    "instrument",
    "session",
    "scale",
    "score",
    "n_items",
    "n_answered",
)
"""Columns of :func:`score_scales`."""


@dataclass(frozen=True)
class ScaleSpec:
    """How to score one scale from its items.

    Attributes
    ----------
    name : str
        Score name (a column of the wide export), e.g. ``"tipi_extraversion"``.
    instrument : str
        Instrument key the items belong to.
    items : tuple of str
        Item keys that form the scale.
    reverse : frozenset of str
        Items scored as ``scale_min + scale_max − value`` (8 − x on TIPI, 6 − x on NARS).
    scale_min, scale_max : float
        Response range of every item; answers outside it are refused.
    method : {"mean", "sum"}
        Mean of the (keyed) items, or their sum.
    label : str
        Human-readable name for the codebook and the report.
    citation : str
        Source of the scoring key.
    """

    name: str
    instrument: str
    items: tuple[ItemKey, ...]
    reverse: frozenset[ItemKey]
    scale_min: float
    scale_max: float
    method: Literal["mean", "sum"] = "mean"
    label: str = ""
    citation: str = ""

    def __post_init__(self) -> None:
        if not self.items:
            raise InvalidInputError(f"scale {self.name!r} has no items")
        if len(set(self.items)) != len(self.items):
            raise InvalidInputError(f"scale {self.name!r} lists an item twice: {self.items}")
        stray = sorted(set(self.reverse) - set(self.items))
        if stray:
            raise InvalidInputError(
                f"scale {self.name!r}: reverse-keyed item(s) {stray} are not among its items"
            )
        if not self.scale_min < self.scale_max:
            raise InvalidInputError(f"scale {self.name!r}: scale_min must be below scale_max")
        if self.method not in ("mean", "sum"):
            raise InvalidInputError(f"scale {self.name!r}: method must be 'mean' or 'sum'")

    @property
    def score_range(self) -> tuple[float, float]:
        """Smallest and largest possible score."""
        k = len(self.items) if self.method == "sum" else 1
        return self.scale_min * k, self.scale_max * k


def _tipi(name: str, label: str, items: Sequence[int], reverse: Iterable[int]) -> ScaleSpec:
    return ScaleSpec(
        name=f"tipi_{name}",
        instrument="tipi",
        items=tuple(f"tipi_{i}" for i in items),
        reverse=frozenset(f"tipi_{i}" for i in reverse),
        scale_min=1,
        scale_max=7,
        method="mean",
        label=f"TIPI {label}",
        citation=TIPI.citation,
    )


TIPI_SCALES: tuple[ScaleSpec, ...] = (
    _tipi("extraversion", "Extraversion", (1, 6), (6,)),
    _tipi("agreeableness", "Agreeableness", (2, 7), (2,)),
    _tipi("conscientiousness", "Conscientiousness", (3, 8), (8,)),
    _tipi("emotional_stability", "Emotional Stability", (4, 9), (4,)),
    _tipi("openness", "Openness to Experiences", (5, 10), (10,)),
)
"""The five TIPI scales: mean of two items, reverse-keyed items 8 − x (Gosling et al., 2003)."""

NARS_SUBSCALES: dict[str, tuple[str, tuple[int, ...]]] = {
    "s1": ("S1 situations of interaction with robots", (4, 7, 8, 9, 10, 12)),
    "s2": ("S2 social influence of robots", (1, 2, 11, 13, 14)),
    "s3": ("S3 emotions in interaction with robots", (3, 5, 6)),
    "total": ("total", tuple(range(1, 15))),
}
"""NARS subscales (label, item numbers) and the total; items 3, 5, 6 are reverse-keyed."""

_NARS_REVERSE = frozenset({3, 5, 6})


def nars_scales(method: Literal["sum", "mean"] = "sum") -> tuple[ScaleSpec, ...]:
    """NARS S1, S2, S3 and total, scored as the sum (default) or the mean of their items.

    Names are ``nars_<sub>_<method>`` (e.g. ``nars_s1_sum``) so both versions can coexist in an
    export.
    """
    return tuple(
        ScaleSpec(
            name=f"nars_{sub}_{method}",
            instrument="nars",
            items=tuple(f"nars_{i}" for i in numbers),
            reverse=frozenset(f"nars_{i}" for i in numbers if i in _NARS_REVERSE),
            scale_min=1,
            scale_max=5,
            method=method,
            label=f"NARS {label} ({method})",
            citation=NARS.citation,
        )
        for sub, (label, numbers) in NARS_SUBSCALES.items()
    )


DEFAULT_SCALES: tuple[ScaleSpec, ...] = (*TIPI_SCALES, *nars_scales("sum"), *nars_scales("mean"))
"""TIPI's five scales and NARS's subscales and total as sums and as means."""


def _item_table(instruments: Sequence[InstrumentSpec]) -> pd.DataFrame:
    """One row per (instrument, item) with what validation and scoring need."""
    records = []
    for spec in instruments:
        for item in spec.items:
            records.append(
                {
                    "instrument": spec.name,
                    "item": item.key,
                    "kind": item.kind,
                    "numeric": item.kind in ("likert", "numeric"),
                    "low": np.nan if item.minimum is None else float(item.minimum),
                    "high": np.nan if item.maximum is None else float(item.maximum),
                    "reverse": item.reverse,
                    "per_session": spec.per_session,
                }
            )
    table = pd.DataFrame.from_records(records)
    if table.empty:
        raise InvalidInputError("no instrument specification given")
    dup = table[table.duplicated(["instrument", "item"])]
    if len(dup):
        raise InvalidInputError(f"instrument specifications repeat {describe_keys(list(dup.item))}")
    return table.set_index(["instrument", "item"])


def validate_responses(
    responses: pd.DataFrame, instruments: Sequence[InstrumentSpec] = DEFAULT_INSTRUMENTS
) -> pd.DataFrame:
    """Check a long responses frame against the instrument specifications.

    Returns a copy with ``session`` as nullable ``Int64``.

    Raises
    ------
    InvalidInputError
        Missing columns, an unknown instrument or item, a session on a once-only instrument
        (or none on a per-session one), a non-numeric or out-of-range answer, or a categorical
        answer that is not one of its codes.
    DuplicateObservationError
        Two answers for the same participant × instrument × session × item.
    """
    out, _ = _validated(responses, instruments)
    return out


def _validated(
    responses: pd.DataFrame, instruments: Sequence[InstrumentSpec]
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Validated copy of ``responses`` and the item attributes aligned with its rows."""
    if not isinstance(responses, pd.DataFrame):
        raise InvalidInputError("responses must be a pandas DataFrame")
    require_columns(responses, RESPONSE_COLUMNS, "responses")
    out = responses.copy()
    try:
        out["session"] = out["session"].astype("Int64")
    except (TypeError, ValueError):
        raise InvalidInputError("responses column 'session' must hold integers or NA") from None
    for column in ("participant", "instrument", "item"):
        if out[column].isna().any():
            raise InvalidInputError(f"responses column {column!r} has missing values")
    refuse_duplicates(out, ["participant", "instrument", "session", "item"], "responses")

    table = _item_table(instruments)
    known_instruments = set(table.index.get_level_values("instrument"))
    unknown_instruments = sorted(set(out["instrument"].unique()) - known_instruments)
    if unknown_instruments:
        raise InvalidInputError(
            f"responses contain instrument(s) {describe_keys(unknown_instruments)} that no "
            "InstrumentSpec describes"
        )
    attrs = table.reindex(pd.MultiIndex.from_arrays([out["instrument"], out["item"]]))
    unknown = attrs["kind"].isna().to_numpy()
    if unknown.any():
        pairs = out.loc[unknown, ["instrument", "item"]].drop_duplicates()
        raise InvalidInputError(
            f"responses contain item(s) {describe_keys(list(pairs['item']))} that instrument "
            f"{describe_keys(list(pairs['instrument'].unique()))} does not define"
        )
    attrs = attrs.reset_index(drop=True)
    has_session = out["session"].notna().to_numpy()
    per_session = attrs["per_session"].to_numpy(dtype=bool)
    if (per_session & ~has_session).any():
        names = sorted(set(out.loc[per_session & ~has_session, "instrument"]))
        raise InvalidInputError(
            f"instrument(s) {describe_keys(names)} are answered per session but "
            f"{int((per_session & ~has_session).sum())} answer(s) have no session"
        )
    if (~per_session & has_session).any():
        names = sorted(set(out.loc[~per_session & has_session, "instrument"]))
        raise InvalidInputError(
            f"instrument(s) {describe_keys(names)} are answered once but "
            f"{int((~per_session & has_session).sum())} answer(s) carry a session number"
        )
    _check_numeric_answers(out, attrs)
    _check_categorical_answers(out, attrs, instruments)
    return out, attrs


def _check_numeric_answers(out: pd.DataFrame, attrs: pd.DataFrame) -> None:
    numeric = attrs["numeric"].to_numpy(dtype=bool)
    raw_numeric = pd.Series(out["value"].to_numpy()[numeric], dtype=object)
    values = pd.to_numeric(raw_numeric, errors="coerce").to_numpy(float)
    bad = np.isnan(values) & raw_numeric.notna().to_numpy()
    items = out["item"].to_numpy()[numeric]
    if bad.any():
        first = int(np.flatnonzero(bad)[0])
        raise InvalidInputError(
            f"item {items[first]!r} needs numeric answers; found "
            f"{describe_keys(list(pd.unique(raw_numeric[bad])))}"
        )
    low = attrs["low"].to_numpy(float)[numeric]
    high = attrs["high"].to_numpy(float)[numeric]
    with np.errstate(invalid="ignore"):
        outside = (values < low) | (values > high)
    if outside.any():
        first = int(np.flatnonzero(outside)[0])
        same = outside & (items == items[first])
        raise InvalidInputError(
            f"item {items[first]!r} has answer(s) {describe_keys(list(pd.unique(values[same])))} "
            f"outside {low[first]:g}–{high[first]:g}"
        )


def _check_categorical_answers(
    out: pd.DataFrame, attrs: pd.DataFrame, instruments: Sequence[InstrumentSpec]
) -> None:
    categorical = (attrs["kind"] == "categorical").to_numpy()
    if not categorical.any():
        return
    codes = {
        (spec.name, item.key): {code for code, _ in item.value_labels}
        for spec in instruments
        for item in spec.items
        if item.kind == "categorical"
    }
    rows = out.loc[categorical, ["instrument", "item", "value"]]
    for (instrument, key), group in rows.groupby(["instrument", "item"], sort=False):
        allowed = codes[(str(instrument), str(key))]
        if not allowed:
            continue
        bad = [v for v in group["value"].dropna().unique() if _code(v) not in allowed]
        if bad:
            raise InvalidInputError(
                f"item {key!r} has answer(s) {describe_keys(bad)} outside its codes "
                f"{describe_keys(sorted(allowed, key=str))}"
            )


def _code(value: object) -> object:
    """Compare categorical codes numerically when they look like numbers (2.0 == 2)."""
    plain = to_python(value)
    if isinstance(plain, float) and plain.is_integer():
        return int(plain)
    if isinstance(plain, str):
        try:
            as_float = float(plain)
        except ValueError:
            return plain
        return int(as_float) if as_float.is_integer() else as_float
    return plain


def score_responses(
    responses: pd.DataFrame, instruments: Sequence[InstrumentSpec] = DEFAULT_INSTRUMENTS
) -> pd.DataFrame:
    """The responses with a ``scored`` column: the value after the instrument's reverse key.

    Parameters
    ----------
    responses : pandas.DataFrame
        Long frame with :data:`RESPONSE_COLUMNS`.
    instruments : sequence of InstrumentSpec
        Specifications of every instrument present.

    Returns
    -------
    pandas.DataFrame
        The validated rows (``session`` as ``Int64``) plus ``scored`` (float): ``min + max − value``
        for reverse-keyed items (e.g. 6 − x for ``trust_5``), the value itself for other
        numeric items, NaN for categorical and free-text items.

    Notes
    -----
    Exclusions: none; missing answers stay NaN.
    """
    out, attrs = _validated(responses, instruments)
    numeric_mask = attrs["numeric"].to_numpy(dtype=bool)
    values = np.full(len(out), np.nan)
    raw = pd.Series(out["value"].to_numpy()[numeric_mask], dtype=object)
    values[numeric_mask] = pd.to_numeric(raw, errors="coerce").to_numpy(float)
    reverse = attrs["reverse"].to_numpy(dtype=bool)
    scored = np.where(
        reverse, attrs["low"].to_numpy(float) + attrs["high"].to_numpy(float) - values, values
    )
    out["scored"] = np.where(numeric_mask, scored, np.nan)
    return out


def score_scales(
    responses: pd.DataFrame,
    scales: Sequence[ScaleSpec] = DEFAULT_SCALES,
) -> pd.DataFrame:
    """Scale scores per participant (and session, for per-session instruments).

    Parameters
    ----------
    responses : pandas.DataFrame
        Long frame with :data:`RESPONSE_COLUMNS` (raw answers; validate it first with
        :func:`validate_responses` when instruments are known).
    scales : sequence of ScaleSpec
        Scoring keys; default TIPI's five scales and NARS's subscales and total (sum and mean).

    Returns
    -------
    pandas.DataFrame
        Columns :data:`SCALE_SCORE_COLUMNS`, one row per participant × session × scale that has
        at least one answered item; sorted by scale order, participant and session.

    Raises
    ------
    InvalidInputError
        An answer of a scale item is non-numeric or outside ``scale_min``–``scale_max``.
    DuplicateObservationError
        Two answers for the same participant × instrument × session × item.

    Notes
    -----
    Exclusions: a score needs every item of its scale; with any item missing it is NaN, and
    ``n_answered`` < ``n_items`` shows why (no prorating, so scores stay comparable).
    Reverse-keyed items are scored ``scale_min + scale_max − value``.

    References
    ----------
    Gosling, Rentfrow & Swann (2003), J. Res. Pers. 37, 504–528 (TIPI).
    Nomura, Suzuki, Kanda & Kato (2006), Interaction Studies 7(3), 437–454 (NARS).
    """
    if not isinstance(responses, pd.DataFrame):
        raise InvalidInputError("responses must be a pandas DataFrame")
    require_columns(responses, RESPONSE_COLUMNS, "responses")
    names = [s.name for s in scales]
    if len(set(names)) != len(names):
        raise InvalidInputError(f"two scales share a name: {names}")
    if not scales:
        return pd.DataFrame(columns=list(SCALE_SCORE_COLUMNS))
    rows = responses[responses["instrument"].isin({scale.instrument for scale in scales})]
    refuse_duplicates(rows, ["participant", "instrument", "session", "item"], "responses")
    values = pd.to_numeric(pd.Series(rows["value"].to_numpy(), dtype=object), errors="coerce")
    instrument = rows["instrument"].to_numpy()
    item_codes, item_uniques = pd.factorize(rows["item"])
    item_index = pd.Index(item_uniques)
    # A unit is one participant × session (instruments are separated per scale below).
    p_codes, _ = pd.factorize(rows["participant"], sort=True)
    s_codes, _ = pd.factorize(rows["session"], sort=True, use_na_sentinel=False)
    unit_key = p_codes.astype(np.int64) * (int(s_codes.max(initial=0)) + 1) + s_codes
    raw_values = rows["value"].to_numpy()
    numbers = values.to_numpy(float)

    columns: dict[str, list[np.ndarray]] = {c: [] for c in SCALE_SCORE_COLUMNS}
    participants = rows["participant"].to_numpy()
    sessions = rows["session"].to_numpy()
    for scale in scales:
        col_of_code = np.full(len(item_index) + 1, -1, dtype=np.intp)
        present = item_index.get_indexer(list(scale.items))
        col_of_code[present[present >= 0]] = np.flatnonzero(present >= 0)
        column = col_of_code[item_codes]
        mask = (instrument == scale.instrument) & (column >= 0)
        if not mask.any():
            continue
        x = numbers[mask]
        bad = np.isnan(x) & pd.notna(raw_values[mask])
        if bad.any():
            raise InvalidInputError(
                f"scale {scale.name!r}: answers must be numeric; found "
                f"{describe_keys(list(pd.unique(raw_values[mask][bad])))}"
            )
        with np.errstate(invalid="ignore"):
            outside = (x < scale.scale_min) | (x > scale.scale_max)
        if outside.any():
            raise InvalidInputError(
                f"scale {scale.name!r}: answer(s) {describe_keys(list(pd.unique(x[outside])))} "
                f"outside {scale.scale_min:g}–{scale.scale_max:g}"
            )
        reverse = np.zeros(len(scale.items), dtype=bool)
        reverse[[scale.items.index(key) for key in scale.reverse]] = True
        cols = column[mask]
        keyed = np.where(reverse[cols], scale.scale_min + scale.scale_max - x, x)
        units, first, unit = np.unique(unit_key[mask], return_index=True, return_inverse=True)
        matrix = np.full((len(units), len(scale.items)), np.nan)
        matrix[unit, cols] = keyed
        n_answered = (~np.isnan(matrix)).sum(axis=1)
        total = np.where(n_answered == len(scale.items), np.nansum(matrix, axis=1), np.nan)
        first_rows = np.flatnonzero(mask)[first]
        columns["participant"].append(participants[first_rows])
        columns["instrument"].append(np.full(len(units), scale.instrument, dtype=object))
        columns["session"].append(sessions[first_rows])
        columns["scale"].append(np.full(len(units), scale.name, dtype=object))
        columns["score"].append(total / len(scale.items) if scale.method == "mean" else total)
        columns["n_items"].append(np.full(len(units), len(scale.items)))
        columns["n_answered"].append(n_answered)
    if not columns["score"]:
        return pd.DataFrame(columns=list(SCALE_SCORE_COLUMNS))
    out = pd.DataFrame({c: np.concatenate(parts) for c, parts in columns.items()})
    out["session"] = pd.array(out["session"].to_numpy(), dtype="Int64")
    return out
