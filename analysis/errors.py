"""Exceptions raised by the analysis package.

Every problem with the data a caller passes in is an :class:`AnalysisError` (a ``ValueError``),
so the web layer and the command line can turn it into a message without a traceback. Two
sub-classes separate "your input is malformed" from "your input is fine but the statistic does
not exist for it", because the fix differs: the first needs corrected data, the second needs more
(or more varied) data.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

__all__ = [
    "AnalysisError",
    "CannotComputeError",
    "DuplicateObservationError",
    "InvalidInputError",
]


class AnalysisError(ValueError):
    """Base class of every data problem reported by :mod:`analysis`."""


class InvalidInputError(AnalysisError):
    """The input is malformed: a missing column, a non-numeric value, an unknown item…"""


class DuplicateObservationError(InvalidInputError):
    """The same unit was observed twice where exactly one observation is allowed.

    Parameters
    ----------
    message : str
        Human-readable description naming the duplicated keys.
    duplicates : sequence of tuple
        The duplicated keys (e.g. ``(subject, session)`` pairs), each listed once.
    """

    def __init__(self, message: str, duplicates: Sequence[tuple[Any, ...]]) -> None:
        super().__init__(message)
        self.duplicates: tuple[tuple[Any, ...], ...] = tuple(duplicates)


class CannotComputeError(AnalysisError):
    """The statistic is undefined for these data (degenerate design or zero variance).

    The message always reads ``"<what> cannot be computed because <why>"``.
    """

    def __init__(self, what: str, because: str) -> None:
        super().__init__(f"{what} cannot be computed because {because}")
        self.what = what
        self.because = because
