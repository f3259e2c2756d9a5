"""Reading and writing sites in the layout of docs/site-format.md.

A site is a folder with `images/*.tif[f]`, `gcps.geojson`, optional `gt_dsm.tif` and optional
`site.json`. Pixel coordinates are (col, row) of the full image, centre of the top-left pixel at
(0, 0). Images are only ever read by window. Every problem with the input is raised as an
`InputError` naming the file and the problem.
"""

from __future__ import annotations

import json
import stat
import warnings
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import rasterio
import rasterio.errors
from rasterio.errors import NotGeoreferencedWarning, RasterioIOError
from rasterio.windows import Window

from recon_core.errors import InputError
from recon_core.io.checks import finite_number, projected_epsg  # noqa: F401 (projected_epsg re-exported)
from recon_core.io.gcps import GCP, read_gcps_geojson
from recon_core.model.images import ImageInfo, ViewAngles, iso_utc  # noqa: F401 (re-exported)

IMAGE_SUFFIXES = (".tif", ".tiff", ".vrt", ".jp2")      # compared in lower case
# what GDAL must read them as: GeoTIFF, a VRT (mosaics, band subsets, products delivered as
# several tiles) or JPEG 2000 (how Pleiades and other products are often delivered)
IMAGE_DRIVERS = {"GTiff": "a GeoTIFF", "VRT": "a GDAL VRT", "JP2OpenJPEG": "a JPEG 2000 image"}
MIN_IMAGE_SIDE = 32            # a smaller image cannot hold a patch of features
MAX_IMAGE_PIXELS = 4e9          # 63,000 px a side: refused with its size (it would not fit)


@dataclass
class Site:
    """A loaded site: its images (sorted by name), GCPs and optional extras."""

    root: Path
    images: list[ImageInfo]
    gcps: list[GCP]
    gt_dsm: Path | None
    hints: dict

    def image(self, name: str) -> ImageInfo:
        for im in self.images:
            if im.name == name:
                return im
        raise KeyError(name)

    @property
    def name(self) -> str:
        return str(self.hints.get("name") or self.root.name)


def parse_iso_time(text: str) -> datetime:
    """Parse an ISO 8601 time; naive times are taken as UTC."""
    t = datetime.fromisoformat(text.strip().replace("Z", "+00:00"))
    return t if t.tzinfo else t.replace(tzinfo=timezone.utc)


def _tiff_datetime(tags: dict) -> datetime | None:
    text = tags.get("TIFFTAG_DATETIME")
    if not text:
        return None
    t = datetime.strptime(text.strip(), "%Y:%m:%d %H:%M:%S")
    return t.replace(tzinfo=timezone.utc)


def _unique_keys(pairs):
    keys = [k for k, _ in pairs]
    dup = sorted({k for k in keys if keys.count(k) > 1})
    if dup:
        raise ValueError(f"the key {dup[0]!r} is given twice")
    return dict(pairs)


FIRST_YEAR, LAST_YEAR = 1957, 2100      # an acquisition time outside these years is an error


def _read_sidecar(sidecar: Path) -> dict:
    """The image's sidecar (images/NAME.json) as a JSON object; InputError naming it otherwise."""
    if not sidecar.is_file():
        raise InputError(sidecar, "the image's sidecar is not a file (a folder, a FIFO, a device or "
                                  "a broken link)")
    if sidecar.stat().st_size > 1 << 20:
        raise InputError(sidecar, f"{sidecar.stat().st_size:,} bytes: not an image sidecar "
                                  "({\"acquired\": ISO time, \"view\": {...}})")
    try:
        meta = json.loads(sidecar.read_bytes().decode("utf-8"), object_pairs_hook=_unique_keys)
    except (ValueError, UnicodeDecodeError) as exc:
        raise InputError(sidecar, f"the image's sidecar is not JSON ({exc})") from None
    except OSError as exc:
        raise InputError(sidecar, f"cannot read the sidecar ({exc.strerror or exc})") from None
    if not isinstance(meta, dict):
        raise InputError(sidecar, "the image's sidecar must hold a JSON object ({\"acquired\": ISO time, \"view\": {...}})")
    return meta


def _view(sidecar: Path, meta: dict) -> ViewAngles | None:
    """The sidecar's optional `view` (docs/site-format.md), checked: incidence 0-90 degrees from
    the local vertical, azimuth a finite bearing (taken modulo 360)."""
    if "view" not in meta:
        return None
    v = meta["view"]
    form = "\"view\" must be {\"incidence_deg\": 0 to 90, \"azimuth_deg\": 0 to 360}"
    if not isinstance(v, dict) or set(v) - {"incidence_deg", "azimuth_deg"} or len(v) != 2:
        raise InputError(sidecar, f"{form}, got {json.dumps(v)[:120]}")
    inc, az = v["incidence_deg"], v["azimuth_deg"]
    for name, x in (("incidence_deg", inc), ("azimuth_deg", az)):
        if isinstance(x, bool) or not isinstance(x, (int, float)) or not np.isfinite(x):
            raise InputError(sidecar, f"{form}: {name} is {json.dumps(x)[:40]}")
    if not 0.0 <= inc < 90.0:
        raise InputError(sidecar, f"{form}: incidence_deg {inc:g} is not an angle from the vertical "
                                  "a satellite sees the ground at (Maxar states elevation: incidence "
                                  "= 90 - meanSatEl)")
    return ViewAngles(float(inc), float(az) % 360.0)


def _acquisition_time(path: Path, tags: dict) -> tuple[datetime | None, str, ViewAngles | None]:
    """The acquisition time (and where it came from) and the viewing direction of an image: the
    sidecar's `acquired` wins over TIFFTAG_DATETIME; `view` comes only from the sidecar."""
    sidecar = path.with_suffix(".json")
    meta, view = None, None
    if sidecar.exists() or sidecar.is_symlink():
        meta = _read_sidecar(sidecar)
        view = _view(sidecar, meta)
    if meta is not None and ("acquired" in meta or view is None):
        try:
            t, source = parse_iso_time(meta["acquired"]), "sidecar"
        except (ValueError, KeyError, TypeError, AttributeError) as exc:
            raise InputError(sidecar, f"sidecar must hold {{\"acquired\": ISO time}} ({exc})") from None
        where = sidecar
    else:
        try:
            t = _tiff_datetime(tags)
        except ValueError:
            raise InputError(path, f"TIFFTAG_DATETIME {tags.get('TIFFTAG_DATETIME')!r} is not "
                                   "'YYYY:MM:DD HH:MM:SS'") from None
        if t is None:
            return None, "none", view
        source, where = "TIFFTAG_DATETIME", path
    if not FIRST_YEAR <= t.year <= LAST_YEAR:
        raise InputError(where, f"acquisition time {t.isoformat()} is "
                                f"not a plausible date (years {FIRST_YEAR}-{LAST_YEAR})")
    return t, source, view


def refuse_blank(image: "ImageInfo") -> np.ndarray:
    """A blank image (one value everywhere: a failed export, an all-black product) gives no
    feature and ended, after sparse and dense, in an error that blamed the GCPs. 3 x 3 windows
    of 32 px and the last rows all one value (nodata aside): InputError naming it. `aerec run`
    checks this before any compute (the reconstruction itself copes with textureless tiles).
    Returns the values sampled."""
    path = image.path
    try:
        v, nodata = sample_values(path)
    except (RasterioIOError, rasterio.errors.RasterioError) as exc:
        raise InputError(path, f"unreadable block ({str(exc).splitlines()[0]})") from None
    if not len(v):
        raise InputError(path, "is empty: every pixel sampled is NaN, infinite or nodata (nothing "
                               "to match in it; check the export)")
    if v.min() == v.max():
        raise InputError(path, f"is blank: every pixel sampled has the value {v[0]:g} (nothing to "
                               "match in it; check the export)")
    return v


def sample_values(path: Path) -> tuple[np.ndarray, float | None]:
    """Finite, non-nodata values of 3 x 3 windows of 32 px and the last rows of band 1."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)
        with rasterio.open(path) as ds:
            w, h = min(ds.width, 32), min(ds.height, 32)
            parts = [ds.read(1, window=Window(0, ds.height - h, ds.width, h)).ravel()]  # pyright: ignore[reportCallIssue]
            for fy in (0.1, 0.5, 0.9):
                for fx in (0.1, 0.5, 0.9):
                    c0, r0 = int(fx * (ds.width - w)), int(fy * (ds.height - h))
                    parts.append(ds.read(1, window=Window(c0, r0, w, h)).ravel())  # pyright: ignore[reportCallIssue]
            nodata = ds.nodata
    v = np.concatenate(parts).astype(np.float64)
    v = v[np.isfinite(v)]
    if nodata is not None:
        v = v[v != nodata]
    return v, nodata


def open_image(path: Path) -> ImageInfo:
    """Read an image's header and check that its pixels can be read (catches truncated files)."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", NotGeoreferencedWarning)
            with rasterio.open(path) as ds:
                if ds.driver not in IMAGE_DRIVERS:
                    raise InputError(path, f"not an image this project reads (GDAL reads it as "
                                           f"{ds.driver}; expected {', '.join(IMAGE_DRIVERS.values())})")
                if ds.count not in (1, 3):
                    raise InputError(path, f"has {ds.count} bands; expected 1 (panchromatic) or 3 (RGB)")
                dtype = ds.dtypes[0]
                if ds.width * ds.height > MAX_IMAGE_PIXELS:
                    raise InputError(path, f"{ds.width:,} x {ds.height:,} px: larger than any satellite "
                                           f"product this project reads ({MAX_IMAGE_PIXELS / 1e9:g} "
                                           "Gpx; a full Pleiades or WorldView scene is 0.4-1.6 Gpx): "
                                           "cut it into the part to reconstruct (a VRT window)")
                if dtype not in ("uint8", "uint16", "float32"):
                    raise InputError(path, f"pixel type {dtype}; expected uint8, uint16 or float32")
                # Read the last block row: a truncated file fails here, not deep in a stage.
                h = min(ds.height, 16)
                ds.read(1, window=Window(0, ds.height - h, ds.width, h))  # pyright: ignore[reportCallIssue]
                info = ImageInfo(name=path.name, path=path, width=ds.width, height=ds.height,
                                 bands=ds.count, dtype=dtype, nodata=ds.nodata, acquired=None,
                                 time_source="none", has_rpc=bool(ds.rpcs))
                tags = ds.tags()
    except InputError:
        raise
    except (RasterioIOError, rasterio.errors.RasterioError) as exc:
        # rasterio's "Read failed. See previous exception" hides GDAL's words (the file, the block)
        msg = str(exc.__cause__ if "previous exception" in str(exc) and exc.__cause__ else exc).split("\n")[0]
        if "not recognized as" in msg or "not a supported file format" in msg:
            raise InputError(path, "not a GeoTIFF, VRT or JPEG 2000 (GDAL cannot read it)") from None
        if path.suffix.lower() == ".vrt":
            missing = [f for f in _vrt_sources(path) if not Path(f).is_file()]
            if missing:
                raise InputError(path, f"a VRT whose source {missing[0]} is missing") from None
            raise InputError(path, f"a VRT that GDAL cannot read through ({msg})") from None
        raise InputError(path, f"unreadable or truncated image ({msg})") from None
    info.acquired, info.time_source, info.view = _acquisition_time(path, tags)
    return info


def list_image_files(images_dir: Path) -> list[Path]:
    if not images_dir.is_dir():
        raise InputError(images_dir, "no images/ folder (see docs/site-format.md)")
    # hidden files are not images of the site: e.g. the temporary file of an interrupted
    # atomic write (.img_00.tif.XXXX.tif) or macOS's ._img_00.tif
    named = sorted(p for p in images_dir.iterdir()
                   if p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith("."))
    for p in named:
        try:
            st = p.stat()                      # follows links: a loop or a dangling one raises
        except OSError as exc:
            raise InputError(p, f"a broken or looping link ({exc.strerror or exc})") from None
        if not stat.S_ISREG(st.st_mode):
            kind = ("a folder" if stat.S_ISDIR(st.st_mode) else "a FIFO" if stat.S_ISFIFO(st.st_mode)
                    else "a device" if stat.S_ISCHR(st.st_mode) or stat.S_ISBLK(st.st_mode) else "not a file")
            raise InputError(p, f"is {kind}, not an image file: remove it from images/ or rename it")
    files = named
    if not files:
        raise InputError(images_dir, "no .tif, .tiff, .vrt or .jp2 image in the folder")
    stems: dict[str, Path] = {}
    for p in files:
        if p.stem in stems:
            raise InputError(p, f"has the name of {stems[p.stem].name} (one sidecar {p.stem}.json, "
                                "one acquisition?): keep one of them in images/")
        stems[p.stem] = p
    for p in files:
        if p.suffix.lower() == ".vrt":
            _check_vrt_sources(p, files)
    return files


def _vrt_sources(vrt: Path) -> list[str]:
    """The source files a VRT names (from its XML: what GDAL would open), absolute."""
    import xml.etree.ElementTree as ET

    try:
        root = ET.parse(vrt).getroot()
    except (ET.ParseError, OSError):
        return []
    out = []
    for el in root.iter("SourceFilename"):
        name = (el.text or "").strip()
        rel = el.get("relativeToVRT", "0") == "1"
        out.append(str((vrt.parent / name) if rel else Path(name)))
    return out


def _check_vrt_sources(vrt: Path, files: list[Path]) -> None:
    """A VRT that wraps another file of images/ would be the same acquisition twice."""
    try:
        with rasterio.open(vrt) as ds:
            sources = {Path(f).resolve() for f in ds.files[1:]}
    except (RasterioIOError, rasterio.errors.RasterioError):
        return                                   # open_image says what is wrong with it
    for p in files:
        if p != vrt and p.resolve() in sources:
            raise InputError(vrt, f"wraps {p.name}, which is also in images/: keep one of them")


def load_site(root: str | Path, *, require_times: bool = True, read_gcps: bool = True) -> Site:
    """Load and validate a site folder. Raises InputError on the first problem found."""
    root = Path(root)
    if not root.is_dir():
        raise InputError(root, "site folder does not exist")
    images = [open_image(p) for p in list_image_files(root / "images")]
    names = [im.name for im in images]
    if len(set(names)) != len(names):
        raise InputError(root / "images", "two images share a file name")
    if require_times:
        for im in images:
            if im.acquired is None:
                raise InputError(im.path, "no acquisition time: set TIFFTAG_DATETIME or write a "
                                          f"sidecar {im.path.with_suffix('.json').name} with "
                                          "{\"acquired\": \"YYYY-MM-DDTHH:MM:SSZ\"}")
    hints = read_site_json(root / "site.json")
    gcps: list[GCP] = []
    if read_gcps and (root / "gcps.geojson").exists():
        gcps = read_gcps_geojson(root / "gcps.geojson", {im.name: im for im in images})
    gt = root / "gt_dsm.tif"
    site = Site(root=root, images=images, gcps=gcps, gt_dsm=gt if gt.exists() else None, hints=hints)
    check_bounds_hold_gcps(site)
    return site


SITE_JSON_KEYS = ("name", "crs_epsg", "resolution_m", "bounds")
MIN_RESOLUTION_M = 0.01        # a finer DSM cell than any satellite resolves
MAX_DSM_CELLS = 1.5e9          # the DSM stage holds a few grids of float32 (6 GB each at this size)


def default_resolution(gsd_m: float) -> float:
    """The DSM's cell when neither the configuration nor site.json names one: the ground sampling
    distance rounded to 0.5 m, 0.5 m at least."""
    return max(0.5, round(gsd_m * 2) / 2)


def check_grid_size(where, bounds, res: float) -> None:
    """A DSM grid over `bounds` at `res` that cannot fit is refused before any compute."""
    cells = ((bounds[2] - bounds[0]) / res) * ((bounds[3] - bounds[1]) / res)
    if cells > MAX_DSM_CELLS:
        raise InputError(where, f"a DSM of {(bounds[2] - bounds[0]) / res:,.0f} x {(bounds[3] - bounds[1]) / res:,.0f} "
                                f"cells at {res:g} m: more than {MAX_DSM_CELLS:.2g} cells would not fit; "
                                "choose a coarser resolution_m or smaller bounds")


def read_site_json(path: Path) -> dict:
    """site.json's hints, validated: name (text), crs_epsg (a projected CRS pyproj knows),
    resolution_m (a positive number), bounds ([xmin, ymin, xmax, ymax] numbers, in that CRS)."""
    if not path.exists():
        return {}
    if not path.is_file():
        raise InputError(path, "is not a file")
    if path.stat().st_size > 1 << 20:
        raise InputError(path, f"{path.stat().st_size:,} bytes: not a site.json (a few hints)")
    try:
        d = json.loads(path.read_bytes().decode("utf-8"))
    except (ValueError, UnicodeDecodeError) as exc:
        raise InputError(path, f"malformed JSON ({exc})") from None
    if not isinstance(d, dict):
        raise InputError(path, "must hold a JSON object")
    for k in d:
        if k not in SITE_JSON_KEYS:
            import difflib

            near = difflib.get_close_matches(k, SITE_JSON_KEYS, n=1, cutoff=0.5)
            raise InputError(path, f"unknown key {k!r}" + (f" (did you mean {near[0]!r}?)" if near else "")
                                   + f"; site.json holds {', '.join(SITE_JSON_KEYS)}")
    if "name" in d and not isinstance(d["name"], str):
        raise InputError(path, f"name must be text, not {d['name']!r}")
    if "crs_epsg" in d:
        d["crs_epsg"] = projected_epsg(d["crs_epsg"], path, "crs_epsg")
    if "resolution_m" in d:
        if not (finite_number(d["resolution_m"]) and MIN_RESOLUTION_M <= d["resolution_m"] <= 1000):
            raise InputError(path, f"resolution_m must be a number of metres from {MIN_RESOLUTION_M} "
                                   f"to 1000, not {d['resolution_m']!r}")
    if "bounds" in d:
        b = d["bounds"]
        if not (isinstance(b, list) and len(b) == 4 and all(finite_number(v) for v in b)
                and b[0] < b[2] and b[1] < b[3]):
            raise InputError(path, "bounds must be [xmin, ymin, xmax, ymax], four numbers with "
                                   "xmin < xmax and ymin < ymax")
        if "crs_epsg" not in d:
            raise InputError(path, "bounds need crs_epsg (the projected CRS they are in)")
        res = float(d.get("resolution_m", 0.5))
        check_grid_size(path, b, res)
        if min(b[2] - b[0], b[3] - b[1]) < 4 * res:
            raise InputError(path, f"bounds span {b[2] - b[0]:g} x {b[3] - b[1]:g} units of EPSG:"
                                   f"{d['crs_epsg']} (metres): under 4 cells; degrees given for a "
                                   "projected CRS?")
    return d


def check_bounds_hold_gcps(site: "Site") -> None:
    """site.json's bounds must be where the site is: at least one GCP inside them (a test that
    catches bounds in the wrong CRS or units, which would give an empty DSM)."""
    b = site.hints.get("bounds")
    if not b or not site.gcps:
        return
    from recon_core.geometry.geodesy import geodetic_to_projected

    xy = geodetic_to_projected(np.array([g.llh for g in site.gcps]), int(site.hints["crs_epsg"]))
    margin = 0.5 * max(b[2] - b[0], b[3] - b[1])
    inside = ((xy[:, 0] >= b[0] - margin) & (xy[:, 0] <= b[2] + margin)
              & (xy[:, 1] >= b[1] - margin) & (xy[:, 1] <= b[3] + margin))
    if not inside.any():
        raise InputError(site.root / "site.json", f"bounds {b} are far from every GCP (the first at "
                                                  f"x {xy[0, 0]:.1f}, y {xy[0, 1]:.1f} in EPSG:"
                                                  f"{site.hints['crs_epsg']}): wrong CRS or units?")


def to_gray_float(a: np.ndarray) -> np.ndarray:
    """(bands, h, w) array -> (h, w) float32: RGB is reduced to luminance."""
    if a.shape[0] == 3:
        return (0.299 * a[0] + 0.587 * a[1] + 0.114 * a[2]).astype(np.float32)
    return a[0].astype(np.float32)


def read_window(image: ImageInfo, col0: int, row0: int, width: int, height: int, *,
                out_shape: tuple[int, int] | None = None, mask_nodata: bool = True,
                nearest: bool = False) -> np.ndarray:
    """Read a window as float32 (h, w), RGB reduced to luminance; pixels equal to nodata become
    NaN. With out_shape (h, w) the window is decimated by averaging (GDAL's overview-style read):
    the one window reader of the project (features, dense matching, the viewer's textures)."""
    from rasterio.enums import Resampling

    kw = {} if out_shape is None else {"out_shape": None, "resampling": Resampling.nearest if nearest
                                       else Resampling.average}
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", NotGeoreferencedWarning)
            with rasterio.open(image.path) as ds:
                if out_shape is not None:
                    kw["out_shape"] = (ds.count, int(out_shape[0]), int(out_shape[1]))
                a = ds.read(window=Window(col0, row0, width, height), boundless=False, **kw)  # pyright: ignore[reportCallIssue]
    except rasterio.errors.RasterioError as exc:
        raise InputError(image.path, f"cannot read window ({exc})") from None
    out = to_gray_float(a)
    if mask_nodata and image.nodata is not None and not np.isnan(image.nodata):
        out[np.any(a == image.nodata, axis=0)] = np.nan
    if out.dtype.kind == "f" and image.dtype == "float32":
        out[np.isinf(out)] = np.nan                 # an infinite pixel is no measurement either
    return out


def read_downsampled(image: ImageInfo, factor: int) -> np.ndarray:
    """Whole image decimated by an integer factor (averaging); nodata is not masked. A float
    image's NaN or infinite pixels would make every cell they fall in NaN (GDAL's average takes
    them in): those cells are read again by nearest sampling, which takes one pixel of the cell."""
    w, h = max(1, image.width // factor), max(1, image.height // factor)
    out = read_window(image, 0, 0, image.width, image.height, out_shape=(h, w), mask_nodata=False)
    bad = ~np.isfinite(out)
    if bad.any() and image.dtype == "float32":
        near = read_window(image, 0, 0, image.width, image.height, out_shape=(h, w), mask_nodata=False,
                           nearest=True)
        out[bad] = near[bad]
        out[~np.isfinite(out)] = np.nan
    return out
