"""A site from vendor products, without copying a pixel (`aerec site init`).

Each product image becomes a VRT in SITE/images/ that refers to the product's file (its band
chosen), with its acquisition time in a sidecar. The time comes from the product's own
metadata as GDAL's metadata readers expose it (the IMAGERY domain, filled from a DIMAP
`DIM_*.XML`, a Maxar `*.IMD`/`*.XML` and others found beside the image: ACQUISITIONDATETIME and
SATELLITEID), from a NITF image subheader (NITF_IDATIM), from TIFFTAG_DATETIME, or from the
user (`--time NAME=ISO`). No vendor XML is parsed here. RPCs are never needed; when a product
has them they give only the site's footprint (site.json), and the user is told so.

The viewing direction at the image centre (the sidecar's `view`, which holds the upgrade's
height scale: recon_core.euclidean.held) comes from the same metadata: Maxar's satEl / satAz
(meanSatEl / meanSatAz; incidence = 90 - elevation), DIMAP's Located_Geometric_Values of the
Center (INCIDENCE_ANGLE; the azimuth from the image's orientation AZIMUTH_ANGLE and the
along- and across-track incidences, as optical-remote-sensing tools read it), or the user
(`--view NAME=INCIDENCE,AZIMUTH`). The run checks each against the others and the GCPs and
leaves out one that disagrees.
"""

from __future__ import annotations

import json
import os
import re
import warnings
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import cast
from xml.sax.saxutils import escape

import numpy as np

from recon_core.errors import InputError
from recon_core.io.files import atomic_path, write_json
from recon_core.io.site import MAX_DSM_CELLS, default_resolution, parse_iso_time
from recon_core.model.images import ViewAngles

RASTER_SUFFIXES = (".tif", ".tiff", ".jp2", ".ntf", ".vrt")
TILE_NAME = re.compile(r"^(?P<base>.+)_R(?P<r>\d+)C(?P<c>\d+)$", re.I)    # IMG_..._R1C2


@dataclass
class ProductImage:
    name: str                       # the site's name for it (the VRT's stem)
    files: list[tuple[Path, int, int]]   # (file, row tile, column tile): one, or a product's tiles
    acquired: datetime
    time_source: str
    satellite: str | None
    band: int
    width: int
    height: int
    dtype: str
    view: ViewAngles | None = None       # the viewing direction at the image centre, if stated
    view_source: str | None = None
    rpc_footprint: list | None = None    # [[lon, lat], ...] from the product's RPC, if any
    crs_footprint: tuple | None = None   # (epsg or wkt, [[x, y], ...]) of a georeferenced product


def _open(path: Path):
    import rasterio
    import rasterio.errors

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return rasterio.open(path)
    except rasterio.errors.RasterioIOError as exc:
        raise InputError(path, f"GDAL cannot read it ({str(exc).splitlines()[0]})") from None


def _parse_time(path: Path, field: str, text: str, fmt: str | None = None) -> datetime:
    try:
        t = datetime.strptime(text.strip(), fmt) if fmt else parse_iso_time(text)
    except ValueError:
        raise InputError(path, f"{field} {text!r} is not a time") from None
    t = t if t.tzinfo else t.replace(tzinfo=timezone.utc)
    if not 1957 <= t.year <= 2100:
        raise InputError(path, f"{field} {text!r} is not a plausible acquisition time")
    return t.astimezone(timezone.utc)


def product_time(path: Path, ds) -> tuple[datetime, str, str | None]:
    """(time, where it came from, satellite) from a product file's metadata (module docstring).
    Raises InputError naming the file and the field when there is none or it is not a time."""
    spaces = ds.tag_namespaces() or []
    imagery = ds.tags(ns="IMAGERY") if "IMAGERY" in spaces else {}
    sat = imagery.get("SATELLITEID") or None
    imd = ds.tags(ns="IMD") if "IMD" in spaces else {}
    # the vendor's own fields, as GDAL read them (IMAGERY rounds them to the second and lets an
    # impossible date through): DIMAP's IMAGING_DATE + IMAGING_TIME, Maxar's firstLineTime
    date = next((k for k in imd if k.endswith("Strip_Source.IMAGING_DATE")), None)
    first = next((k for k in imd if k.endswith("firstLineTime")), None)
    if date:
        tkey = date.replace("IMAGING_DATE", "IMAGING_TIME")
        text = f"{imd[date].strip()}T{imd.get(tkey, '00:00:00Z').strip()}"
        return _parse_time(path, f"DIMAP IMAGING_DATE / IMAGING_TIME ({_vendor_file(ds)})", text), \
            "the product's DIMAP metadata", sat
    if first:
        return _parse_time(path, f"firstLineTime ({_vendor_file(ds)})", imd[first].strip().rstrip(";")), \
            "the product's IMD metadata", sat
    if imagery.get("ACQUISITIONDATETIME"):
        return (_parse_time(path, "IMAGERY ACQUISITIONDATETIME", imagery["ACQUISITIONDATETIME"],
                            "%Y-%m-%d %H:%M:%S"), "product metadata (GDAL IMAGERY domain)", sat)
    tags = ds.tags()
    if tags.get("NITF_IDATIM"):
        return _parse_time(path, "NITF_IDATIM", tags["NITF_IDATIM"], "%Y%m%d%H%M%S"), "NITF_IDATIM", sat
    if tags.get("TIFFTAG_DATETIME"):
        return (_parse_time(path, "TIFFTAG_DATETIME", tags["TIFFTAG_DATETIME"], "%Y:%m:%d %H:%M:%S"),
                "TIFFTAG_DATETIME", sat)
    raise InputError(path, "no acquisition time in its metadata (no vendor metadata file beside it that "
                           "GDAL reads, no NITF_IDATIM, no TIFFTAG_DATETIME): give it with "
                           f"--time {path.stem}=YYYY-MM-DDTHH:MM:SSZ")


def _angle(path: Path, field: str, text: str) -> float:
    try:
        v = float(str(text).strip().strip('";'))
    except ValueError:
        raise InputError(path, f"{field} {text!r} is not an angle") from None
    if not np.isfinite(v) or abs(v) > 360.0:
        raise InputError(path, f"{field} {text!r} is not an angle in degrees")
    return v


def product_view(path: Path, ds) -> tuple[ViewAngles | None, str | None]:
    """(the viewing direction at the image centre, where it came from) from a product's
    metadata as GDAL reads it (module docstring), or (None, None)."""
    imd = ds.tags(ns="IMD") if "IMD" in (ds.tag_namespaces() or []) else {}
    el = next((k for k in imd if k.endswith(("meanSatEl", ".satEl"))), None)
    az = next((k for k in imd if k.endswith(("meanSatAz", ".satAz"))), None)
    if el and az:
        e = _angle(path, f"{el} ({_vendor_file(ds)})", imd[el])
        if not 0.0 < e <= 90.0:
            raise InputError(path, f"{el} {imd[el]!r} ({_vendor_file(ds)}) is not a satellite elevation")
        return ViewAngles(round(90.0 - e, 6), _angle(path, az, imd[az]) % 360.0), "the product's IMD metadata"
    centre = next((k[:-len(".LOCATION_TYPE")] for k, v in imd.items()
                   if k.endswith("Located_Geometric_Values.LOCATION_TYPE") or
                   (k.endswith(".LOCATION_TYPE") and "Located_Geometric_Values" in k)
                   if str(v).strip().lower() == "center"), None)
    if centre is None:
        return None, None
    ang = {k.rsplit(".", 1)[1]: v for k, v in imd.items() if k.startswith(centre + ".Acquisition_Angles.")}
    need = ("INCIDENCE_ANGLE", "AZIMUTH_ANGLE", "INCIDENCE_ANGLE_ALONG_TRACK", "INCIDENCE_ANGLE_ACROSS_TRACK")
    if not all(n in ang for n in need):
        return None, None
    where = f"DIMAP Acquisition_Angles of the Center ({_vendor_file(ds)})"
    inc, orient, along, across = (_angle(path, f"{n} ({where})", ang[n]) for n in need)
    if not 0.0 <= inc < 90.0:
        raise InputError(path, f"INCIDENCE_ANGLE {ang['INCIDENCE_ANGLE']!r} ({where}) is not an incidence")
    azimuth = orient - np.degrees(np.arctan2(np.tan(np.radians(across)), np.tan(np.radians(along))))
    return ViewAngles(inc, float(azimuth % 360.0)), "the product's DIMAP metadata"


def _vendor_file(ds) -> str:
    """The metadata file GDAL read beside the image (for messages)."""
    others = [f for f in (ds.files or [])[1:] if f.lower().endswith((".xml", ".imd", ".txt"))]
    return Path(others[0]).name if others else "its metadata"


def find_product_images(paths: list[Path]) -> list[list[tuple[Path, int, int]]]:
    """The images of the products given (files or folders): each image as its files, one or
    the tiles of a product split in several (IMG_..._R1C1, _R1C2, ...: DIMAP's and Maxar's
    naming), in tile order."""
    files: list[Path] = []
    for p in paths:
        p = Path(p)
        if not p.exists():
            raise InputError(p, "no such product file or folder")
        if p.is_dir():
            found = sorted(q for q in p.rglob("*") if q.is_file() and q.suffix.lower() in RASTER_SUFFIXES
                           and not q.name.startswith("."))
            if not found:
                raise InputError(p, "holds no image (.tif, .tiff, .jp2, .ntf, .vrt)")
            files += found
        elif p.suffix.lower() in RASTER_SUFFIXES:
            files.append(p)
        else:
            raise InputError(p, "not an image (.tif, .tiff, .jp2, .ntf, .vrt) nor a product folder")
    unique: dict[Path, Path] = {}
    for f in files:                        # a product given twice (or a folder and a file of it)
        unique.setdefault(f.resolve(), f)
    groups: dict[tuple[Path, str], list[tuple[Path, int, int]]] = {}
    for f in unique.values():
        m = TILE_NAME.match(f.stem)
        key = (f.parent, m.group("base") if m else f.stem)
        groups.setdefault(key, []).append((f, int(m.group("r")) if m else 1, int(m.group("c")) if m else 1))
    for tiles in groups.values():
        seen: dict[tuple[int, int], Path] = {}
        for f, r, c in tiles:
            if (r, c) in seen:
                raise InputError(f, f"is tile R{r}C{c} of its image, as {seen[(r, c)].name} is: two files "
                                    "for one tile (keep one)")
            seen[(r, c)] = f
    return [sorted(v, key=lambda t: (t[1], t[2])) for _, v in sorted(groups.items(), key=lambda kv: str(kv[0]))]


def describe_image(tiles: list[tuple[Path, int, int]], band: int | None, times: dict[str, str],
                   views: dict[str, ViewAngles] | None = None) -> ProductImage:
    """What the site needs of one product image: its size (tiles mosaicked), band, time, and
    its viewing direction when its metadata (or `views`, by image name) states it."""
    first = tiles[0][0]
    base = m.group("base") if (m := TILE_NAME.match(first.stem)) else first.stem
    with _open(first) as ds:
        count, dtype = ds.count, ds.dtypes[0]
        if band is None and count not in (1, 3):
            raise InputError(first, f"has {count} bands: choose the panchromatic one with --band N "
                                    "(a site's image has 1 band, or 3 for RGB)")
        if f"{base}" in times or first.stem in times:
            text = times.get(base) or times[first.stem]
            acquired, source, sat = _parse_time(first, "--time", text), "--time", None
            imagery = ds.tags(ns="IMAGERY") if "IMAGERY" in (ds.tag_namespaces() or []) else {}
            sat = imagery.get("SATELLITEID") or None
        else:
            acquired, source, sat = product_time(first, ds)
        views = views or {}
        given = views.get(base) or views.get(first.stem)
        view, view_source = (given, "--view") if given else product_view(first, ds)
        rpc = ds.rpcs
        crs, transform = ds.crs, ds.transform
        declared = declared_size(ds)
    if band is not None and not 1 <= band <= count:
        raise InputError(first, f"--band {band}: the image has {count} band(s)")
    if dtype not in PIXEL_TYPES:
        raise InputError(first, f"pixel type {dtype}; a site's images are uint8, uint16 or float32 "
                                "(convert it, e.g. gdal_translate -ot UInt16)")
    width, height = tile_mosaic(base, tiles, count, dtype, declared)
    img = ProductImage(name=base, files=tiles, acquired=acquired, time_source=source, satellite=sat,
                       band=band or 0, width=width, height=height, dtype=dtype, view=view,
                       view_source=view_source)
    if rpc is not None and len(tiles) == 1:
        img.rpc_footprint = _rpc_footprint(rpc, width, height)
    elif crs is not None and not transform.is_identity and len(tiles) == 1:
        a = transform
        corners = [(a.a * x + a.b * y + a.c, a.d * x + a.e * y + a.f)
                   for x, y in ((0, 0), (width, 0), (width, height), (0, height))]
        img.crs_footprint = (crs.to_wkt(), corners)
    return img


PIXEL_TYPES = ("uint8", "uint16", "float32")     # what a site's images may be (recon_core.io.site)


def declared_size(ds) -> tuple[int, int] | None:
    """The whole image's (width, height) as the vendor's metadata declares it (DIMAP's
    Raster_Dimensions NCOLS / NROWS, Maxar's numColumns / numRows), or None."""
    imd = ds.tags(ns="IMD") if "IMD" in (ds.tag_namespaces() or []) else {}
    for wk, hk in (("Raster_Dimensions.NCOLS", "Raster_Dimensions.NROWS"), ("numColumns", "numRows")):
        w = next((v for k, v in imd.items() if k.endswith(wk)), None)
        h = next((v for k, v in imd.items() if k.endswith(hk)), None)
        try:
            if w is not None and h is not None:
                return int(str(w).strip('"; ')), int(str(h).strip('"; '))
        except ValueError:
            return None
    return None


def tile_mosaic(base: str, tiles: list[tuple[Path, int, int]], count: int, dtype: str,
                declared: tuple[int, int] | None) -> tuple[int, int]:
    """The (width, height) of an image's tiles put together: every tile of the grid R1C1 ..
    RmCn present, of one band count and type, the tiles of a row of one height and those of a
    column of one width, and the whole of the size the metadata declares. InputError naming
    the tile otherwise (a missing tile would shift the others; a short one leave a band of
    zeros)."""
    first = tiles[0][0]
    have = {(r, c): f for f, r, c in tiles}
    n_r, n_c = max(r for _, r, _ in tiles), max(c for _, _, c in tiles)
    for r in range(1, n_r + 1):
        for c in range(1, n_c + 1):
            if (r, c) not in have:
                where = first.parent / f"{base}_R{r}C{c}{first.suffix}"
                raise InputError(where, f"missing: {base} is tiled R1C1 .. R{n_r}C{n_c} and this tile is "
                                        "not there (the others would be put in the wrong place)")
    widths, heights = {}, {}
    for (r, c), f in sorted(have.items()):
        with _open(f) as ds:
            if ds.count != count or ds.dtypes[0] != dtype:
                raise InputError(f, f"a tile of {base} with {ds.count} band(s) of {ds.dtypes[0]}, where "
                                    f"{first.name} has {count} of {dtype}")
            w, h = widths.setdefault(c, ds.width), heights.setdefault(r, ds.height)
            if (ds.width, ds.height) != (w, h) and n_r * n_c > 1:
                raise InputError(f, f"{ds.width} x {ds.height} px where the tiles of its column are {w} px wide "
                                    f"and those of its row {h} px high: {base}'s tiles do not fit together")
    width, height = sum(widths.values()), sum(heights.values())
    if declared is not None and declared != (width, height):
        raise InputError(first, f"{base}'s tiles make {width} x {height} px where its metadata declares "
                                f"{declared[0]} x {declared[1]}: a tile is missing or of the wrong size")
    return width, height


def _rpc_footprint(rpcs, width: int, height: int) -> list:
    from recon_core.geometry.rpc import RPCModel

    rpc = RPCModel.from_rasterio(rpcs)
    cr = np.array([[0, 0], [width - 1, 0], [width - 1, height - 1], [0, height - 1]], float)
    llh = rpc.localize(cr, rpc.height_off)
    return llh[:, :2].tolist()


def write_vrt(path: Path, img: ProductImage) -> None:
    """A VRT of the product image: its tiles placed side by side, the chosen band (or all of
    a 1- or 3-band product), the source files by absolute path."""
    bands = [img.band] if img.band else list(range(1, (3 if _count(img) == 3 else 1) + 1))
    gdal_type = {"uint8": "Byte", "uint16": "UInt16", "int16": "Int16", "float32": "Float32",
                 "uint32": "UInt32", "int32": "Int32", "float64": "Float64"}.get(img.dtype)
    if gdal_type is None:
        raise InputError(img.files[0][0], f"pixel type {img.dtype} is not one a site reads")
    rows = sorted({r for _, r, _ in img.files})
    cols = sorted({c for _, _, c in img.files})
    sizes = {}
    for f, r, c in img.files:
        with _open(f) as ds:
            sizes[(r, c)] = (ds.width, ds.height)
    x_off = {c: sum(sizes[(rows[0], cc)][0] for cc in cols if cc < c) for c in cols}
    y_off = {r: sum(sizes[(rr, cols[0])][1] for rr in rows if rr < r) for r in rows}
    out = [f'<VRTDataset rasterXSize="{img.width}" rasterYSize="{img.height}">']
    for k, b in enumerate(bands, 1):
        out.append(f'  <VRTRasterBand dataType="{gdal_type}" band="{k}">')
        for f, r, c in img.files:
            w, h = sizes[(r, c)]
            out += ["    <SimpleSource>",
                    f'      <SourceFilename relativeToVRT="0">{escape(str(f.resolve()))}</SourceFilename>',
                    f"      <SourceBand>{b}</SourceBand>",
                    f'      <SrcRect xOff="0" yOff="0" xSize="{w}" ySize="{h}"/>',
                    f'      <DstRect xOff="{x_off[c]}" yOff="{y_off[r]}" xSize="{w}" ySize="{h}"/>',
                    "    </SimpleSource>"]
        out.append("  </VRTRasterBand>")
    out.append("</VRTDataset>")
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(out) + "\n")


def _count(img: ProductImage) -> int:
    with _open(img.files[0][0]) as ds:
        return ds.count


def site_grid(images: list[ProductImage]) -> tuple[dict | None, str | None]:
    """site.json's hints from the products' footprints (RPC or georeferencing), and a note to
    the user about where they came from; (None, None) without any."""
    from recon_core.geometry.geodesy import geodetic_to_projected

    lonlat = [ll for im in images if im.rpc_footprint for ll in cast(np.ndarray, _footprint_lonlat(im))]
    note = "the footprint in site.json comes from the products' RPCs (used for nothing else)"
    if not lonlat:
        lonlat = [ll for im in images if im.crs_footprint for ll in cast(np.ndarray, _footprint_lonlat(im))]
        note = "the footprint in site.json comes from the products' georeferencing"
    if not lonlat:
        return None, None
    ll = np.array(lonlat)
    lon, lat = float(ll[:, 0].mean()), float(ll[:, 1].mean())
    epsg = (32600 if lat >= 0 else 32700) + int((lon + 180) // 6) + 1
    xy = geodetic_to_projected(np.column_stack([ll, np.zeros(len(ll))]), epsg)
    b = [round(float(v), 1) for v in (xy[:, 0].min(), xy[:, 1].min(), xy[:, 0].max(), xy[:, 1].max())]
    if not all(np.isfinite(b)):
        return None, None
    hints = {"crs_epsg": epsg, "bounds": b}
    # a full scene's footprint (20 km a side) at the DSM's default cell (from the GSD, 0.5 m at
    # least) may be more cells than fit (site.check_grid_size): site.json then names the finest
    # resolution, in 0.5 m steps, that fits. Only then: otherwise the run's own default stands.
    area = (b[2] - b[0]) * (b[3] - b[1])
    res = max(0.5, float(np.ceil(2.0 * np.sqrt(area / MAX_DSM_CELLS))) / 2.0)
    while area / res ** 2 > MAX_DSM_CELLS:           # rounding at the boundary
        res += 0.5
    gsd = _gsd_estimate(images, epsg)
    usual = default_resolution(gsd) if gsd else 0.5
    if res > usual:
        hints["resolution_m"] = res
        note += (f"; at {usual:g} m{' (from the GSD)' if gsd else ''} its DSM would be {area / usual ** 2:.3g} cells, "
                 f"more than fit ({MAX_DSM_CELLS:.2g}): resolution_m is {res:g} m (smaller bounds for a finer DSM)")
    return hints, note


def _footprint_lonlat(im: ProductImage) -> np.ndarray | None:
    """(4, 2) lon, lat of an image's corners: from its RPCs, else from its georeferencing."""
    if im.rpc_footprint:
        return np.array(im.rpc_footprint, float)
    if im.crs_footprint:
        from pyproj import Transformer

        t = Transformer.from_crs(im.crs_footprint[0], "EPSG:4326", always_xy=True)
        return np.array([t.transform(x, y) for x, y in im.crs_footprint[1]], float)
    return None


def _gsd_estimate(images: list[ProductImage], epsg: int) -> float | None:
    """The median over the images with a footprint of sqrt(footprint area / pixels) (m): the
    ground sampling distance the run would find, to the footprint's accuracy."""
    from recon_core.geometry.geodesy import geodetic_to_projected

    out = []
    for im in images:
        ll = _footprint_lonlat(im)
        if ll is None:
            continue
        xy = geodetic_to_projected(np.column_stack([ll, np.zeros(len(ll))]), epsg)
        x, y = xy[:, 0], xy[:, 1]
        area = 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))
        if area > 0 and im.width * im.height > 0:
            out.append(np.sqrt(area / (im.width * im.height)))
    return float(np.median(out)) if out else None


MAX_PRODUCT_SPREAD_M = 100_000.0   # the footprints of one site's images lie closer than any scene is wide


def _refuse_nesting(site: Path, products: list[Path]) -> None:
    """A site inside a product folder would be read as a product by the next `site init` of it
    (its VRTs), and a product inside the site folder is not a product the site can hold."""
    s = Path(os.path.abspath(site))
    for p in products:
        q = Path(os.path.abspath(p))
        folder = q if q.is_dir() else q.parent
        if s == folder or folder in s.parents:
            raise InputError(site, f"is inside the product folder {folder}: write the site elsewhere "
                                   "(a later `site init` of that folder would take the site's images for products)")
        if s in q.parents:
            raise InputError(p, f"is inside the new site {site}: give products from outside it")


def _refuse_far_products(images: list[ProductImage]) -> None:
    """Images whose footprints (RPC or georeferencing) lie farther apart than any scene is wide
    are not one site."""
    from recon_core.geometry.geodesy import LocalFrame

    cen = [(im, _footprint_lonlat(im)) for im in images]
    cen = [(im, ll.mean(0)) for im, ll in cen if ll is not None and np.all(np.isfinite(ll))]
    if len(cen) < 2:
        return
    lonlat = np.array([c for _, c in cen])
    mid = np.median(lonlat, axis=0)
    enu = LocalFrame(float(mid[0]), float(mid[1])).geodetic_to_enu(np.c_[lonlat, np.zeros(len(lonlat))])
    d = np.hypot(enu[:, 0], enu[:, 1])
    k = int(np.argmax(d))
    if d[k] > MAX_PRODUCT_SPREAD_M:
        im = cen[k][0]
        raise InputError(im.files[0][0], f"lies {d[k] / 1000:,.0f} km from the other products' footprints "
                                         f"(lon {cen[k][1][0]:.4f}, lat {cen[k][1][1]:.4f}): not an image of the same site")


def init_site(site: Path, products: list[Path], *, band: int | None = None, times: dict[str, str] | None = None,
              gcps: Path | None = None, name: str | None = None,
              views: dict[str, ViewAngles] | None = None) -> tuple[list[ProductImage], list[str]]:
    """Write SITE from products (module docstring). Returns the images and notes for the user.
    Every problem is an InputError and nothing is written: the site is made in a hidden folder
    beside SITE, read back with the checks `aerec info` and `aerec run` make, and renamed into
    place only when whole and valid."""
    from recon_core.io.files import atomic_folder

    site = Path(site)
    if site.exists() and (not site.is_dir() or any(site.iterdir())):
        raise InputError(site, "exists and is not empty: `aerec site init` writes a new site")
    _refuse_nesting(site, products)
    times = dict(times or {})
    views = dict(views or {})
    images = [describe_image(tiles, band, times, views) for tiles in find_product_images(products)]
    names = [im.name for im in images]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise InputError(None, f"two products give images named {dup[0]}: keep one")
    unknown = sorted(set(times) - set(names) - {im.files[0][0].stem for im in images})
    if unknown:
        raise InputError(None, f"--time {unknown[0]}=...: no product image of that name ({', '.join(names)})")
    unknown = sorted(set(views) - set(names) - {im.files[0][0].stem for im in images})
    if unknown:
        raise InputError(None, f"--view {unknown[0]}=...: no product image of that name ({', '.join(names)})")
    _refuse_far_products(images)
    if gcps is not None:
        from recon_core.io.gcps import read_gcps_geojson

        read_gcps_geojson(gcps, {im.name + ".vrt": _Size(im.width, im.height) for im in images})
    hints, note = site_grid(images)
    with atomic_folder(site) as tmp:
        _write_site(tmp, images, hints, name, gcps)
        _check_written(tmp, site, images, gcps)
    notes = [note] if hints and note else []
    return images, notes


@dataclass
class _Size:
    """What the GCP reader checks an observation against: the image's size."""

    width: int
    height: int


def _write_site(root: Path, images: list[ProductImage], hints: dict | None, name: str | None,
                gcps: Path | None) -> None:
    (root / "images").mkdir(parents=True, exist_ok=True)
    for im in images:
        write_vrt(root / "images" / f"{im.name}.vrt", im)
        side = {"acquired": im.acquired.strftime("%Y-%m-%dT%H:%M:%SZ"), "time_source": im.time_source,
                "satellite": im.satellite, "product": [str(f.resolve()) for f, _, _ in im.files]}
        if im.view is not None:
            side.update(view=im.view.to_dict(), view_source=im.view_source)
        write_json(root / "images" / f"{im.name}.json", side)
    with atomic_path(root / "gcps.geojson") as tmp:
        tmp.write_text(Path(gcps).read_text() if gcps else json.dumps(
            {"type": "FeatureCollection", "features": []}, indent=1) + "\n")
    if hints:
        write_json(root / "site.json", {**hints, **({"name": name} if name else {})})
    elif name:
        write_json(root / "site.json", {"name": name})


def _check_written(root: Path, final: Path, images: list[ProductImage], gcps: Path | None) -> None:
    """Read the written site back as `aerec info` and `aerec run` do (images through their VRTs,
    times, GCPs against the images, site.json); a refusal names the product or the GCP file it
    comes from, not the hidden folder."""
    from recon_core.io.site import load_site

    try:
        site = load_site(root)
    except InputError as exc:
        path = Path(exc.path) if exc.path else None
        where = None
        if path is not None and path.parent.name == "images":
            im = next((i for i in images if i.name == path.stem), None)
            where = im.files[0][0] if im is not None else final / "images" / path.name
        elif path is not None and path.name == "gcps.geojson":
            where = gcps or final / "gcps.geojson"
        elif path is not None:
            where = final / path.relative_to(root) if root in path.parents else path
        raise InputError(where, exc.problem) from None
    from recon_core.config import Config
    from recon_core.model.grouping import group_by_date

    g = Config().grouping
    if all(len(grp.images) < 2 for grp in group_by_date(site.images, g.max_gap_days, g.max_span_days)):
        raise InputError(None, ("the products give one image" if len(site.images) < 2 else
                                "every date group of the products has one image")
                         + f" ({', '.join(im.name for im in images[:6])}): the method needs 2 or more views "
                           "of one date; add the other images of the acquisition")


