"""The one way trustlab writes a CSV file, with text cells that spreadsheets cannot run.

Excel, LibreOffice and Google Sheets treat a cell that begins with ``=``, ``+``, ``-`` or ``@``
(and, after a tab or carriage return, the same) as a formula: a participant's free-text answer
``=HYPERLINK("http://…","click")`` becomes a live link in the PI's spreadsheet ("CSV injection",
OWASP). Every CSV the app writes therefore goes through :func:`csv_bytes`, which prefixes such a
*text* cell with a single quote ``'``, the documented way to make spreadsheets show it as text.
Numbers are never touched: a stored ``-1.5`` stays the number ``-1.5``, while the text ``"-1+2"``
becomes ``'-1+2``.

A text cell that already begins with ``'`` gets one more, so the rule can be undone exactly:
drop one leading ``'`` from any text cell that begins with ``'``. The .sav file, the JSON
codebook and the HTML report keep the raw values (the report HTML-escapes them).
"""

from __future__ import annotations

import csv
import io
from pathlib import Path

import pandas as pd

__all__ = [
    "CSV_TEXT_RULE",
    "FORMULA_PREFIX",
    "FORMULA_TRIGGERS",
    "csv_bytes",
    "neutralise_cell",
    "neutralise_formulas",
    "write_csv",
]

FORMULA_PREFIX = "'"
"""Put before a text cell that a spreadsheet would otherwise read as a formula."""

FORMULA_TRIGGERS = ("=", "+", "-", "@", "\t", "\r", FORMULA_PREFIX)
"""First characters that get :data:`FORMULA_PREFIX`: the formula starters, and the prefix
itself (so that removing one leading prefix always gives back the stored text)."""

CSV_TEXT_RULE = (
    "In the CSV files a text cell that begins with = + - @, a tab, a carriage return or ' is "
    "written with one ' in front, so that spreadsheets show it as text instead of running it "
    "as a formula; remove one leading ' from such a cell to get the stored value. Numbers are "
    "never changed. The .sav file and codebook.json hold the stored values."
)
"""The rule in words, for the codebook."""


def neutralise_cell(value: object) -> object:
    """``value`` with :data:`FORMULA_PREFIX` in front if it is text starting with a trigger.

    Anything that is not a ``str`` (numbers, missing values, booleans) is returned unchanged.
    """
    if isinstance(value, str) and value.startswith(FORMULA_TRIGGERS):
        return FORMULA_PREFIX + value
    return value


def neutralise_formulas(frame: pd.DataFrame) -> pd.DataFrame:
    """A copy of ``frame`` with :func:`neutralise_cell` applied to every text cell and header.

    Only columns that can hold text (object, string and categorical dtypes) are looked at, and
    within them only ``str`` cells change, so an object column mixing numbers and answers (the
    long table's ``value``) keeps its numbers as numbers.
    """
    out = frame.copy()
    for position in range(frame.shape[1]):
        series = frame.iloc[:, position]
        if pd.api.types.is_numeric_dtype(series) or pd.api.types.is_datetime64_any_dtype(series):
            continue
        out.isetitem(
            position,
            pd.Series([neutralise_cell(v) for v in series], index=frame.index, dtype=object),
        )
    out.columns = pd.Index([neutralise_cell(c) for c in frame.columns], dtype=object)
    return out


def csv_bytes(frame: pd.DataFrame) -> bytes:
    """The exact bytes of every CSV trustlab writes: UTF-8, comma, ``\\n``, no index, empty =
    missing, text cells neutralised by :func:`neutralise_formulas`.

    pandas formats the cells; the quoting is RFC 4180's, which :mod:`csv` does not give with a
    ``\\n`` line end: it leaves a cell holding a carriage return unquoted, and every reader then
    splits the row there. So pandas writes every cell quoted, :mod:`csv` reads them back as
    text, and :func:`_line` quotes exactly the cells that need it.
    """
    quoted = neutralise_formulas(frame).to_csv(
        index=False, na_rep="", lineterminator="\n", quoting=csv.QUOTE_ALL
    )
    rows = csv.reader(io.StringIO(quoted, newline=""))
    return "".join(_line(row) for row in rows).encode("utf-8")


def _line(cells: list[str]) -> str:
    if cells == [""]:
        return '""\n'  # a lone empty cell, not a blank line (which readers skip)
    return ",".join(_field(cell) for cell in cells) + "\n"


_NEEDS_QUOTES = (",", '"', "\r", "\n")


def _field(cell: str) -> str:
    if any(special in cell for special in _NEEDS_QUOTES):
        return '"' + cell.replace('"', '""') + '"'
    return cell


def write_csv(frame: pd.DataFrame, path: str | Path) -> Path:
    """Write ``frame`` with :func:`csv_bytes` and return the path."""
    target = Path(path)
    target.write_bytes(csv_bytes(frame))
    return target
