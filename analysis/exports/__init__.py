"""Export formats for PIs: long, wide and step-log CSV, codebook (CSV/JSON), SPSS, HTML report.

Every CSV (these and the app's others) is written by :mod:`analysis.exports.csvfile`.

The names below are imported from their modules on first use (PEP 562), not with the package:
``trustlab export --format long-csv`` then loads the tables' modules (pandas) and neither the
SPSS writer nor the statistics (issue 49; docs/development.md, "What a command may import").
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from analysis.exports.codebook import CODEBOOK_COLUMNS, codebook_json, codebook_table
    from analysis.exports.csvfile import (
        CSV_TEXT_RULE,
        csv_bytes,
        neutralise_cell,
        neutralise_formulas,
        write_csv,
    )
    from analysis.exports.files import (
        EXPORT_FORMATS,
        SUMS_FILE,
        ExportFormat,
        FittedAnalyses,
        Staging,
        sha256_file,
        write_all_exports,
        write_export,
    )
    from analysis.exports.names import session_column, spss_name
    from analysis.exports.spss import write_sav
    from analysis.exports.tables import (
        ADAPTATION_BASE_COLUMNS,
        LONG_COLUMNS,
        STEP_EXPORT_BASE_COLUMNS,
        WideColumn,
        adaptation_trust_table,
        long_table,
        steps_table,
        wide_columns,
        wide_table,
    )

_HOMES = {
    "CODEBOOK_COLUMNS": "codebook",
    "codebook_json": "codebook",
    "codebook_table": "codebook",
    "CSV_TEXT_RULE": "csvfile",
    "csv_bytes": "csvfile",
    "neutralise_cell": "csvfile",
    "neutralise_formulas": "csvfile",
    "write_csv": "csvfile",
    "EXPORT_FORMATS": "files",
    "SUMS_FILE": "files",
    "ExportFormat": "files",
    "FittedAnalyses": "files",
    "Staging": "files",
    "sha256_file": "files",
    "write_all_exports": "files",
    "write_export": "files",
    "session_column": "names",
    "spss_name": "names",
    "write_sav": "spss",
    "ADAPTATION_BASE_COLUMNS": "tables",
    "LONG_COLUMNS": "tables",
    "STEP_EXPORT_BASE_COLUMNS": "tables",
    "WideColumn": "tables",
    "adaptation_trust_table": "tables",
    "long_table": "tables",
    "steps_table": "tables",
    "wide_columns": "tables",
    "wide_table": "tables",
}
"""Where each name lives: imported from there on first use."""


def __getattr__(name: str) -> Any:
    home = _HOMES.get(name)
    if home is None:
        raise AttributeError(f"module 'analysis.exports' has no attribute {name!r}")
    return getattr(importlib.import_module(f"analysis.exports.{home}"), name)


__all__ = [
    "ADAPTATION_BASE_COLUMNS",
    "CODEBOOK_COLUMNS",
    "CSV_TEXT_RULE",
    "EXPORT_FORMATS",
    "LONG_COLUMNS",
    "STEP_EXPORT_BASE_COLUMNS",
    "SUMS_FILE",
    "ExportFormat",
    "FittedAnalyses",
    "Staging",
    "WideColumn",
    "adaptation_trust_table",
    "codebook_json",
    "codebook_table",
    "csv_bytes",
    "long_table",
    "neutralise_cell",
    "neutralise_formulas",
    "session_column",
    "sha256_file",
    "spss_name",
    "steps_table",
    "wide_columns",
    "wide_table",
    "write_all_exports",
    "write_csv",
    "write_export",
    "write_sav",
]
