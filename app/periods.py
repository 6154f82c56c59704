"""Calendar periods such as a retention period: "5 years", "18 months", "P1Y6M", "90 days".

A retention period is a promise made to an ethics board in calendar terms ("five years after the
study ends"), so it is added in calendar years, months and days, not as a number of seconds: five
years after 2026-02-28 is 2031-02-28, and one month after January 31st is the last day of
February. Written either in words (English, singular or plural, combined: "1 year 6 months") or
as an ISO 8601 duration of years, months, weeks and days ("P5Y", "P1Y6M", "P2W").
"""

from __future__ import annotations

import calendar
import re
from dataclasses import dataclass
from datetime import datetime, timedelta

_ISO = re.compile(r"P(?:(\d+)Y)?(?:(\d+)M)?(?:(\d+)W)?(?:(\d+)D)?", re.IGNORECASE)
_WORD = re.compile(r"(\d+)\s*(years?|months?|weeks?|days?)", re.IGNORECASE)
_EXAMPLES = '"5 years", "18 months", "1 year 6 months", "90 days" or "P5Y"'


class NotAPeriod(ValueError):
    """A text that is not a positive calendar period; the message says what is accepted."""


@dataclass(frozen=True)
class Period:
    """Whole years, months and days (weeks are stored as days)."""

    years: int = 0
    months: int = 0
    days: int = 0

    @classmethod
    def parse(cls, text: str) -> Period:
        """Read a period; NotAPeriod for anything else, for a negative one and for zero."""
        cleaned = " ".join(text.strip().split())
        if cleaned.startswith("-"):
            raise NotAPeriod(f"{text!r} is negative: a retention period runs forwards")
        iso = _ISO.fullmatch(cleaned)
        if iso and any(iso.groups()):
            years, months, weeks, days = (int(g or 0) for g in iso.groups())
            period = cls(years, months, 7 * weeks + days)
        else:
            parts = _WORD.findall(cleaned)
            if not parts or _WORD.sub("", cleaned).replace(",", "").replace("and", "").strip():
                raise NotAPeriod(f"{text!r} is not a period: write e.g. {_EXAMPLES}")
            amounts = {"y": 0, "m": 0, "w": 0, "d": 0}
            for number, unit in parts:
                amounts[unit[0].lower()] += int(number)
            period = cls(amounts["y"], amounts["m"], 7 * amounts["w"] + amounts["d"])
        if period == cls():
            raise NotAPeriod(f"{text!r} is zero: give a period of at least one day")
        return period

    def after(self, moment: datetime) -> datetime:
        """``moment`` plus this period on the calendar (the day clamped to the month's end)."""
        month_index = moment.month - 1 + self.months + 12 * self.years
        year, month = moment.year + month_index // 12, month_index % 12 + 1
        day = min(moment.day, calendar.monthrange(year, month)[1])
        return moment.replace(year=year, month=month, day=day) + timedelta(days=self.days)

    def describe(self) -> str:
        """In words, for pages: "5 years", "1 year 6 months"."""
        parts = [
            f"{n} {unit}{'s' if n != 1 else ''}"
            for n, unit in ((self.years, "year"), (self.months, "month"), (self.days, "day"))
            if n
        ]
        return " ".join(parts)
