"""Retention periods on the calendar: words or ISO 8601, added in years, months and days."""

from __future__ import annotations

from datetime import UTC, datetime

import pytest

from app.periods import NotAPeriod, Period


@pytest.mark.parametrize(
    ("text", "period"),
    [
        ("5 years", Period(years=5)),
        ("1 year 6 months", Period(years=1, months=6)),
        ("18 Months", Period(months=18)),
        ("2 weeks, 3 days", Period(days=17)),
        ("P5Y", Period(years=5)),
        ("p1y6m", Period(years=1, months=6)),
        ("P2W", Period(days=14)),
        ("P90D", Period(days=90)),
    ],
)
def test_periods_are_read_in_words_or_iso(text: str, period: Period) -> None:
    assert Period.parse(text) == period


@pytest.mark.parametrize(
    ("text", "why"),
    [
        ("-1 year", "negative"),
        ("soon", "not a period"),
        ("5", "not a period"),
        ("5 years and then some", "not a period"),
        ("P", "not a period"),
        ("PT5H", "not a period"),
        ("0 days", "zero"),
        ("P0Y", "zero"),
    ],
)
def test_anything_else_is_refused_saying_why(text: str, why: str) -> None:
    with pytest.raises(NotAPeriod, match=why):
        Period.parse(text)


def test_adding_follows_the_calendar() -> None:
    leap = datetime(2028, 2, 29, 12, 0, tzinfo=UTC)
    assert Period(years=1).after(leap) == datetime(2029, 2, 28, 12, 0, tzinfo=UTC)
    assert Period(months=1).after(datetime(2027, 1, 31, tzinfo=UTC)).day == 28
    assert Period(years=1, months=11).after(datetime(2026, 3, 15, tzinfo=UTC)) == datetime(
        2028, 2, 15, tzinfo=UTC
    )
    assert Period(days=30).after(datetime(2026, 12, 6, tzinfo=UTC)) == datetime(
        2027, 1, 5, tzinfo=UTC
    )
    assert Period(years=1, months=6).describe() == "1 year 6 months"
