"""Checks of single values that several input readers share (a JSON number, an EPSG code)."""

from __future__ import annotations

import math
from pathlib import Path

from recon_core.errors import InputError


def finite_number(v) -> bool:
    """A JSON number that is a finite float (an integer of 400 digits is not: no float holds it)."""
    if not isinstance(v, (int, float)) or isinstance(v, bool):
        return False
    try:
        return math.isfinite(v)
    except OverflowError:
        return False


def projected_epsg(value, path: Path | None, what: str) -> int:
    """An EPSG code of a projected CRS in metres that pyproj knows, else an InputError."""
    from pyproj import CRS
    from pyproj.exceptions import CRSError

    if not finite_number(value) or int(value) != value or not 1024 <= value <= 999_999:
        raise InputError(path, f"{what} must be an EPSG code (an integer), not {value!r}")
    try:
        crs = CRS.from_epsg(int(value))
    except CRSError:
        raise InputError(path, f"{what} {int(value)} is not an EPSG code pyproj knows") from None
    if not crs.is_projected:
        raise InputError(path, f"{what} {int(value)} ({crs.name}) is not a projected CRS: outputs "
                               "need x, y in metres (e.g. a UTM zone)")
    unit = crs.axis_info[0].unit_name if crs.axis_info else "metre"
    if unit not in ("metre", "meter"):
        raise InputError(path, f"{what} {int(value)} ({crs.name}) has units of {unit}, not metres")
    return int(value)
