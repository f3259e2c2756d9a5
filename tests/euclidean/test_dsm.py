"""DSM grid, rasterisation, streaming, hole filling, GeoTIFF and PLY round trips."""

from __future__ import annotations

import numpy as np
import pytest
import rasterio

from recon_core.errors import InputError
from recon_core.euclidean.dsm import DsmAccumulator, fill_small_holes, rasterize
from recon_core.io.ply import read_ply, write_ply
from recon_core.io.raster import Grid, read_dsm, write_dsm

EPSG = 32631
X0, Y0 = 500_000.0, 4_650_000.0


def building_height(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Ground at 100 m with a 30 m box on [X0+10, X0+20) x (Y0-20, Y0-8]."""
    inside = (x >= X0 + 10) & (x < X0 + 20) & (y > Y0 - 20) & (y <= Y0 - 8)
    return 100.0 + 30.0 * inside


def sample_cells(grid: Grid, per_cell: int, rng: np.random.Generator) -> np.ndarray:
    """per_cell uniform points inside every cell, heights from building_height. (n, 3)."""
    X, Y = grid.centres()
    u = rng.uniform(-0.5, 0.5, (per_cell,) + X.shape) * grid.res
    v = rng.uniform(-0.5, 0.5, (per_cell,) + X.shape) * grid.res
    x, y = (X + u).ravel(), (Y + v).ravel()
    return np.column_stack([x, y, building_height(x, y)])


def brute_force(xyz: np.ndarray, grid: Grid, fn) -> np.ndarray:
    """Independent per-cell loop with numpy's own statistics."""
    out = np.full(grid.shape, np.nan)
    for r in range(grid.height):
        for c in range(grid.width):
            x0, y1 = grid.xmin + c * grid.res, grid.ymax - r * grid.res
            m = ((xyz[:, 0] >= x0) & (xyz[:, 0] < x0 + grid.res) & (xyz[:, 1] <= y1)
                 & (xyz[:, 1] > y1 - grid.res))
            if m.any():
                out[r, c] = fn(xyz[m, 2])
    return out


@pytest.fixture
def grid() -> Grid:
    return Grid(EPSG, X0, Y0, 1.0, 30, 25)


def test_grid_geometry(grid):
    assert (grid.transform.c, grid.transform.f) == (X0, Y0)
    X, Y = grid.centres()
    assert X[0, 0] == X0 + 0.5 and Y[0, 0] == Y0 - 0.5 and X.shape == (25, 30)
    r, c = grid.cell_of(X, Y)
    assert np.array_equal(r, np.repeat(np.arange(25)[:, None], 30, 1))
    assert np.array_equal(c, np.repeat(np.arange(30)[None], 25, 0))
    g = Grid.from_site_json({"crs_epsg": EPSG, "resolution_m": 0.5,
                             "bounds": [X0, Y0 - 10, X0 + 20, Y0]})
    assert (g.width, g.height, g.xmin, g.ymax) == (40, 20, X0, Y0)
    with pytest.raises(InputError, match="missing resolution_m"):
        Grid.from_site_json({"crs_epsg": EPSG, "bounds": [0, 0, 1, 1]})
    pts = np.random.default_rng(0).uniform([X0, Y0], [X0 + 37.3, Y0 + 11.1], (500, 2))
    g = Grid.from_points(pts, 0.5, EPSG, margin=1.0)
    r, c = g.cell_of(pts[:, 0], pts[:, 1])
    assert g.contains(r, c).all() and g.xmin % 0.5 == 0


def test_rasterize_box_building(grid):
    rng = np.random.default_rng(1)
    xyz = sample_cells(grid, 9, rng)
    xyz = np.vstack([xyz, [[X0 + 2.5, Y0 - 2.5, 180.0]], [[X0 - 5, Y0 - 5, 0.0]]])  # outlier; outside
    H, count = rasterize(xyz, grid)
    X, Y = grid.centres()
    expected = building_height(X, Y)
    assert H.dtype == np.float32 and count.dtype == np.int32
    assert np.array_equal(H, expected.astype(np.float32))   # outlier rejected by the median
    assert count[2, 2] == 10 and count.sum() == 9 * grid.width * grid.height + 1
    Hmax, _ = rasterize(xyz, grid, stat="max")
    assert Hmax[2, 2] == 180.0


@pytest.mark.parametrize("stat,fn", [("median", np.median),
                                     ("upper_median", lambda v: np.percentile(v, 75)),
                                     ("max", np.max), ("min", np.min), ("mean", np.mean)])
def test_rasterize_matches_brute_force(stat, fn):
    g = Grid(EPSG, X0, Y0, 2.0, 9, 7)
    rng = np.random.default_rng(2)
    n = 400
    xyz = np.column_stack([rng.uniform(X0 - 2, X0 + 20, n), rng.uniform(Y0 - 16, Y0 + 2, n),
                           rng.normal(50, 10, n)])
    H, count = rasterize(xyz, g, stat=stat)
    ref = brute_force(xyz, g, fn)
    assert np.allclose(H, ref, equal_nan=True, atol=1e-4)
    assert np.array_equal(count, np.nan_to_num(brute_force(xyz, g, len)).astype(int))
    assert np.isnan(H).any()                                  # some cells are empty


@pytest.mark.parametrize("spill", [False, True])
def test_streaming_equals_one_shot(tmp_path, spill):
    g = Grid(EPSG, X0, Y0, 0.5, 83, 61)
    rng = np.random.default_rng(3)
    n = 60_000
    xyz = np.column_stack([rng.uniform(X0 - 3, X0 + 45, n), rng.uniform(Y0 - 33, Y0 + 3, n),
                           rng.normal(50, 10, n)])
    for stat in ("median", "upper_median", "mean", "max"):
        ref_H, ref_c = rasterize(xyz, g, stat=stat)
        acc = DsmAccumulator(g, stat=stat, block_rows=7, spill_dir=tmp_path if spill else None)
        cuts = np.sort(rng.integers(0, n, 6))
        for part in np.split(xyz, cuts):
            acc.add(part)
        H, c = acc.finish()
        assert np.array_equal(H, ref_H, equal_nan=True) and np.array_equal(c, ref_c)
    assert list(tmp_path.iterdir()) == []                     # spilled blocks removed


@pytest.mark.parametrize("spill", [False, True])
def test_fallback_points_count_only_where_no_other_point_falls(tmp_path, spill):
    """Tier 1 (a weak pair's two-view points): a cell with any tier-0 point is the statistic of
    its tier-0 points alone; a cell with tier-1 points only takes theirs."""
    g = Grid(EPSG, X0, Y0, 0.5, 40, 30)
    rng = np.random.default_rng(5)
    n = 20_000
    xyz = np.column_stack([rng.uniform(X0, X0 + 20, n), rng.uniform(Y0 - 15, Y0, n),
                           rng.normal(50, 1, n)])
    tier = (rng.random(n) < 0.4).astype(np.uint8)
    tier[xyz[:, 0] > X0 + 15] = 1                             # a strip of fallback cells only
    xyz[tier == 1, 2] += 30.0                                 # fallbacks are far off
    acc = DsmAccumulator(g, block_rows=7, spill_dir=tmp_path if spill else None)
    for part, t in zip(np.array_split(xyz, 5), np.array_split(tier, 5)):
        acc.add(part, t)
    H, count = acc.finish()
    H0, c0 = rasterize(xyz[tier == 0], g)
    H1, c1 = rasterize(xyz[tier == 1], g)
    has0 = np.isfinite(H0)
    assert has0.sum() > 500 and (~has0 & np.isfinite(H1)).sum() > 200
    assert np.array_equal(H[has0], H0[has0]) and np.array_equal(count[has0], c0[has0])
    assert np.array_equal(H[~has0], H1[~has0], equal_nan=True)


def test_fill_small_holes_but_not_voids():
    rng = np.random.default_rng(4)
    H = (100 + rng.normal(0, 0.1, (60, 60))).astype(np.float32)
    H[10, 10] = np.nan
    H[20:23, 40:43] = np.nan                                  # 3x3 hole
    H[30:50, 5:25] = np.nan                                   # 20x20 void
    out = fill_small_holes(H)
    expected = np.median(np.delete(H[8:13, 8:13].ravel(), 12))
    assert out[10, 10] == pytest.approx(expected)
    assert np.isfinite(out[20:23, 40:43]).all()
    assert np.isnan(out[30:50, 5:25]).all()
    valid = np.isfinite(H)
    assert np.array_equal(out[valid], H[valid])               # valid cells untouched


def test_fill_small_holes_by_blocks_is_the_same(tmp_path):
    """Blocks of a few rows (disk-backed in and out) give the same DSM as one block: holes and
    voids of every size, some cut by many block edges."""
    rng = np.random.default_rng(8)
    H = (100 + rng.normal(0, 0.5, (300, 120))).astype(np.float32)
    H[rng.random(H.shape) < 0.08] = np.nan                     # single cells and small clusters
    for _ in range(40):
        r, c = rng.integers(0, 290), rng.integers(0, 110)
        H[r:r + rng.integers(1, 9), c:c + rng.integers(1, 9)] = np.nan
    H[100:103, 30] = np.nan
    H[40:70, 60] = np.nan                                       # a thin line of 30 cells: a void
    one = fill_small_holes(H, max_hole_px=2, block_rows=10_000)
    src = np.lib.format.open_memmap(tmp_path / "h.npy", "w+", np.float32, H.shape)
    src[:] = H
    dst = np.lib.format.open_memmap(tmp_path / "o.npy", "w+", np.float32, H.shape)
    for rows in (1, 7, 64):
        out = fill_small_holes(src, max_hole_px=2, block_rows=rows, out=dst)
        assert out is dst and np.array_equal(np.asarray(dst), one, equal_nan=True), rows
    assert np.isnan(one[40:70, 60]).all() and np.isfinite(one[100:103, 30]).all()
    with pytest.raises(ValueError):
        fill_small_holes(src, out=src)
    assert np.isnan(one).sum() < np.isnan(H).sum()


def test_geotiff_round_trip(tmp_path, grid):
    H = np.random.default_rng(5).normal(100, 5, grid.shape).astype(np.float32)
    H[3:6, 4:9] = np.nan
    big = Grid(EPSG, X0, Y0, 0.5, 700, 600)
    Hb = np.resize(H, big.shape)
    for g, A in ((grid, H), (big, Hb)):
        p = write_dsm(tmp_path / "sub" / "dsm.tif", A, g)
        A2, g2 = read_dsm(p)
        assert g2 == g and np.array_equal(A2, A, equal_nan=True)
        with rasterio.open(p) as src:
            assert src.crs.to_epsg() == EPSG and np.isnan(src.nodata)
            assert src.dtypes[0] == "float32" and src.profile["tiled"]
            assert src.block_shapes[0] == (256, 256) and src.compression.name.lower() == "deflate"
            if g is big:
                assert src.overviews(1)                       # internal overviews
    assert sorted(x.name for x in (tmp_path / "sub").iterdir()) == ["dsm.tif"]   # atomic
    with rasterio.open(tmp_path / "nocrs.tif", "w", driver="GTiff", width=4, height=4, count=1,
                       dtype="float32") as dst:
        dst.write(np.zeros((1, 4, 4), np.float32))
    with pytest.raises(InputError, match="nocrs.tif: has no CRS"):
        read_dsm(tmp_path / "nocrs.tif")


def test_ply_round_trip_keeps_utm_exactly(tmp_path):
    rng = np.random.default_rng(6)
    n = 1000
    xyz = np.column_stack([rng.uniform(4e5, 6e5, n), rng.uniform(4e6, 5e6, n), rng.uniform(0, 300, n)])
    rgb = rng.integers(0, 256, (n, 3)).astype(np.uint8)
    conf = rng.random(n)
    p = write_ply(tmp_path / "cloud.ply", xyz, rgb, {"confidence": conf})
    xyz2, rgb2, extra = read_ply(p)
    assert np.array_equal(xyz2, xyz) and np.array_equal(rgb2, rgb)
    assert np.array_equal(extra["confidence"], conf.astype(np.float32))
    header = p.read_bytes()[:300].decode("ascii", "replace")
    assert "binary_little_endian" in header and "property double x" in header
    p2 = write_ply(tmp_path / "bare.ply", xyz[:5], chunk=2)
    xyz3, rgb3, extra3 = read_ply(p2)
    assert np.array_equal(xyz3, xyz[:5]) and rgb3 is None and extra3 == {}


def test_ply_writer_streams_and_is_atomic(tmp_path):
    """Chunks appended to a PlyWriter read back as one cloud; an exception leaves no file."""
    from recon_core.io.ply import PlyWriter, open_ply, ply_fields

    rng = np.random.default_rng(3)
    xyz = rng.normal(size=(1000, 3)) * 1e5
    grey = rng.integers(0, 255, 1000).astype(np.uint8)
    nv = rng.integers(2, 4, 1000).astype(np.float32)
    path = tmp_path / "s.ply"
    with PlyWriter(path, ["n_views"]) as w:
        for a in range(0, 1000, 300):
            w.append(xyz[a:a + 300], grey[a:a + 300, None], {"n_views": nv[a:a + 300]})
    x2, c2, e2 = read_ply(path)
    np.testing.assert_array_equal(x2, xyz)
    np.testing.assert_array_equal(c2[:, 1], grey)
    np.testing.assert_array_equal(e2["n_views"], nv)
    rec = open_ply(path)
    assert len(rec) == 1000
    np.testing.assert_array_equal(ply_fields(rec[10:20])[0], xyz[10:20])
    plyfile = pytest.importorskip("plyfile")                         # an independent reader
    vert = plyfile.PlyData.read(str(path))["vertex"]                   # accepts the header padding
    np.testing.assert_array_equal(np.column_stack([vert["x"], vert["y"], vert["z"]]), xyz)
    np.testing.assert_array_equal(vert["n_views"], nv)

    bad = tmp_path / "bad.ply"
    with pytest.raises(ZeroDivisionError):
        with PlyWriter(bad) as w:
            w.append(xyz[:10], grey[:10, None])
            1 / 0
    assert not bad.exists() and not list(tmp_path.glob(".bad*"))
