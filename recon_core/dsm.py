"""Rasterising Euclidean clouds into a DSM grid; DSM GeoTIFF and PLY input/output.

Grid convention: north-up, square cells of side `res` metres; cell (row 0, col 0) has its
top-left corner at (xmin, ymax); cell (r, c) covers x in [xmin + c res, xmin + (c+1) res) and
y in (ymax - (r+1) res, ymax - r res]. Its centre is at (xmin + (c + 0.5) res, ymax - (r + 0.5) res).

Cell statistic (`rasterize(stat=...)`): the default is the **median** of the heights falling in a
cell. It is unbiased where a cell straddles a roof edge (the cell takes the height of the larger
part, as a ground-truth DSM sampled at the cell centre does) and rejects isolated outliers on
both sides. "upper_median" (the 75th percentile) keeps roof edges sharper when walls and ground
points outnumber roof points near an edge (at the cost of fattening buildings by part of a cell)
and still rejects isolated high outliers; "max" is the lidar-style first-return statistic and
is outlier-sensitive; "mean" and "min" are there for comparisons.
"""

from __future__ import annotations

import math
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import rasterio
from rasterio.crs import CRS
from rasterio.enums import Resampling
from rasterio.transform import Affine

from .errors import InputError
from .io_utils import atomic_path

STATS = {"median": 0.5, "upper_median": 0.75, "max": None, "min": None, "mean": None}


# --------------------------------------------------------------------------------------------
# Grid
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Grid:
    """A north-up raster grid in a projected CRS (see the module docstring for conventions)."""

    crs_epsg: int
    xmin: float
    ymax: float
    res: float
    width: int
    height: int

    @property
    def transform(self) -> Affine:
        """rasterio Affine: pixel (col, row) corner -> (x, y)."""
        return Affine(self.res, 0.0, self.xmin, 0.0, -self.res, self.ymax)

    @property
    def crs(self) -> CRS:
        return CRS.from_epsg(self.crs_epsg)

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(xmin, ymin, xmax, ymax)."""
        return (self.xmin, self.ymax - self.height * self.res,
                self.xmin + self.width * self.res, self.ymax)

    @property
    def shape(self) -> tuple[int, int]:
        return (self.height, self.width)

    def cell_of(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(row, col) int64 arrays of the cells containing (x, y); may lie outside the grid."""
        col = np.floor((np.asarray(x, dtype=np.float64) - self.xmin) / self.res).astype(np.int64)
        row = np.floor((self.ymax - np.asarray(y, dtype=np.float64)) / self.res).astype(np.int64)
        return row, col

    def contains(self, row: np.ndarray, col: np.ndarray) -> np.ndarray:
        """Bool mask of (row, col) inside the grid."""
        return (row >= 0) & (row < self.height) & (col >= 0) & (col < self.width)

    def centres(self) -> tuple[np.ndarray, np.ndarray]:
        """Cell-centre coordinates X, Y, each (height, width) float64."""
        xs = self.xmin + (np.arange(self.width) + 0.5) * self.res
        ys = self.ymax - (np.arange(self.height) + 0.5) * self.res
        return np.meshgrid(xs, ys)

    def to_dict(self) -> dict[str, Any]:
        return {"crs_epsg": self.crs_epsg, "xmin": self.xmin, "ymax": self.ymax, "res": self.res,
                "width": self.width, "height": self.height, "bounds": list(self.bounds)}

    @classmethod
    def from_bounds(cls, bounds: tuple[float, float, float, float], res: float,
                    crs_epsg: int) -> "Grid":
        """Grid covering (xmin, ymin, xmax, ymax) with cells of `res` starting at (xmin, ymax)."""
        xmin, ymin, xmax, ymax = map(float, bounds)
        if not (res > 0 and xmax > xmin and ymax > ymin):
            raise ValueError(f"bad grid bounds {bounds} or resolution {res}")
        width = max(1, math.ceil((xmax - xmin) / res - 1e-9))
        height = max(1, math.ceil((ymax - ymin) / res - 1e-9))
        return cls(int(crs_epsg), xmin, ymax, float(res), width, height)

    @classmethod
    def from_site_json(cls, d: dict[str, Any], path: str | Path = "site.json") -> "Grid":
        """Grid from site.json hints {"crs_epsg", "resolution_m", "bounds": [xmin, ymin, xmax, ymax]}."""
        missing = [k for k in ("crs_epsg", "resolution_m", "bounds") if d.get(k) is None]
        if missing:
            raise InputError(path, f"cannot build the DSM grid: missing {', '.join(missing)}")
        b = d["bounds"]
        if len(b) != 4 or not (b[2] > b[0] and b[3] > b[1]) or not d["resolution_m"] > 0:
            raise InputError(path, f"bad bounds {b} or resolution_m {d['resolution_m']}")
        return cls.from_bounds(tuple(b), float(d["resolution_m"]), int(d["crs_epsg"]))

    @classmethod
    def from_points(cls, xy: np.ndarray, res: float, crs_epsg: int,
                    margin: float = 0.0) -> "Grid":
        """Smallest grid snapped to multiples of `res` holding all points plus a margin.

        xy: (n, 2) or (n, 3) coordinates in the grid's CRS.
        """
        xy = np.asarray(xy, dtype=np.float64)
        if len(xy) == 0:
            raise ValueError("no points to build a grid from")
        lo = xy[:, :2].min(axis=0) - margin
        hi = xy[:, :2].max(axis=0) + margin
        xmin = math.floor(lo[0] / res) * res
        ymax = math.ceil(hi[1] / res) * res
        xmin -= res if xmin > lo[0] else 0.0             # guard against rounding
        ymax += res if ymax < hi[1] else 0.0
        width = int(math.floor((hi[0] - xmin) / res)) + 1
        height = int(math.floor((ymax - lo[1]) / res)) + 1
        return cls(int(crs_epsg), float(xmin), float(ymax), float(res), width, height)


# --------------------------------------------------------------------------------------------
# Rasterisation
# --------------------------------------------------------------------------------------------
def _reduce_sorted(lin: np.ndarray, h: np.ndarray,
                   stat: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-cell statistic of heights.

    Args:
        lin: (n,) linear cell indices; h: (n,) float64 heights.
        stat: one of STATS.
    Returns:
        cells (k,) unique cell indices, values (k,) float64, counts (k,) int64.
    """
    order = np.lexsort((h, lin))                         # by cell, then by height
    lin, h = lin[order], h[order]
    start = np.flatnonzero(np.r_[True, lin[1:] != lin[:-1]])
    counts = np.diff(np.r_[start, len(lin)])
    cells = lin[start]
    if stat == "max":
        return cells, h[start + counts - 1], counts
    if stat == "min":
        return cells, h[start], counts
    if stat == "mean":
        return cells, np.add.reduceat(h, start) / counts, counts
    pos = STATS[stat] * (counts - 1)                     # linear interpolation, as np.percentile
    lo = np.floor(pos).astype(np.int64)
    hi = np.minimum(lo + 1, counts - 1)
    frac = pos - lo
    return cells, h[start + lo] + frac * (h[start + hi] - h[start + lo]), counts


def _check_stat(stat: str) -> None:
    if stat not in STATS:
        raise ValueError(f"unknown cell statistic {stat!r}; choose one of {sorted(STATS)}")


def rasterize(xyz: np.ndarray, grid: Grid, *, stat: str = "median") -> tuple[np.ndarray, np.ndarray]:
    """Rasterise a cloud into a DSM in one pass.

    Args:
        xyz: (n, 3) points (x, y, h) in the grid's CRS; non-finite points are ignored.
        grid: the output grid; points outside it are ignored.
        stat: cell statistic (default "median"; see the module docstring).
    Returns:
        H: (height, width) float32, NaN where no point fell; count: (height, width) int32.
    """
    _check_stat(stat)
    xyz = np.asarray(xyz)
    row, col, h = _points_in_grid(xyz, grid)
    H = np.full(grid.shape, np.nan, dtype=np.float32)
    count = np.zeros(grid.shape, dtype=np.int32)
    if len(h):
        cells, vals, counts = _reduce_sorted(row * grid.width + col, h, stat)
        H.flat[cells] = vals
        count.flat[cells] = counts
    return H, count


def _points_in_grid(xyz: np.ndarray, grid: Grid) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(row, col, h) of the finite points of (n, 3) xyz that fall inside the grid."""
    if xyz.ndim != 2 or xyz.shape[1] < 3:
        raise ValueError(f"expected (n, 3) points, got shape {xyz.shape}")
    row, col = grid.cell_of(xyz[:, 0], xyz[:, 1])
    h = xyz[:, 2].astype(np.float64)
    keep = grid.contains(row, col) & np.isfinite(h)
    return row[keep], col[keep], h[keep]


class DsmAccumulator:
    """Streaming rasteriser: feed chunks of points, get the same DSM as `rasterize`.

    Each point is reduced to (cell index within its block, height) and filed under its block of
    `block_rows` grid rows, so the caller can drop each chunk after `add`. With `spill_dir` the
    per-block values go to files on disk (12 bytes per point) instead of memory. `finish` then
    reduces one block at a time with the same code as `rasterize`, so results are identical.
    """

    def __init__(self, grid: Grid, *, stat: str = "median", block_rows: int = 512,
                 spill_dir: str | Path | None = None):
        _check_stat(stat)
        self.grid, self.stat, self.block_rows = grid, stat, max(1, int(block_rows))
        self.n_blocks = math.ceil(grid.height / self.block_rows)
        self.n_points = 0
        self._mem: dict[int, list[tuple[np.ndarray, np.ndarray]]] = {}
        self._tmp = None
        if spill_dir is not None:
            self._tmp = tempfile.TemporaryDirectory(prefix="dsm_blocks_", dir=spill_dir)

    def add(self, xyz: np.ndarray) -> None:
        """File a chunk of (n, 3) points (x, y, h in the grid's CRS) under their blocks."""
        row, col, h = _points_in_grid(np.asarray(xyz), self.grid)
        if not len(h):
            return
        self.n_points += len(h)
        block = row // self.block_rows
        local = ((row - block * self.block_rows) * self.grid.width + col).astype(np.int64)
        order = np.argsort(block, kind="stable")
        block, local, h = block[order], local[order], h[order]
        cuts = np.flatnonzero(np.r_[True, block[1:] != block[:-1], True])
        for a, b in zip(cuts[:-1], cuts[1:]):
            self._store(int(block[a]), local[a:b], h[a:b])

    def _store(self, b: int, local: np.ndarray, h: np.ndarray) -> None:
        if self._tmp is None:
            self._mem.setdefault(b, []).append((local.copy(), h.copy()))
            return
        base = Path(self._tmp.name) / f"b{b:06d}"
        with open(f"{base}.idx", "ab") as f:
            local.astype("<i4" if self.block_rows * self.grid.width < 2**31 else "<i8").tofile(f)
        with open(f"{base}.h", "ab") as f:
            h.astype("<f8").tofile(f)

    def _load(self, b: int) -> tuple[np.ndarray, np.ndarray] | None:
        if self._tmp is None:
            parts = self._mem.pop(b, None)
            if not parts:
                return None
            return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])
        base = Path(self._tmp.name) / f"b{b:06d}"
        if not os.path.exists(f"{base}.h"):
            return None
        dt = "<i4" if self.block_rows * self.grid.width < 2**31 else "<i8"
        return (np.fromfile(f"{base}.idx", dtype=dt).astype(np.int64),
                np.fromfile(f"{base}.h", dtype="<f8"))

    def finish(self) -> tuple[np.ndarray, np.ndarray]:
        """Reduce every block. Returns H (height, width) float32 NaN-empty, count int32."""
        H = np.full(self.grid.shape, np.nan, dtype=np.float32)
        count = np.zeros(self.grid.shape, dtype=np.int32)
        for b in range(self.n_blocks):
            data = self._load(b)
            if data is None:
                continue
            cells, vals, counts = _reduce_sorted(data[0], data[1], self.stat)
            r0 = b * self.block_rows
            r1 = min(r0 + self.block_rows, self.grid.height)
            H[r0:r1].flat[cells] = vals
            count[r0:r1].flat[cells] = counts
        self.close()
        return H, count

    def close(self) -> None:
        """Remove spilled block files."""
        if self._tmp is not None:
            self._tmp.cleanup()
            self._tmp = None
        self._mem.clear()


# --------------------------------------------------------------------------------------------
# Hole filling
# --------------------------------------------------------------------------------------------
def fill_small_holes(H: np.ndarray, max_hole_px: int = 3, min_support: float = 0.5,
                     window: int = 5) -> np.ndarray:
    """Fill only small NaN holes; big voids stay NaN.

    A NaN cell is a candidate when its connected NaN region (4-connectivity) has at most
    (2 max_hole_px + 1)^2 cells. A candidate is filled with the median of the valid cells of its
    `window` x `window` neighbourhood when at least `min_support` of that window is valid. This
    is iterated at most `max_hole_px` times (holes close from their rim inwards).

    Args:
        H: (height, width) float array, NaN = empty.
    Returns:
        A filled float32 copy.
    """
    from scipy import ndimage

    out = np.array(H, dtype=np.float32, copy=True)
    nan = np.isnan(out)
    if not nan.any() or nan.all():
        return out
    lab, n = ndimage.label(nan)
    sizes = np.bincount(lab.ravel(), minlength=n + 1)
    small = (sizes <= (2 * max_hole_px + 1) ** 2)
    small[0] = False
    cand = small[lab]
    r = window // 2
    offs = np.array([(dy, dx) for dy in range(-r, r + 1) for dx in range(-r, r + 1)])
    for _ in range(max(1, int(max_hole_px))):
        rows, cols = np.nonzero(cand & np.isnan(out))
        if not len(rows):
            break
        pad = np.pad(out, r, constant_values=np.nan)
        vals = pad[rows[:, None] + r + offs[:, 0], cols[:, None] + r + offs[:, 1]]   # (k, w*w)
        ok = np.isfinite(vals).sum(axis=1) >= min_support * len(offs)
        if not ok.any():
            break
        out[rows[ok], cols[ok]] = np.nanmedian(vals[ok], axis=1)
    return out


# --------------------------------------------------------------------------------------------
# GeoTIFF
# --------------------------------------------------------------------------------------------
def _has_cog_driver() -> bool:
    with rasterio.Env() as env:
        return "COG" in env.drivers()


def write_geotiff(path: str | Path, arr: np.ndarray, transform: Affine, crs: Any,
                  *, resampling: str = "average") -> Path:
    """Write a single-band float32 raster (NaN nodata) as a Cloud-Optimized GeoTIFF, atomically.

    256 x 256 tiles, DEFLATE with the floating-point predictor, internal overviews. Uses GDAL's
    COG driver when present; otherwise a tiled GTiff with overviews built after writing.
    """
    path = Path(path)
    arr = np.asarray(arr, dtype=np.float32)
    if arr.ndim != 2:
        raise ValueError(f"expected a 2D array, got shape {arr.shape}")
    profile = dict(count=1, dtype="float32", width=arr.shape[1], height=arr.shape[0],
                   crs=crs, transform=transform, nodata=np.nan)
    with atomic_path(path) as tmp:
        if _has_cog_driver():
            with rasterio.open(tmp, "w", driver="COG", BLOCKSIZE=256, COMPRESS="DEFLATE",
                               PREDICTOR="FLOATING_POINT", OVERVIEWS="AUTO",
                               OVERVIEW_RESAMPLING=resampling.upper(), **profile) as dst:
                dst.write(arr, 1)
        else:
            _write_gtiff_tiled(tmp, arr, profile, resampling)
    return path


def _write_gtiff_tiled(tmp: Path, arr: np.ndarray, profile: dict, resampling: str) -> None:
    """Fallback: tiled DEFLATE GTiff plus internal overviews."""
    with rasterio.open(tmp, "w", driver="GTiff", tiled=True, blockxsize=256, blockysize=256,
                       compress="deflate", predictor=3, BIGTIFF="IF_SAFER", **profile) as dst:
        dst.write(arr, 1)
        factors, f = [], 2
        while max(arr.shape) / f >= 256:
            factors.append(f)
            f *= 2
        if factors:
            dst.build_overviews(factors, Resampling[resampling])


def write_dsm(path: str | Path, H: np.ndarray, grid: Grid) -> Path:
    """Write a DSM (height, width) float32, NaN nodata, in the grid's CRS (see write_geotiff)."""
    if H.shape != grid.shape:
        raise ValueError(f"DSM shape {H.shape} does not match the grid {grid.shape}")
    return write_geotiff(path, H, grid.transform, grid.crs)


def read_dsm(path: str | Path) -> tuple[np.ndarray, Grid]:
    """Read a single-band DSM: (H (height, width) float32 with NaN nodata, its Grid).

    Raises:
        InputError: no CRS, no EPSG code, rotated or non-square pixels.
    """
    with rasterio.open(path) as src:
        if src.crs is None:
            raise InputError(path, "has no CRS; a DSM must be geo-referenced in a projected CRS")
        epsg = src.crs.to_epsg()
        t = src.transform
        if epsg is None:
            raise InputError(path, f"its CRS has no EPSG code ({src.crs.to_string()[:60]})")
        if t.b != 0 or t.d != 0 or t.e >= 0 or not math.isclose(t.a, -t.e, rel_tol=1e-9):
            raise InputError(path, f"needs a north-up grid with square cells, got {tuple(t)[:6]}")
        H = src.read(1, masked=True).astype(np.float32).filled(np.nan)
        grid = Grid(int(epsg), float(t.c), float(t.f), float(t.a), src.width, src.height)
    return H, grid


# --------------------------------------------------------------------------------------------
# PLY
# --------------------------------------------------------------------------------------------
_PLY_TYPES = {"char": "i1", "uchar": "u1", "short": "<i2", "ushort": "<u2", "int": "<i4",
              "uint": "<u4", "float": "<f4", "double": "<f8", "int8": "i1", "uint8": "u1",
              "int16": "<i2", "uint16": "<u2", "int32": "<i4", "uint32": "<u4",
              "float32": "<f4", "float64": "<f8"}


def _ply_dtype(n_extra: list[str], with_colors: bool) -> np.dtype:
    fields = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    if with_colors:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    return np.dtype(fields + [(k, "<f4") for k in n_extra])


def write_ply(path: str | Path, xyz: np.ndarray, colors: np.ndarray | None = None,
              extra: dict[str, np.ndarray] | None = None, chunk: int = 1 << 20) -> Path:
    """Write a binary little-endian PLY point cloud atomically.

    Args:
        xyz: (n, 3) float64 coordinates (stored as double so UTM survives exactly).
        colors: (n, 3) uint8 RGB, optional.
        extra: name -> (n,) values stored as float32 properties, optional.
        chunk: points per write (bounds the temporary memory).
    """
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    n = len(xyz)
    extra = {k: np.asarray(v).reshape(-1) for k, v in (extra or {}).items()}
    for k, v in extra.items():
        if len(v) != n or not k.isidentifier():
            raise ValueError(f"extra field {k!r}: bad name or length {len(v)} != {n}")
    if colors is not None:
        colors = np.asarray(colors).reshape(-1, 3)
        if len(colors) != n:
            raise ValueError(f"{len(colors)} colours for {n} points")
    with PlyWriter(path, list(extra), colors is not None) as w:
        for a in range(0, n, chunk):
            b = min(n, a + chunk)
            w.append(xyz[a:b], None if colors is None else colors[a:b],
                     {k: v[a:b] for k, v in extra.items()})
    return Path(path)


class PlyWriter:
    """Streaming binary little-endian PLY writer: append chunks, the count is set on close.

    The file is written under a temporary name and renamed onto `path` only when the block
    ends without an exception (a crash leaves no half-written cloud). The header is written
    first with room for any count (a padding comment absorbs the difference), so closing only
    rewrites the header in place: no second copy of a cloud of hundreds of millions of points.
    """

    _COUNT_DIGITS = 20

    def __init__(self, path: str | Path, extra: list[str] | tuple[str, ...] = (), with_colors: bool = True):
        for k in extra:
            if not k.isidentifier():
                raise ValueError(f"extra field {k!r}: bad name")
        self.path = Path(path)
        self.dtype = _ply_dtype(list(extra), with_colors)
        self.extra, self.with_colors = list(extra), with_colors
        self.n = 0
        self._ctx = atomic_path(self.path)
        self._tmp = self._ctx.__enter__()
        self._f = open(self._tmp, "wb")
        self._header_len = len(self._header(10 ** (self._COUNT_DIGITS - 1), 0)) + 10
        self._f.write(self._header(0, self._header_len))

    def _header(self, n: int, size: int) -> bytes:
        ply_name = {np.dtype("<f8"): "double", np.dtype("u1"): "uchar", np.dtype("<f4"): "float"}
        head = ["ply", "format binary_little_endian 1.0", "comment written by AE-Rec",
                f"element vertex {n}"]
        head += [f"property {ply_name[self.dtype[k]]} {k}" for k in self.dtype.names]
        text = "\n".join(head) + "\n"
        tail = "end_header\n"
        if size:
            pad = size - len(text) - len(tail) - len("comment \n")
            text += "comment " + " " * pad + "\n"
        return (text + tail).encode("ascii")

    def append(self, xyz: np.ndarray, colors: np.ndarray | None = None,
               extra: dict[str, np.ndarray] | None = None) -> None:
        xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
        m = len(xyz)
        rec = np.empty(m, dtype=self.dtype)
        rec["x"], rec["y"], rec["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
        if self.with_colors:
            if colors is None:
                raise ValueError("this PLY has colours: pass them")
            colors = np.asarray(colors).reshape(m, -1)
            for i, c in enumerate(("red", "green", "blue")):
                rec[c] = colors[:, i if colors.shape[1] == 3 else 0]
        extra = extra or {}
        if set(extra) != set(self.extra):
            raise ValueError(f"extra fields {sorted(extra)} != {sorted(self.extra)}")
        for k, v in extra.items():
            rec[k] = np.asarray(v).reshape(-1)
        rec.tofile(self._f)
        self.n += m

    def close(self, ok: bool = True) -> None:
        """Finish the file (ok) or discard it (not ok, e.g. after an exception)."""
        if self._f is None:
            return
        f, self._f = self._f, None
        try:
            if ok:
                f.seek(0)
                f.write(self._header(self.n, self._header_len))
            f.close()
        except BaseException as exc:
            f.close()
            self._ctx.__exit__(type(exc), exc, exc.__traceback__)
            raise
        if ok:
            self._ctx.__exit__(None, None, None)
        else:
            err = RuntimeError("PLY writing aborted")
            self._ctx.__exit__(RuntimeError, err, None)

    def __enter__(self) -> "PlyWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.close(ok=exc_type is None)


def _read_ply_header(f, path) -> tuple[int, np.dtype]:
    """Parse a binary little-endian PLY header. Returns (vertex count, vertex dtype)."""
    if f.readline().strip() != b"ply":
        raise InputError(path, "not a PLY file")
    n, fields, element = None, [], None
    while True:
        line = f.readline()
        if not line:
            raise InputError(path, "PLY header has no end_header")
        tok = line.decode("ascii", "replace").split()
        if not tok or tok[0] in ("comment", "obj_info"):
            continue
        if tok[0] == "end_header":
            break
        if tok[0] == "format" and tok[1] != "binary_little_endian":
            raise InputError(path, f"PLY format {tok[1]} is not supported (binary_little_endian only)")
        if tok[0] == "element":
            if element is None and tok[1] != "vertex":
                raise InputError(path, "the first PLY element must be 'vertex'")
            element = tok[1]
            if element == "vertex":
                n = int(tok[2])
        elif tok[0] == "property" and element == "vertex":
            if tok[1] == "list" or tok[1] not in _PLY_TYPES:
                raise InputError(path, f"unsupported vertex property {' '.join(tok[1:])}")
            fields.append((tok[2], _PLY_TYPES[tok[1]]))
    if n is None:
        raise InputError(path, "PLY file has no vertex element")
    return n, np.dtype(fields)


def open_ply(path: str | Path) -> np.ndarray:
    """Memory-map the vertices of a binary PLY as a structured array (nothing read yet)."""
    path = Path(path)
    with open(path, "rb") as f:
        n, dt = _read_ply_header(f, path)
        offset = f.tell()
    size = path.stat().st_size
    if size < offset + n * dt.itemsize:
        raise InputError(path, f"PLY file truncated: {(size - offset) // dt.itemsize} of {n} vertices")
    if not {"x", "y", "z"} <= set(dt.names):
        raise InputError(path, "PLY vertices lack x, y, z")
    if n == 0:
        return np.zeros(0, dtype=dt)
    return np.memmap(path, dtype=dt, mode="r", offset=offset, shape=(n,))


def ply_fields(rec: np.ndarray) -> tuple[np.ndarray, np.ndarray | None, dict[str, np.ndarray]]:
    """(xyz (n, 3) float64, colors (n, 3) uint8 or None, extra) of PLY vertex records (copies)."""
    names = set(rec.dtype.names)
    xyz = np.column_stack([rec["x"], rec["y"], rec["z"]]).astype(np.float64)
    rgb = ("red", "green", "blue")
    colors = np.column_stack([rec[c] for c in rgb]).astype(np.uint8) if set(rgb) <= names else None
    extra = {k: np.array(rec[k]) for k in rec.dtype.names if k not in ("x", "y", "z", *rgb)}
    return xyz, colors, extra


def read_ply(path: str | Path) -> tuple[np.ndarray, np.ndarray | None, dict[str, np.ndarray]]:
    """Read a binary little-endian PLY: (xyz (n, 3) float64, colors (n, 3) uint8 or None, extra)."""
    rec = open_ply(path)
    out = ply_fields(rec)
    del rec
    return out
