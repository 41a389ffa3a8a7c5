"""Earth-field reference from the World Magnetic Model (thin wrapper over pygeomag 1.1.0, WMM-2025).

The paper (sec. II-C, footnote 1) takes the earth-frame field ``u^e`` of eq. (13) from NOAA's magnetic
calculator; this module gives the same quantity offline. The DPI calibration (eq. (3)) needs its down
component ``Z`` as the dot-product constant, the field norm ``F`` for the optional norm refinement, and
heading users need the declination.

Units: pygeomag returns nT; we return mgauss (1 mgauss = 1e-7 T = 100 nT), NED (north, east, down).
Altitude is metres above the WGS-84 ellipsoid (pygeomag takes km).

This is not part of :mod:`magcomp.core` only because it reads pygeomag's coefficient file on first use.
"""

from __future__ import annotations

import datetime as _dt
import functools
import math
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from magcomp.core.heading import declination_deg as declination_deg  # re-exported: pure, lives in core
from magcomp.errors import InputError

#: The paper's lab (University of Florida, Gainesville FL): latitude deg N, longitude deg E, altitude m.
GAINESVILLE_LAT_DEG = 29.65
GAINESVILLE_LON_DEG = -82.35
GAINESVILLE_ALT_M = 30.0
DEFAULT_LOCATION: tuple[float, float, float] = (GAINESVILLE_LAT_DEG, GAINESVILLE_LON_DEG, GAINESVILLE_ALT_M)

NT_PER_MGAUSS = 100.0
WMM_COEFFICIENTS = "wmm/WMM_2025.COF"


#: WMM releases bundled with pygeomag 1.1.0, by the first year of their 5-year life span. A log's date picks
#: the release valid then (a 2015 flight uses WMM-2015v2, not WMM-2025 extrapolated ten years back).
WMM_RELEASES: dict[int, str] = {
    2010: "wmm/WMM_2010.COF",
    2015: "wmm/WMM_2015v2.COF",
    2020: "wmm/WMM_2020.COF",
    2025: WMM_COEFFICIENTS,
}


class WmmRelease(NamedTuple):
    """The WMM release used for a date."""

    epoch: int  # its base year
    in_life_span: bool  # the date lies inside its five-year life span


def wmm_release(decimal_year: float) -> WmmRelease:
    """The WMM release for this date (the oldest bundled one before its epoch, flagged outside its span)."""
    epochs = sorted(WMM_RELEASES)
    for e in reversed(epochs):
        if decimal_year >= e:
            return WmmRelease(e, decimal_year < e + 5.0)
    return WmmRelease(epochs[0], False)


@functools.lru_cache(maxsize=8)
def _geomag(epoch: int = 2025) -> Any:
    from pygeomag import GeoMag

    return GeoMag(coefficients_file=WMM_RELEASES[epoch])


def decimal_year(when: _dt.date | _dt.datetime) -> float:
    """Decimal year of a date or datetime (UTC assumed for naive datetimes), e.g. 2025-07-02 -> ~2025.5."""
    if isinstance(when, _dt.datetime):
        if when.tzinfo is not None:
            when = when.astimezone(_dt.UTC).replace(tzinfo=None)
        start = _dt.datetime(when.year, 1, 1)
        end = _dt.datetime(when.year + 1, 1, 1)
        return when.year + (when - start).total_seconds() / (end - start).total_seconds()
    start_d = _dt.date(when.year, 1, 1)
    days = (_dt.date(when.year + 1, 1, 1) - start_d).days
    return when.year + (when - start_d).days / days


def earth_field_ned_mgauss(
    lat_deg: float,
    lon_deg: float,
    alt_m: float,
    decimal_year: float,
    allow_outside_lifespan: bool = False,
) -> NDArray[np.float64]:
    """WMM main field at a point: ``[north, east, down]`` in mgauss, shape (3,), from the release valid at
    ``decimal_year`` (2010, 2015v2, 2020 or 2025; before 2010 WMM-2010's secular variation is extrapolated).

    Raises :class:`InputError` for coordinates out of range or a date after 2030.0 (unless
    ``allow_outside_lifespan``, which extrapolates the secular variation).
    """
    if not (-90.0 <= lat_deg <= 90.0) or not (-180.0 <= lon_deg <= 360.0):
        raise InputError(f"location out of range: lat {lat_deg} deg, lon {lon_deg} deg")
    if not all(math.isfinite(x) for x in (lat_deg, lon_deg, alt_m, decimal_year)):
        raise InputError("location/date for the magnetic model must be finite numbers")
    lon = lon_deg - 360.0 if lon_deg > 180.0 else lon_deg
    epoch, inside = wmm_release(float(decimal_year))
    if not inside and epoch != 2025:
        inside = True  # a release older than 2025 whose span ended: the next release is bundled (not reached)
    try:
        res = _geomag(epoch).calculate(
            glat=float(lat_deg),
            glon=float(lon),
            alt=float(alt_m) / 1000.0,
            time=float(decimal_year),
            allow_date_outside_lifespan=allow_outside_lifespan or (decimal_year < 2010.0),
        )
    except ValueError as exc:
        raise InputError(f"magnetic model (WMM-{epoch}): {exc} (date {decimal_year:.2f})") from exc
    return np.array([res.x, res.y, res.z], dtype=float) / NT_PER_MGAUSS
