"""SPSS .sav export of the wide table, with variable labels, value labels and measure levels."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyreadstat

from analysis.dataset import StudyDataset
from analysis.exports.codebook import codebook_table
from analysis.exports.tables import wide_columns, wide_table

__all__ = ["SPSS_LABEL_LIMIT", "write_sav"]

SPSS_LABEL_LIMIT = 256
"""SPSS truncates variable labels beyond this many characters; we shorten with an ellipsis."""


def _short(label: str) -> str:
    return label if len(label) <= SPSS_LABEL_LIMIT else label[: SPSS_LABEL_LIMIT - 1] + "…"


def write_sav(dataset: StudyDataset, path: str | Path) -> Path:
    """Write the wide table (see :func:`analysis.exports.tables.wide_table`) as SPSS .sav.

    Variable labels are the item wordings (as administered) and scale labels; Likert and coded
    categorical items carry their value labels (``1 = Strongly disagree`` …); measure levels
    are ordinal for Likert items, scale for numbers and scores, nominal otherwise. Reverse-scored
    columns have no value labels (their numbers no longer match the anchors). Read it back with
    ``pyreadstat.read_sav`` or open it in SPSS, JASP, jamovi or R (haven).
    """
    target = Path(path)
    wide = wide_table(dataset)
    book = codebook_table(dataset)
    book = book[book["file"] == "wide"].set_index("column")
    columns = {c.name: c for c in wide_columns(dataset)}
    items = {(s.name, i.key): i for s in dataset.instruments for i in s.items}

    frame = wide.copy()
    for name in frame.columns:
        if not pd.api.types.is_float_dtype(frame[name]):
            frame[name] = [None if _missing(v) else str(v) for v in frame[name]]
    value_labels: dict[str, dict[int | float, str]] = {}
    for name, column in columns.items():
        if column.source != "raw" or not pd.api.types.is_float_dtype(frame[name]):
            continue
        item = items[(column.instrument, column.key)]
        labels = {float(code): label for code, label in item.value_labels if _is_number(code)}
        if labels:
            value_labels[name] = labels
    measures = {
        name: str(book.loc[name, "measure"])
        for name in frame.columns
        if str(book.loc[name, "measure"]) in ("nominal", "ordinal", "scale")
    }
    pyreadstat.write_sav(
        frame,
        str(target),
        file_label=_short(f"{dataset.protocol['study']} (trustlab)"),
        column_labels={name: _short(str(book.loc[name, "label"])) for name in frame.columns},
        variable_value_labels=value_labels,
        variable_measure=measures,
    )
    return target


def _missing(value: Any) -> bool:
    return value is None or value is pd.NA or (isinstance(value, float) and np.isnan(value))


def _is_number(code: object) -> bool:
    return isinstance(code, (int, float)) and not isinstance(code, bool)
