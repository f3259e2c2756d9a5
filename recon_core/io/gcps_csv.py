"""GCPs as CSV, to exchange them with surveying tools, spreadsheets and other pipelines.

One row per observation (a GCP without observation: one row with empty image, col, row):

    id,role,x,y,h,epsg,sigma_m,image,col,row
    GCP-01,control,55.4524110,-20.9047210,98.312,4979,,img_00.tif,1034.25,88.50
    GCP-01,control,55.4524110,-20.9047210,98.312,4979,,img_01.tif,1012.75,95.00

x, y: longitude and latitude in degrees when epsg is 4326 or 4979 (or empty), else easting and
northing in that projected EPSG; h: ellipsoidal height in metres (docs: site-format.md); col, row:
full-image pixel, centre of the top-left pixel = (0, 0). Columns may come in any order; id, x, y,
h are required, role defaults to control; an optional sigma_h_m column gives a height known worse
than the horizontal (written when a GCP has one). Every row of one id must give the same ground
coordinates, role and sigma. gcps.geojson stays the site's format: `aerec gcps convert` turns one
into the other.
"""

from __future__ import annotations

import csv
import io
import math
from pathlib import Path
from typing import Literal, overload

import numpy as np

from recon_core.errors import InputError
from recon_core.geometry.geodesy import geodetic_to_projected, projected_to_geodetic
from recon_core.io.files import atomic_path
from recon_core.io.gcps import GCP

COLUMNS = ("id", "role", "x", "y", "h", "epsg", "sigma_m", "image", "col", "row")
GEOGRAPHIC = (0, 4326, 4979)


def write_gcps_csv(path: str | Path, gcps: list[GCP], epsg: int | None = None) -> Path:
    """Write GCPs as CSV atomically; ground coordinates in lon/lat (epsg None) or E/N (a
    projected EPSG)."""
    text = gcps_csv_text(gcps, epsg)
    with atomic_path(path) as tmp:
        Path(tmp).write_text(text)
    return Path(path)


def gcps_csv_text(gcps: list[GCP], epsg: int | None = None) -> str:
    """The CSV text of GCPs (write_gcps_csv)."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    with_h = any(g.sigma_h_m is not None for g in gcps)
    w.writerow(COLUMNS + (("sigma_h_m",) if with_h else ()))
    for g in gcps:
        if epsg is None or int(epsg) in GEOGRAPHIC:
            x, y, code = f"{g.lon:.9f}", f"{g.lat:.9f}", 4979
        else:
            try:
                e, n, _ = geodetic_to_projected(np.array([g.lon, g.lat, g.h]), int(epsg))
            except Exception as exc:      # pyproj: unknown or unsuitable code
                raise InputError(None, f"--epsg {epsg}: cannot write E, N in it ({exc})") from None
            if not (np.isfinite(e) and np.isfinite(n)):
                raise InputError(None, f"--epsg {epsg}: {g.id} has no E, N in it")
            x, y, code = f"{float(e):.4f}", f"{float(n):.4f}", int(epsg)
        base = [g.id, g.role, x, y, f"{g.h:.4f}", code, "" if g.sigma_m is None else f"{g.sigma_m:g}"]
        tail = (["" if g.sigma_h_m is None else f"{g.sigma_h_m:g}"] if with_h else [])
        obs = sorted(g.observations.items()) or [(None, None)]
        for im, cr in obs:
            w.writerow(base + ([im, f"{cr[0]:.3f}", f"{cr[1]:.3f}"] if im and cr else ["", "", ""]) + tail)
    return buf.getvalue()


@overload
def _number(path: Path, line: int, name: str, text: str, required: Literal[True] = True) -> float: ...
@overload
def _number(path: Path, line: int, name: str, text: str, required: bool) -> float | None: ...


def _number(path: Path, line: int, name: str, text: str, required: bool = True) -> float | None:
    text = (text or "").strip()
    if not text:
        if required:
            raise InputError(path, f"line {line}: {name} is empty")
        return None
    try:
        v = float(text)
    except ValueError:
        raise InputError(path, f"line {line}: {name} {text!r} is not a number") from None
    if not math.isfinite(v):
        raise InputError(path, f"line {line}: {name} is not finite")
    return v


def read_gcps_csv(path: str | Path, default_epsg: int | None = None) -> list[GCP]:
    """Read GCPs from CSV (see the module docstring). Raises InputError naming the line."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "is not a file" if path.exists() else "does not exist")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(path, f"cannot read it as UTF-8 text ({exc})") from None
    sample = text[:4096]
    try:
        dialect = csv.Sniffer().sniff(sample, delimiters=",;\t")
    except csv.Error:
        dialect = csv.excel
    reader = csv.DictReader(io.StringIO(text), dialect=dialect)
    if reader.fieldnames is None:
        raise InputError(path, "is empty")
    names = {(f or "").strip().lower(): f for f in reader.fieldnames}
    missing = [c for c in ("id", "x", "y", "h") if c not in names]
    if missing:
        raise InputError(path, f"missing column(s) {', '.join(missing)}; columns: {', '.join(COLUMNS)}")

    def get(row, col):
        key = names.get(col)
        return (row.get(key) or "").strip() if key else ""

    gcps: dict[str, GCP] = {}
    for row in reader:
        k = reader.line_num                                # the file's line (blank lines count)
        gid = get(row, "id")
        if not gid:
            if not any((v or "").strip() for v in row.values() if isinstance(v, str)):
                continue                                    # a blank line
            raise InputError(path, f"line {k}: empty id")
        x, y, h = (_number(path, k, c, get(row, c)) for c in ("x", "y", "h"))
        code_txt = get(row, "epsg").upper().removeprefix("EPSG:")
        code_v = _number(path, k, "epsg", code_txt, required=False)
        code = int(code_v) if code_v is not None else int(default_epsg if default_epsg is not None else 4979)
        if code in GEOGRAPHIC:
            if not (-180 <= x <= 180 and -90 <= y <= 90):
                raise InputError(path, f"line {k}: lon/lat {x}, {y} out of range (for E/N give the "
                                       "projected EPSG in the epsg column or with --epsg)")
            lon, lat = x, y
        else:
            try:
                lon, lat, _ = projected_to_geodetic(np.array([x, y, h]), code)
            except Exception as exc:      # pyproj: unknown code, not projected, ...
                raise InputError(path, f"line {k}: cannot use EPSG:{code} ({exc})") from None
            if not (np.isfinite(lon) and np.isfinite(lat) and -180 <= lon <= 180 and -90 <= lat <= 90):
                raise InputError(path, f"line {k}: E, N {x}, {y} are not a place in EPSG:{code}")
        role = get(row, "role").lower() or "control"
        if role not in ("control", "check"):
            raise InputError(path, f"line {k}: role {role!r}; expected control or check")
        sigma = _number(path, k, "sigma_m", get(row, "sigma_m"), required=False)
        if sigma is not None and sigma <= 0:
            raise InputError(path, f"line {k}: sigma_m must be positive")
        sigma_h = _number(path, k, "sigma_h_m", get(row, "sigma_h_m"), required=False)
        if sigma_h is not None and sigma_h <= 0:
            raise InputError(path, f"line {k}: sigma_h_m must be positive")
        g = gcps.get(gid)
        if g is None:
            g = gcps[gid] = GCP(gid, float(lon), float(lat), float(h), role, sigma, {}, sigma_h_m=sigma_h)
        elif (abs(g.lon - lon) > 1e-9 or abs(g.lat - lat) > 1e-9 or abs(g.h - h) > 1e-4
              or g.role != role or g.sigma_m != sigma or g.sigma_h_m != sigma_h):
            raise InputError(path, f"line {k}: {gid} has other ground coordinates, role or sigma "
                                   "than on its first line")
        im = get(row, "image")
        if im:
            c = _number(path, k, "col", get(row, "col"))
            r = _number(path, k, "row", get(row, "row"))
            if im in g.observations:
                raise InputError(path, f"line {k}: {gid} observed twice in {im}")
            g.observations[im] = (c, r)
        elif get(row, "col") or get(row, "row"):
            raise InputError(path, f"line {k}: col/row without an image")
    if not gcps:
        raise InputError(path, "no GCP row")
    return list(gcps.values())
