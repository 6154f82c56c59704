"""CSV formula injection: every CSV export writes text that a spreadsheet would run as a formula
with a leading ``'``; numbers, the .sav file and the HTML report keep the stored values."""

from __future__ import annotations

import csv
import dataclasses
import html
import io
from pathlib import Path

import numpy as np
import pandas as pd
import pyreadstat
import pytest

from analysis.dataset import StudyDataset
from analysis.exports import (
    CSV_TEXT_RULE,
    EXPORT_FORMATS,
    codebook_json,
    csv_bytes,
    neutralise_cell,
    neutralise_formulas,
    write_export,
)
from analysis.instruments import DEFAULT_INSTRUMENTS, InstrumentSpec, ItemSpec
from analysis.report import build_report
from analysis.synthetic import synthetic_study

FORMULAS = ['=HYPERLINK("http://x","y")', "+1", "-2+3", "@SUM(A1)", "\tx", "\rx"]
"""Free-text answers a spreadsheet would run (or, for tab and CR, reinterpret)."""

TRIGGERS = ("=", "+", "-", "@", "\t", "\r")

POST = InstrumentSpec(
    "post",
    "Post-study",
    (
        ItemSpec("post_comment", "Anything else?", "text"),
        ItemSpec(
            "post_offset", "How many degrees too warm (negative: too cold)?", "numeric", -5, 5
        ),
    ),
)


@pytest.fixture(scope="module")
def formulas() -> StudyDataset:
    """Six participants, each with one formula-like comment and the number -1.5."""
    ds = synthetic_study(6, seed=2, dropout_rate=0.0)
    codes = ds.participants["participant"].tolist()
    extra = pd.DataFrame(
        {
            "participant": codes * 2,
            "instrument": "post",
            "session": pd.array([pd.NA] * 12, dtype="Int64"),
            "item": ["post_comment"] * 6 + ["post_offset"] * 6,
            "value": [*FORMULAS, *([-1.5] * 6)],
        }
    )
    responses = pd.concat([ds.responses.astype({"value": object}), extra], ignore_index=True)
    people = ds.participants.assign(site=["+44 lab", "@home", "=1", "-", "'quoted", "plain"])
    return dataclasses.replace(
        ds, responses=responses, participants=people, instruments=(*DEFAULT_INSTRUMENTS, POST)
    )


def _rows(path: Path) -> list[dict[str, str]]:
    with path.open(newline="", encoding="utf-8") as handle:
        return list(csv.DictReader(handle))


@pytest.fixture(scope="module")
def bundle(formulas: StudyDataset, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Every CSV export and the .sav file of ``formulas``, the files these tests read: not the
    mixed-models JSON and the report, which fit models for 14 s (the report's escaping is checked
    through build_report below; the whole bundle in tests/analysis/test_exports.py)."""
    folder = tmp_path_factory.mktemp("bundle")
    read = [name for name, spec in EXPORT_FORMATS.items() if spec.media_type == "text/csv"]
    return {
        name: write_export(formulas, name, folder / EXPORT_FORMATS[name].filename)
        for name in [*read, "sav"]
    }


def test_long_csv_neutralises_each_formula_and_keeps_numbers(bundle: dict[str, Path]) -> None:
    rows = _rows(bundle["long-csv"])
    comments = [r["value"] for r in rows if r["item"] == "post_comment"]
    assert comments == ["'" + f for f in FORMULAS]
    offsets = [r for r in rows if r["item"] == "post_offset"]
    assert [r["value"] for r in offsets] == ["-1.5"] * 6  # a stored number stays a number
    assert [r["scored"] for r in offsets] == ["-1.5"] * 6


def test_wide_csv_neutralises_answers_and_attributes(bundle: dict[str, Path]) -> None:
    rows = _rows(bundle["wide-csv"])
    assert [r["post_comment"] for r in rows] == ["'" + f for f in FORMULAS]
    assert [r["post_offset"] for r in rows] == ["-1.5"] * 6
    assert [r["site"] for r in rows] == ["'+44 lab", "'@home", "'=1", "'-", "''quoted", "plain"]


def test_no_csv_cell_starts_a_formula(bundle: dict[str, Path]) -> None:
    csvs = [name for name, spec in EXPORT_FORMATS.items() if spec.media_type == "text/csv"]
    assert set(csvs) == {"long-csv", "wide-csv", "steps-csv", "codebook-csv", "adaptation-csv"}
    for name in csvs:
        with bundle[name].open(newline="", encoding="utf-8") as handle:
            for row in csv.reader(handle):
                for cell in row:
                    if cell.startswith(TRIGGERS):
                        float(cell)  # only numbers may start so (-1.5, -0.25)


def test_codebook_states_the_rule(formulas: StudyDataset, bundle: dict[str, Path]) -> None:
    book = _rows(bundle["codebook-csv"])
    text = {(r["file"], r["column"]): r["derivation"] for r in book}
    for key in (("wide", "post_comment"), ("wide", "site"), ("long", "value")):
        assert CSV_TEXT_RULE in text[key]
    assert CSV_TEXT_RULE not in text[("wide", "post_offset")]  # numbers are never changed
    assert codebook_json(formulas)["csv_text_cells"] == CSV_TEXT_RULE


def test_sav_keeps_the_raw_values(bundle: dict[str, Path]) -> None:
    frame, _ = pyreadstat.read_sav(str(bundle["sav"]))
    assert frame["post_comment"].tolist() == FORMULAS
    assert frame["site"].tolist() == ["+44 lab", "@home", "=1", "-", "'quoted", "plain"]
    np.testing.assert_allclose(frame["post_offset"], -1.5)


def test_report_escapes_the_raw_value(formulas: StudyDataset) -> None:
    label = '=HYPERLINK("http://x","<b>y</b>")'
    protocol = dict(formulas.protocol)
    protocol["conditions"] = [dict(protocol["conditions"][0], label=label)] + [
        dict(c) for c in protocol["conditions"][1:]
    ]
    page = build_report(dataclasses.replace(formulas, protocol=protocol))
    assert f"C1 ({html.escape(label)})" in page  # the methods paragraph, raw but escaped
    assert "<b>y</b>" not in page
    assert "'=HYPERLINK" not in page and "&#x27;=HYPERLINK" not in page


@pytest.mark.parametrize(
    ("value", "expected"),
    [
        ("=1+1", "'=1+1"),
        ("+1", "'+1"),
        ("-1+2", "'-1+2"),
        ("@SUM(A1)", "'@SUM(A1)"),
        ("\tx", "'\tx"),
        ("\rx", "'\rx"),
        ("'x", "''x"),  # the prefix itself, so one leading ' can always be removed
        ("a=1", "a=1"),
        ("", ""),
        (-1.5, -1.5),
        (-3, -3),
        (None, None),
    ],
)
def test_neutralise_cell(value: object, expected: object) -> None:
    assert neutralise_cell(value) == expected
    assert type(neutralise_cell(value)) is type(expected)


def test_only_text_cells_and_headers_change() -> None:
    frame = pd.DataFrame(
        {
            "number": [-1.5, np.nan],
            "integer": [-2, 3],
            "mixed": pd.Series([-1.5, "-1+2"], dtype=object),
            "string": pd.array(["=x", pd.NA], dtype="string"),
            "category": pd.Categorical(["@a", "b"]),
            "=header": ["ok", None],
        }
    )
    out = neutralise_formulas(frame)
    assert out.columns.tolist() == ["number", "integer", "mixed", "string", "category", "'=header"]
    assert out["number"].dtype == float and out["number"].iloc[0] == -1.5
    assert out["integer"].tolist() == [-2, 3]
    assert out["mixed"].tolist() == [-1.5, "'-1+2"]
    assert out["string"].iloc[0] == "'=x" and out["string"].iloc[1] is pd.NA
    assert out["category"].tolist() == ["'@a", "b"]
    assert frame["mixed"].iloc[1] == "-1+2"  # the input is not changed
    assert csv_bytes(frame).decode().splitlines() == [
        "number,integer,mixed,string,category,'=header",
        "-1.5,-2,-1.5,'=x,'@a,ok",
        ",3,'-1+2,,b,",
    ]


def test_a_carriage_return_inside_a_cell_keeps_the_row_whole() -> None:
    frame = pd.DataFrame({"text": ["a\rb", "c\r\nd", 'say "hi", then', None]})
    data = csv_bytes(frame)
    assert data == b'text\n"a\rb"\n"c\r\nd"\n"say ""hi"", then"\n""\n'
    back = list(csv.reader(io.StringIO(data.decode(), newline="")))
    assert back == [["text"], ["a\rb"], ["c\r\nd"], ['say "hi", then'], [""]]
