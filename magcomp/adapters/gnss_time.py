"""UTC decimal years from the clocks a vehicle reports (Unix time, GPS week + time of week), for the WMM
epoch.

Leap seconds are ignored: 18 s is 6e-7 year, far below what the Earth-field model resolves.
"""

from __future__ import annotations

import math
from datetime import UTC, datetime, timedelta

GPS_EPOCH = datetime(1980, 1, 6, tzinfo=UTC)
EARLIEST_PLAUSIBLE_YEAR = 2010.0  # a clock before this was never set (PX4/ArduPilot boot at 1970 or 1980)
LATEST_PLAUSIBLE_YEAR = 2100.0
UNIX_2010_S = 1_262_304_000.0


def decimal_year_from_datetime(when: datetime) -> float:
    start = datetime(when.year, 1, 1, tzinfo=UTC)
    end = datetime(when.year + 1, 1, 1, tzinfo=UTC)
    return when.year + (when - start).total_seconds() / (end - start).total_seconds()


def decimal_year_from_unix(unix_s: float) -> float:
    """Decimal year of a Unix time (s); NaN when the clock is not set (0, before 2010, absurd)."""
    if not math.isfinite(unix_s) or unix_s < UNIX_2010_S:
        return math.nan
    try:
        year = decimal_year_from_datetime(datetime.fromtimestamp(unix_s, tz=UTC))
    except (OverflowError, OSError, ValueError):
        return math.nan
    return year if year <= LATEST_PLAUSIBLE_YEAR else math.nan


def decimal_year_from_gps(week: float, time_of_week_ms: float) -> float:
    """Decimal year of a GPS week number and time of week (ms); NaN when the week is 0 (no GPS time)."""
    if not (math.isfinite(week) and math.isfinite(time_of_week_ms)) or week <= 0:
        return math.nan
    try:
        when = GPS_EPOCH + timedelta(weeks=float(week), milliseconds=float(time_of_week_ms))
    except OverflowError:
        return math.nan
    year = decimal_year_from_datetime(when)
    return year if EARLIEST_PLAUSIBLE_YEAR <= year <= LATEST_PLAUSIBLE_YEAR else math.nan
