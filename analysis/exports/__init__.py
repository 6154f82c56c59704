"""Export formats for PIs: long, wide and step-log CSV, codebook (CSV/JSON), SPSS, HTML report."""

from analysis.exports.codebook import CODEBOOK_COLUMNS, codebook_json, codebook_table
from analysis.exports.files import (
    EXPORT_FORMATS,
    ExportFormat,
    csv_bytes,
    sha256_file,
    write_all_exports,
    write_csv,
    write_export,
)
from analysis.exports.names import session_column, spss_name
from analysis.exports.spss import write_sav
from analysis.exports.tables import (
    LONG_COLUMNS,
    STEP_EXPORT_BASE_COLUMNS,
    WideColumn,
    long_table,
    steps_table,
    wide_columns,
    wide_table,
)

__all__ = [
    "CODEBOOK_COLUMNS",
    "EXPORT_FORMATS",
    "LONG_COLUMNS",
    "STEP_EXPORT_BASE_COLUMNS",
    "ExportFormat",
    "WideColumn",
    "codebook_json",
    "codebook_table",
    "csv_bytes",
    "long_table",
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
