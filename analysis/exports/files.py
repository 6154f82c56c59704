"""Writing the exports to files, and the list of formats the app offers.

The dashboard buttons and ``trustlab export --format F`` map straight onto
:data:`EXPORT_FORMATS`; :func:`write_export` writes one, :func:`write_all_exports` writes a
complete bundle (with a ``SHA256SUMS`` file) for archiving.

The formats made of tables need pandas and nothing of the statistics; the SPSS writer
(pyreadstat) and the fitted analyses (SciPy, statsmodels, Plotly for the report) are imported
by the formats that use them, when they are written, so ``trustlab export --format long-csv``
pays for none of them (issue 49).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
from collections.abc import Callable, Iterator, Mapping
from contextlib import AbstractContextManager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from analysis.dataset import StudyDataset
from analysis.errors import InvalidInputError
from analysis.exports.codebook import codebook_json, codebook_table
from analysis.exports.csvfile import write_csv
from analysis.exports.tables import (
    adaptation_trust_table,
    long_table,
    steps_table,
    wide_table,
)

if TYPE_CHECKING:
    from analysis.mixed_models import StudyMixedModels
    from analysis.study import StudyAnalysis

__all__ = [
    "EXPORT_FORMATS",
    "SUMS_FILE",
    "ExportFormat",
    "FittedAnalyses",
    "Staging",
    "sha256_file",
    "write_all_exports",
    "write_export",
]


def sha256_file(path: str | Path) -> str:
    """Hex SHA-256 of a file (for manifests and ``SHA256SUMS``)."""
    digest = hashlib.sha256()
    with Path(path).open("rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _json(dataset: StudyDataset, path: Path) -> Path:
    path.write_text(
        json.dumps(codebook_json(dataset), indent=2, ensure_ascii=False) + "\n", encoding="utf-8"
    )
    return path


@dataclass(frozen=True)
class FittedAnalyses:
    """The analyses of a dataset, fitted already (the app keeps them per data version), so that
    an export made of them does not fit them again.

    Attributes
    ----------
    study : StudyAnalysis
        :func:`analysis.study.analyse_study` of the dataset (type III, 95 %).
    mixed : StudyMixedModels
        :func:`analysis.mixed_models.analyse_mixed_models` of ``study`` (random slope included).
    """

    study: StudyAnalysis
    mixed: StudyMixedModels


def _mixed_json(dataset: StudyDataset, path: Path, fitted: FittedAnalyses | None = None) -> Path:
    """Every mixed model of the study, with the data manifest that produced them."""
    if fitted is not None:
        models = fitted.mixed
    else:
        from analysis.mixed_models import analyse_mixed_models
        from analysis.study import analyse_study

        models = analyse_mixed_models(analyse_study(dataset))
    payload = {"manifest": dict(dataset.manifest), **models.to_dict()}
    path.write_text(
        json.dumps(payload, indent=2, ensure_ascii=False, allow_nan=False) + "\n",
        encoding="utf-8",
    )
    return path


@dataclass(frozen=True)
class ExportFormat:
    """One downloadable export.

    Attributes
    ----------
    name : str
        Identifier used by the app (``--format``).
    filename : str
        Suggested file name.
    media_type : str
        HTTP content type.
    description : str
        One line for the dashboard.
    write : callable
        ``write(dataset, path) -> path``.
    write_fitted : callable, optional
        ``write_fitted(dataset, path, fitted) -> path`` for the exports made of fitted analyses
        (:class:`FittedAnalyses`): the same file from analyses fitted already.
    """

    name: str
    filename: str
    media_type: str
    description: str
    write: Callable[[StudyDataset, Path], Path]
    write_fitted: Callable[[StudyDataset, Path, FittedAnalyses], Path] | None = None


def _report(dataset: StudyDataset, path: Path, fitted: FittedAnalyses) -> Path:
    """:func:`analysis.report.write_report` from analyses fitted already."""
    from analysis.report import build_report

    path.write_text(build_report(fitted.study, mixed=fitted.mixed), encoding="utf-8")
    return path


def _report_from_data(dataset: StudyDataset, path: Path) -> Path:
    """:func:`analysis.report.write_report`: the report, fitting its analyses now."""
    from analysis.report import write_report

    return write_report(dataset, path)


def _sav(dataset: StudyDataset, path: Path) -> Path:
    """:func:`analysis.exports.spss.write_sav` (pyreadstat imported for it alone)."""
    from analysis.exports.spss import write_sav

    return write_sav(dataset, path)


EXPORT_FORMATS: Mapping[str, ExportFormat] = {
    f.name: f
    for f in (
        ExportFormat(
            "long-csv",
            "answers_long.csv",
            "text/csv",
            "Every answer, raw and scored (participant × instrument × session × item)",
            lambda d, p: write_csv(long_table(d), p),
        ),
        ExportFormat(
            "wide-csv",
            "participants_wide.csv",
            "text/csv",
            "One row per participant, JASP/SPSS-ready (trust_1_s1 … and scale scores)",
            lambda d, p: write_csv(wide_table(d), p),
        ),
        ExportFormat(
            "steps-csv",
            "adaptation_steps.csv",
            "text/csv",
            "The adaptation step log with every arm's probability before and after",
            lambda d, p: write_csv(steps_table(d), p),
        ),
        ExportFormat(
            "codebook-csv",
            "codebook.csv",
            "text/csv",
            "What every exported column means (CSV)",
            lambda d, p: write_csv(codebook_table(d), p),
        ),
        ExportFormat(
            "codebook-json",
            "codebook.json",
            "application/json",
            "Codebook with instruments and scales (JSON)",
            _json,
        ),
        ExportFormat(
            "sav",
            "participants_wide.sav",
            "application/x-spss-sav",
            "SPSS file of the wide table with variable and value labels",
            _sav,
        ),
        ExportFormat(
            "adaptation-csv",
            "adaptation_trust.csv",
            "text/csv",
            "Per participant × session: the robot's confidence, reply-level shares, answers to "
            ".95, with that session's trust ratings",
            lambda d, p: write_csv(adaptation_trust_table(d), p),
        ),
        ExportFormat(
            "mixed-json",
            "mixed_models.json",
            "application/json",
            "Mixed models of every measure: linear (Satterthwaite), ordinal, adaptation and "
            "trust (JSON)",
            _mixed_json,
            _mixed_json,
        ),
        ExportFormat(
            "html",
            "report.html",
            "text/html",
            "Self-contained report: methods, ANOVAs, figures, exclusions, manifest (offline)",
            _report_from_data,
            _report,
        ),
    )
}
"""Every export the app offers, by name."""


def write_export(
    dataset: StudyDataset,
    format_name: str,
    path: str | Path,
    *,
    fitted: FittedAnalyses | None = None,
) -> Path:
    """Write one export format to ``path`` (from ``fitted``, the analyses of ``dataset`` fitted
    already, when the format is made of them and they are given).

    Raises
    ------
    InvalidInputError
        Unknown format name (the message lists the known ones).
    """
    try:
        export = EXPORT_FORMATS[format_name]
    except KeyError:
        raise InvalidInputError(
            f"unknown export format {format_name!r}; choose one of {', '.join(EXPORT_FORMATS)}"
        ) from None
    if fitted is not None and export.write_fitted is not None:
        return export.write_fitted(dataset, Path(path), fitted)
    return export.write(dataset, Path(path))


SUMS_FILE = "SHA256SUMS"
"""The bundle's list of checksums (``sha256sum -c`` reads it)."""

Staging = Callable[[Path], AbstractContextManager[Path]]
"""``staging(target)`` gives the path to write a file to; the file is at ``target`` once the
``with`` block ends (the app writes private temporary files and moves them into place)."""


@contextlib.contextmanager
def _in_place(target: Path) -> Iterator[Path]:
    yield target


def write_all_exports(
    dataset: StudyDataset,
    directory: str | Path,
    *,
    staging: Staging = _in_place,
    fitted: FittedAnalyses | None = None,
) -> dict[str, Path]:
    """Write every format into ``directory`` (created if needed) plus ``SHA256SUMS``, each file
    through ``staging`` (default: straight to its path); the formats made of fitted analyses
    from ``fitted`` when given (as :func:`write_export`).

    Returns the path of each format by name.
    """
    folder = Path(directory)
    folder.mkdir(parents=True, exist_ok=True)
    written = {}
    for name, export in EXPORT_FORMATS.items():
        target = folder / export.filename
        with staging(target) as draft:
            write_export(dataset, name, draft, fitted=fitted)
        written[name] = target
    sums = "".join(f"{sha256_file(p)}  {p.name}\n" for p in written.values())
    with staging(folder / SUMS_FILE) as draft:
        draft.write_text(sums, encoding="utf-8")
    return written
