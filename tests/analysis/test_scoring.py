"""Scoring of TIPI, NARS and the trust items from raw answers (hand-computed examples)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from analysis.errors import DuplicateObservationError, InvalidInputError
from analysis.instruments import (
    DEFAULT_INSTRUMENTS,
    TIPI,
    TRUST,
    InstrumentSpec,
    ItemSpec,
    likert_instrument,
)
from analysis.scoring import (
    DEFAULT_SCALES,
    SCALE_SCORE_COLUMNS,
    TIPI_SCALES,
    ScaleSpec,
    nars_scales,
    score_responses,
    score_scales,
    validate_responses,
)

TIPI_A = [6, 2, 5, 3, 7, 2, 6, 1, 5, 2]
TIPI_B = [1, 7, 2, 6, 3, 5, 4, 7, 1, 6]
NARS_A = [2, 3, 4, 1, 5, 4, 2, 3, 1, 2, 3, 4, 5, 1]


def _rows(participant: str, instrument: str, values: list[int], session: int | None = None):  # type: ignore[no-untyped-def]
    return [
        (participant, instrument, session, f"{instrument}_{i}", v)
        for i, v in enumerate(values, start=1)
    ]


def _frame(rows: list[tuple]) -> pd.DataFrame:  # type: ignore[type-arg]
    df = pd.DataFrame(rows, columns=["participant", "instrument", "session", "item", "value"])
    df["session"] = df["session"].astype("Int64")
    return df


@pytest.fixture
def answers() -> pd.DataFrame:
    rows = _rows("A", "tipi", TIPI_A) + _rows("B", "tipi", TIPI_B) + _rows("A", "nars", NARS_A)
    rows += _rows("A", "trust", [4, 3, 3, 5, 2], session=1)
    rows += _rows("A", "trust", [5, 4, 2, 4, 1], session=2)
    rows += [("A", "demographics", None, "age", 31), ("A", "demographics", None, "gender", 3)]
    return _frame(rows)


def _scores(df: pd.DataFrame) -> dict[tuple[str, str], float]:
    out = score_scales(df)
    return {(p, s): v for p, s, v in zip(out.participant, out.scale, out.score, strict=True)}


def test_tipi_by_hand(answers: pd.DataFrame) -> None:
    # Participant A: 1 Extraverted 6, 6R Reserved 2 → (6 + 8−2)/2 = 6.0
    #   Agreeableness (8−2 + 6)/2 = 6.0; Conscientiousness (5 + 8−1)/2 = 6.0
    #   Emotional stability (8−3 + 5)/2 = 5.0; Openness (7 + 8−2)/2 = 6.5
    # Participant B: E (1 + 8−5)/2 = 2.0; A (8−7 + 4)/2 = 2.5; C (2 + 8−7)/2 = 1.5;
    #   ES (8−6 + 1)/2 = 1.5; O (3 + 8−6)/2 = 2.5
    scores = _scores(answers)
    expected = {
        "A": [6.0, 6.0, 6.0, 5.0, 6.5],
        "B": [2.0, 2.5, 1.5, 1.5, 2.5],
    }
    for participant, values in expected.items():
        got = [scores[(participant, s.name)] for s in TIPI_SCALES]
        assert got == values


def test_nars_by_hand_sum_and_mean(answers: pd.DataFrame) -> None:
    # S1 items 4,7,8,9,10,12 = 1+2+3+1+2+4 = 13; S2 items 1,2,11,13,14 = 2+3+3+5+1 = 14;
    # S3 items 3R,5R,6R = (6−4)+(6−5)+(6−4) = 5; total = 40 − (4+5+4) + 5 = 32.
    scores = _scores(answers)
    assert scores[("A", "nars_s1_sum")] == 13
    assert scores[("A", "nars_s2_sum")] == 14
    assert scores[("A", "nars_s3_sum")] == 5
    assert scores[("A", "nars_total_sum")] == 32
    assert scores[("A", "nars_s1_mean")] == pytest.approx(13 / 6)
    assert scores[("A", "nars_s3_mean")] == pytest.approx(5 / 3)
    assert scores[("A", "nars_total_mean")] == pytest.approx(32 / 14)
    assert ("B", "nars_s1_sum") not in scores  # B has no NARS answers: no row at all


def test_score_table_shape(answers: pd.DataFrame) -> None:
    out = score_scales(answers)
    assert tuple(out.columns) == SCALE_SCORE_COLUMNS
    assert str(out["session"].dtype) == "Int64"
    assert out["session"].isna().all()
    assert len(out) == 5 * 2 + 8


def test_trust_item_5_is_reverse_keyed(answers: pd.DataFrame) -> None:
    out = score_responses(answers)
    trust = out[out.instrument == "trust"].set_index(["session", "item"])
    assert trust.loc[(1, "trust_5"), "scored"] == 6 - 2
    assert trust.loc[(2, "trust_5"), "scored"] == 6 - 1
    assert trust.loc[(1, "trust_4"), "scored"] == 5  # not reversed
    tipi = out[(out.instrument == "tipi") & (out.participant == "A")].set_index("item")
    assert tipi.loc["tipi_6", "scored"] == 8 - 2
    assert tipi.loc["tipi_1", "scored"] == 6
    demo = out[out.instrument == "demographics"].set_index("item")
    assert demo.loc["age", "scored"] == 31
    assert np.isnan(demo.loc["gender", "scored"])  # categorical: no numeric score
    assert out["value"].tolist() == answers["value"].tolist()  # raw answers kept


def test_missing_item_gives_nan_score_with_count(answers: pd.DataFrame) -> None:
    partial = answers[~((answers.participant == "B") & (answers["item"] == "tipi_6"))]
    out = score_scales(partial, TIPI_SCALES).set_index(["participant", "scale"])
    row = out.loc[("B", "tipi_extraversion")]
    assert np.isnan(row["score"])
    assert (row["n_items"], row["n_answered"]) == (2, 1)
    assert out.loc[("B", "tipi_openness"), "score"] == 2.5
    nan_value = answers.copy()
    nan_value.loc[(nan_value.participant == "A") & (nan_value["item"] == "tipi_1"), "value"] = None
    out = score_scales(nan_value, TIPI_SCALES).set_index(["participant", "scale"])
    assert np.isnan(out.loc[("A", "tipi_extraversion"), "score"])


def test_out_of_range_and_duplicates_refused(answers: pd.DataFrame) -> None:
    bad = answers.copy()
    bad.loc[bad["item"] == "tipi_3", "value"] = 8
    with pytest.raises(InvalidInputError, match="outside 1–7"):
        score_scales(bad)
    with pytest.raises(InvalidInputError, match=r"'tipi_3' has answer\(s\) 8 outside 1–7"):
        validate_responses(bad)
    dup = pd.concat([answers, answers.iloc[[0]]])
    with pytest.raises(DuplicateObservationError, match="'A', 'tipi', None, 'tipi_1'"):
        score_scales(dup)
    with pytest.raises(DuplicateObservationError):
        score_responses(dup)


@pytest.mark.parametrize(
    ("row", "message"),
    [
        (("A", "tipi", None, "tipi_11", 3), "does not define"),
        (("A", "bfi", None, "bfi_1", 3), "no InstrumentSpec"),
        (("A", "trust", None, "trust_1", 3), "answered per session"),
        (("A", "nars", 1, "nars_1", 3), "answered once"),
        (("A", "demographics", None, "gender", 9), "outside its codes"),
        (("A", "demographics", None, "age", 12), "outside 18–99"),
        (("A", "trust", 3, "trust_1", "agree"), "numeric"),
    ],
)
def test_validation_names_the_problem(row: tuple, message: str) -> None:  # type: ignore[type-arg]
    df = _frame([row])
    with pytest.raises(InvalidInputError, match=message):
        validate_responses(df)


def test_categorical_codes_compare_numerically() -> None:
    df = _frame(
        [("A", "demographics", None, "gender", "2"), ("B", "demographics", None, "gender", 4.0)]
    )
    assert len(validate_responses(df)) == 2


def test_adapted_instrument_is_scored_from_its_spec() -> None:
    # A lab's 7-point German adaptation with its own key: items 1 and 3 reversed (8 − x), sum.
    adapted = likert_instrument(
        "vertrauen",
        "Vertrauen (adaptiert)",
        ["Ich vertraue dem Roboter.", "Der Roboter ist zuverlässig.", "Ich bin misstrauisch."],
        scale_min=1,
        scale_max=7,
        reverse=(3,),
        per_session=True,
    )
    scale = ScaleSpec(
        "vertrauen_sum", "vertrauen", ("vertrauen_1", "vertrauen_2", "vertrauen_3"),
        frozenset({"vertrauen_1", "vertrauen_3"}), 1, 7, "sum",
    )  # fmt: skip
    df = _frame(_rows("P1", "vertrauen", [7, 5, 2], session=1))
    validate_responses(df, [adapted])
    out = score_scales(df, [scale])
    assert out["score"].tolist() == [(8 - 7) + 5 + (8 - 2)]
    assert out["session"].tolist() == [1]
    scored = score_responses(df, [adapted]).set_index("item")["scored"]
    assert scored.to_dict() == {"vertrauen_1": 7, "vertrauen_2": 5, "vertrauen_3": 6}


def test_scale_spec_is_validated() -> None:
    with pytest.raises(InvalidInputError, match="not among its items"):
        ScaleSpec("x", "tipi", ("tipi_1",), frozenset({"tipi_2"}), 1, 7)
    with pytest.raises(InvalidInputError, match="twice"):
        ScaleSpec("x", "tipi", ("tipi_1", "tipi_1"), frozenset(), 1, 7)
    with pytest.raises(InvalidInputError, match="scale_min"):
        ScaleSpec("x", "tipi", ("tipi_1",), frozenset(), 7, 1)
    with pytest.raises(InvalidInputError, match="method"):
        ScaleSpec("x", "tipi", ("tipi_1",), frozenset(), 1, 7, "median")  # type: ignore[arg-type]
    with pytest.raises(InvalidInputError, match="share a name"):
        score_scales(_frame([]), [TIPI_SCALES[0], TIPI_SCALES[0]])


def test_default_specs_follow_the_published_keys() -> None:
    by_name = {s.name: s for s in DEFAULT_SCALES}
    assert by_name["tipi_extraversion"].reverse == {"tipi_6"}
    assert by_name["nars_s3_sum"].reverse == {"nars_3", "nars_5", "nars_6"}
    assert by_name["nars_total_mean"].items == tuple(f"nars_{i}" for i in range(1, 15))
    assert by_name["nars_s1_sum"].score_range == (6, 30)
    assert [s.name for s in nars_scales("mean")][:1] == ["nars_s1_mean"]
    assert TRUST.reverse == {"trust_5"}
    instruments = {i.name: i for i in DEFAULT_INSTRUMENTS}
    assert instruments["tipi"].reverse == {"tipi_2", "tipi_4", "tipi_6", "tipi_8", "tipi_10"}
    assert instruments["nars"].reverse == {"nars_3", "nars_5", "nars_6"}
    with pytest.raises(InvalidInputError):
        InstrumentSpec("empty", "Empty", ())


@settings(max_examples=40, deadline=None)
@given(st.lists(st.integers(1, 7), min_size=10, max_size=10))
def test_tipi_properties(values: list[int]) -> None:
    df = _frame(_rows("P", "tipi", values))
    out = score_scales(df, TIPI_SCALES).set_index("scale")["score"]
    assert out.between(1, 7).all()
    assert out["tipi_extraversion"] == (values[0] + 8 - values[5]) / 2
    # Flipping every answer (8 − x) mirrors every score around the midpoint 4.
    flipped = score_scales(df.assign(value=8 - df["value"]), TIPI_SCALES).set_index("scale")
    np.testing.assert_allclose(flipped["score"], 8 - out, rtol=0, atol=1e-12)


def test_item_and_instrument_specs_are_validated() -> None:
    with pytest.raises(InvalidInputError, match="needs minimum and maximum"):
        ItemSpec("x_1", "text", "likert")
    with pytest.raises(InvalidInputError, match="minimum must be below maximum"):
        ItemSpec("x_1", "text", "numeric", 5, 1)
    with pytest.raises(InvalidInputError, match="unknown kind"):
        ItemSpec("x_1", "text", "slider")  # type: ignore[arg-type]
    with pytest.raises(InvalidInputError, match="reverse-keyed item 'x_1' needs"):
        ItemSpec("x_1", "text", "categorical", reverse=True)
    assert ItemSpec("x_1", "t", "likert", 1, 7, reverse=True).scored(2) == 6
    assert ItemSpec("x_1", "t", "likert", 1, 7).scored(2) == 2
    with pytest.raises(InvalidInputError, match="reverse item number"):
        likert_instrument("x", "X", ["a", "b"], scale_min=1, scale_max=5, reverse=(3,))
    with pytest.raises(InvalidInputError, match="twice"):
        InstrumentSpec("x", "X", (ItemSpec("a", "a", "text"), ItemSpec("a", "b", "text")))
    with pytest.raises(InvalidInputError, match="has no item 'tipi_99'"):
        TIPI.item("tipi_99")


def test_scores_sorted_by_participant_and_session() -> None:
    rows = _rows("B", "tipi", TIPI_B) + _rows("A", "tipi", TIPI_A)
    out = score_scales(_frame(rows), TIPI_SCALES[:1])
    assert out["participant"].tolist() == ["A", "B"]
