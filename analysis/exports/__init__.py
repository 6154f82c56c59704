"""Export formats for PIs: long, wide and step-log CSV, codebook (CSV/JSON), SPSS, HTML report.

Every CSV (these and the app's others) is written by :mod:`analysis.exports.csvfile`.
"""

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
