"""DSM evaluation: alignment recovery, metrics, refusals, outputs."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import rasterio
from rasterio.crs import CRS
from rasterio.transform import Affine

from recon_core.errors import InputError
from recon_core.evaluation.evaluate import evaluate_dsm, height_metrics, main

EPSG = 32631
X0, Y0 = 500_000.0, 4_650_000.0          # top-left corner of the GT
SHIFT = (1.5, -2.0, 0.7)                  # the DSM's displacement: east, north, up
NOISE = 0.15


BUILDINGS = [  # (u centre, v centre, width, depth, height, rotation in degrees), not grid-aligned
    (35.4, 29.7, 30.3, 18.6, 12.0, 17.0), (78.2, 50.9, 16.5, 40.2, 25.0, 0.0),
    (137.7, 102.3, 35.1, 25.8, 9.0, 63.0), (47.3, 107.6, 14.2, 14.9, 30.0, 38.0),
    (160.6, 35.1, 20.4, 30.7, 15.0, 81.0)]


def surface(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Analytic terrain with rotated box buildings and a gable roof (heights in metres)."""
    u, v = x - X0, Y0 - y
    z = 100.0 + 3.0 * np.sin(u / 37.0) + 2.0 * np.cos(v / 23.0)
    for (cu, cv, w, d, h, a) in BUILDINGS:
        a = np.radians(a)
        p = (u - cu) * np.cos(a) + (v - cv) * np.sin(a)
        q = -(u - cu) * np.sin(a) + (v - cv) * np.cos(a)
        z = np.where((np.abs(p) < w / 2) & (np.abs(q) < d / 2), z + h, z)
    gable = (u >= 100.3) & (u < 140.6) & (v >= 40.2) & (v < 52.2)
    return np.where(gable, z + 6.0 + 4.0 * (1 - np.abs(v - 46.2) / 6.0), z)


def from_origin(x0: float, y0: float, rx: float, ry: float) -> Affine:
    return Affine(rx, 0.0, x0, 0.0, -ry, y0)


def centres(x0: float, y0: float, res: float, w: int, h: int):
    xs = x0 + (np.arange(w) + 0.5) * res
    ys = y0 - (np.arange(h) + 0.5) * res
    return np.meshgrid(xs, ys)


def write_tif(path, arr, x0, y0, res, crs=CRS.from_epsg(EPSG), nodata=np.nan):
    with rasterio.open(path, "w", driver="GTiff", width=arr.shape[1], height=arr.shape[0],
                       count=1, dtype="float32", crs=crs, transform=from_origin(x0, y0, res, res),
                       nodata=nodata) as dst:
        dst.write(arr.astype(np.float32), 1)
    return path


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """GT at 1 m (200 x 160) and a shifted, noisy DSM at 0.5 m with a 30 m x 30 m void."""
    d = tmp_path_factory.mktemp("eval")
    X, Y = centres(X0, Y0, 1.0, 200, 160)
    gt = surface(X, Y)
    gt[:3, :] = np.nan                                      # some GT nodata
    gt_w = np.where(np.isfinite(gt), gt, -9999.0)
    write_tif(d / "gt.tif", gt_w, X0, Y0, 1.0, nodata=-9999.0)
    dx0, dy0, res = X0 - 15.25, Y0 + 14.9, 0.5             # DSM grid: bigger, offset origin
    Xd, Yd = centres(dx0, dy0, res, 460, 380)
    rng = np.random.default_rng(0)
    dsm = surface(Xd - SHIFT[0], Yd - SHIFT[1]) + SHIFT[2] + rng.normal(0, NOISE, Xd.shape)
    void = (Xd >= X0 + 150) & (Xd < X0 + 180) & (Yd <= Y0 - 110) & (Yd > Y0 - 140)
    dsm[void] = np.nan
    write_tif(d / "dsm.tif", dsm, dx0, dy0, res)
    return d


def test_alignment_recovers_shift_and_offset(site, tmp_path):
    r = evaluate_dsm(site / "dsm.tif", site / "gt.tif", tmp_path / "out")
    a = r["alignment"]
    assert abs(a["dx_m"] - SHIFT[0]) < 0.25 and abs(a["dy_m"] - SHIFT[1]) < 0.25
    assert abs(a["dz_m"] - SHIFT[2]) < 0.05
    al, un = r["aligned"], r["unaligned"]
    assert al["median_abs_err_m"] < 0.674 * NOISE * 1.5         # ~ the noise
    assert al["n_gt_cells"] == 200 * 157
    void_pct = 100.0 * 900 / al["n_gt_cells"]                  # the GT cells under the void
    assert al["coverage_pct"] == pytest.approx(100 - void_pct, abs=0.5)
    assert 100 - void_pct - 4 < al["completeness_pct"] <= 100 - void_pct + 0.5
    assert un["median_abs_err_m"] > 2 * al["median_abs_err_m"]
    assert un["completeness_pct"] < al["completeness_pct"] - 3
    assert un["rmse_m"] > al["rmse_m"] and abs(un["mean_err_m"]) > 0.5
    assert not r["warnings"]


def test_outputs_written(site, tmp_path):
    out = tmp_path / "out"
    r = evaluate_dsm(site / "dsm.tif", site / "gt.tif", out, max_shift_m=4.0)
    assert json.loads((out / "eval.json").read_text())["alignment"] == r["alignment"]
    with rasterio.open(out / "height_error.tif") as src:
        assert src.crs.to_epsg() == EPSG and src.shape == (160, 200) and np.isnan(src.nodata)
        assert src.transform == from_origin(X0, Y0, 1.0, 1.0)
        err = src.read(1)
    assert np.isnan(err[:3]).all() and np.isnan(err[115, 160])  # GT nodata; DSM void
    assert np.nanmedian(np.abs(err)) == pytest.approx(r["aligned"]["median_abs_err_m"], rel=1e-5)
    for name in ("height_error.png", "dsm_vs_gt.png"):
        img = cv2.imread(str(out / name))
        assert img is not None and img.shape[0] >= 300 and img.shape[1] >= 400
    assert sorted(p.name for p in out.iterdir()) == ["dsm_vs_gt.png", "eval.json",
                                                     "height_error.png", "height_error.tif"]


def test_refusals_name_the_file(site, tmp_path):
    arr = np.ones((50, 50), np.float32)
    with rasterio.open(tmp_path / "nocrs.tif", "w", driver="GTiff", width=50, height=50, count=1,
                       dtype="float32", transform=from_origin(X0, Y0, 1, 1)) as dst:
        dst.write(arr, 1)
    with pytest.raises(InputError, match=r"nocrs\.tif.*no CRS"):
        evaluate_dsm(tmp_path / "nocrs.tif", site / "gt.tif")
    write_tif(tmp_path / "far.tif", arr, X0 + 5000, Y0, 1.0)
    with pytest.raises(InputError, match=r"far\.tif.*does not overlap"):
        evaluate_dsm(tmp_path / "far.tif", site / "gt.tif")
    local = CRS.from_wkt('LOCAL_CS["site grid",LOCAL_DATUM["unknown",32767],'
                         'UNIT["metre",1],AXIS["Easting",EAST],AXIS["Northing",NORTH]]')
    write_tif(tmp_path / "local.tif", arr, 0.0, 50.0, 1.0, crs=local)
    with pytest.raises(InputError, match=r"local\.tif.*cannot be reprojected"):
        evaluate_dsm(tmp_path / "local.tif", site / "gt.tif")
    with pytest.raises(InputError, match=r"missing\.tif"):
        evaluate_dsm(tmp_path / "missing.tif", site / "gt.tif")


def test_metrics_on_known_errors():
    err = np.array([[0.5, -0.5, 2.0], [np.nan, 0.1, -0.1]])
    gt_valid = np.array([[True, True, True], [True, True, False]])
    m = height_metrics(err, gt_valid)
    e = np.array([0.5, -0.5, 2.0, 0.1])
    assert m["n_gt_cells"] == 5 and m["n_compared"] == 4
    assert m["completeness_pct"] == pytest.approx(100 * 3 / 5)     # the NaN cell fails
    assert m["median_abs_err_m"] == pytest.approx(np.median(np.abs(e)))
    assert m["rmse_m"] == pytest.approx(np.sqrt(np.mean(e ** 2)))
    assert m["nmad_m"] == pytest.approx(1.4826 * np.median(np.abs(e - np.median(e))))


def test_cli_prints_table(site, capsys):
    assert main([str(site / "dsm.tif"), str(site / "gt.tif"), "--max-shift", "3"]) == 0
    out = capsys.readouterr().out
    assert "completeness, within 1 m (%)" in out and "aligned" in out and "dx +1.5" in out
    assert main([str(site / "nope.tif"), str(site / "gt.tif")]) == 2


def test_reduce_for_display_is_a_nan_aware_block_mean():
    from recon_core.evaluation.evaluate import reduce_for_display

    v = np.arange(7 * 5, dtype=np.float32).reshape(7, 5)
    v[0, 0] = np.nan
    same, k = reduce_for_display(v, max_side=10)
    assert k == 1 and same is v
    r, k = reduce_for_display(v, max_side=3)
    assert k == 3 and r.shape == (3, 2)
    assert r[0, 0] == np.mean(v[:3, :3][np.isfinite(v[:3, :3])])      # NaN left out
    assert r[2, 1] == np.mean(v[6:, 3:])                                # partial edge block
    allnan = np.full((9, 9), np.nan, np.float32)
    assert np.isnan(reduce_for_display(allnan, max_side=3)[0]).all()


def test_bend_report_separates_a_dome_from_point_noise():
    """A quadratic dome of 1.2 m plus 0.2 m of point noise over a 3 km site: the quadratic part
    carries the dome, the local part (each point minus its 150 m cell's mean) the noise."""
    from recon_core.synthetic.truth import bend_report

    rng = np.random.default_rng(2)
    Xt = np.column_stack([rng.uniform(-1500, 1500, (60000, 2)), rng.uniform(0, 40, 60000)])
    dome = 1.2 * (1.0 - (Xt[:, 0] ** 2 + Xt[:, 1] ** 2) / 1500.0 ** 2)
    noise = rng.normal(0, 0.2, len(Xt))
    b = bend_report(Xt, dome + noise)
    assert abs(b["local_rms_m"] - 0.2) < 0.02
    assert b["quadratic_range_m"] > 2.0                  # 1.2 m at the centre, -1.2 m at corners
    assert abs(b["rest_rms_m"] - 0.2) < 0.02
    smooth = bend_report(Xt, dome)
    assert smooth["local_rms_m"] < 0.08                  # only the dome's slope across a cell


def test_height_metrics_are_the_plain_formulas():
    """The figures, computed with one reused scratch array, equal the textbook formulas on the
    compared cells (missing DSM cells fail completeness, invalid GT cells are left out)."""
    from recon_core.evaluation.evaluate import NMAD_K, height_metrics

    rng = np.random.default_rng(3)
    err = (rng.standard_t(3, (300, 200)) * 0.4 + 0.1).astype(np.float32)
    err[rng.random(err.shape) < 0.2] = np.nan
    gt_valid = rng.random(err.shape) > 0.1
    r = height_metrics(err, gt_valid, 1.0)
    e = err[gt_valid & np.isfinite(err)].astype(np.float64)
    med = np.median(e)
    assert r["n_gt_cells"] == gt_valid.sum() and r["n_compared"] == e.size
    assert r["completeness_pct"] == 100.0 * np.sum(np.abs(e) < 1.0) / gt_valid.sum()
    assert r["median_abs_err_m"] == np.median(np.abs(e))
    assert r["rmse_m"] == np.sqrt(np.mean(e ** 2)) and r["mean_err_m"] == e.mean()
    assert r["nmad_m"] == NMAD_K * np.median(np.abs(e - med))


def test_same_cells_compares_two_dsms_where_both_have_heights(site, tmp_path):
    """A DSM that fills its void with bad heights has a larger median over its own cells,
    yet on the cells both cover it is as good as the one with the void: same_cells sees that,
    each DSM with its own alignment."""
    from recon_core.evaluation.evaluate import same_cells

    dx0, dy0, res = X0 - 15.25, Y0 + 14.9, 0.5
    Xd, Yd = centres(dx0, dy0, res, 460, 380)
    rng = np.random.default_rng(1)
    base = surface(Xd - SHIFT[0], Yd - SHIFT[1]) + SHIFT[2]
    full = base + rng.normal(0, 2 * NOISE, Xd.shape)
    bad = rng.random(Xd.shape) < 0.6                        # 60 % of the cells 3 m off, up or down...
    holes = (Xd >= X0 + 20) & (Xd < X0 + 120) & (Yd <= Y0 - 20) & (Yd > Y0 - 150)
    full[bad & holes] += rng.choice([-3.0, 3.0], Xd.shape)[bad & holes]   # ...where the other has none
    write_tif(tmp_path / "full.tif", full, dx0, dy0, res)
    holed = np.where(holes, np.nan, base + rng.normal(0, NOISE, Xd.shape))
    write_tif(tmp_path / "holed.tif", holed, dx0, dy0, res)
    rf = evaluate_dsm(tmp_path / "full.tif", site / "gt.tif", None)
    rh = evaluate_dsm(tmp_path / "holed.tif", site / "gt.tif", None)
    assert rf["aligned"]["median_abs_err_m"] > 2 * rh["aligned"]["median_abs_err_m"]
    sc = same_cells(tmp_path / "full.tif", rf["alignment"], tmp_path / "holed.tif", rh["alignment"],
                    site / "gt.tif")
    assert 0 < sc["cells"] < rh["aligned"]["n_compared"] + 1
    # on the shared cells: twice the other's noise, whatever the bad cells elsewhere
    assert sc["a"]["median_abs_err_m"] == pytest.approx(2 * sc["b"]["median_abs_err_m"], rel=0.2)
    assert sc["b"]["median_abs_err_m"] == pytest.approx(rh["aligned"]["median_abs_err_m"], rel=0.05)
    assert sc["a"]["within_pct"] > 95 and sc["b"]["within_pct"] > 95


def test_by_class_scores_the_cells_of_each_class_apart(site, tmp_path):
    """A DSM whose cells of class 1 are 3 m off and class 2 exact (to the noise), the class
    layer on the DSM's grid: by_class finds each class's error and share of the GT's cells,
    with the DSM's alignment applied to both."""
    from recon_core.evaluation.evaluate import by_class

    dx0, dy0, res = X0 - 15.25, Y0 + 14.9, 0.5
    Xd, Yd = centres(dx0, dy0, res, 460, 380)
    rng = np.random.default_rng(2)
    H = surface(Xd - SHIFT[0], Yd - SHIFT[1]) + SHIFT[2] + rng.normal(0, NOISE, Xd.shape)
    cls = np.where(Xd < X0 + 60, 1.0, 2.0).astype(np.float32)
    bad = (cls == 1) & (Yd > np.median(Yd))                    # half of class 1, in one piece
    H[bad] += 3.0
    write_tif(tmp_path / "dsm.tif", H, dx0, dy0, res)
    write_tif(tmp_path / "cls.tif", cls, dx0, dy0, res)
    r = evaluate_dsm(tmp_path / "dsm.tif", site / "gt.tif", None)
    out = by_class(tmp_path / "dsm.tif", r["alignment"], tmp_path / "cls.tif", site / "gt.tif")
    c1, c2 = out["classes"]["1"], out["classes"]["2"]
    # half of class 1 is 3 m off: its cells within 1 m are about half; class 2 all of them
    assert c1["within_pct"] == pytest.approx(50, abs=5) and c2["within_pct"] > 95
    assert c2["median_abs_err_m"] < 3 * NOISE
    # the classes' shares add up to the cells compared, and their completeness to the DSM's
    assert c1["cells_pct_of_gt"] + c2["cells_pct_of_gt"] == pytest.approx(r["aligned"]["coverage_pct"], abs=0.5)
    assert c1["completeness_share_pct"] + c2["completeness_share_pct"] == pytest.approx(
        r["aligned"]["completeness_pct"], abs=0.5)


def _grid(path, res, n, shift=(0.0, 0.0, 0.0)):
    """The analytic surface on an n x n grid of res-metre cells from the GT's corner, shifted."""
    c = (np.arange(n) + 0.5) * res
    xx, yy = np.meshgrid(X0 + c - shift[0], Y0 - c - shift[1])
    z = (surface(xx, yy) + shift[2]).astype(np.float32)
    with rasterio.open(path, "w", driver="GTiff", width=n, height=n, count=1, dtype="float32",
                       crs=CRS.from_epsg(EPSG), transform=Affine(res, 0, X0, 0, -res, Y0), nodata=np.nan) as d:
        d.write(z, 1)
    return path


def test_a_dsm_much_finer_than_the_ground_truth_is_read_averaged_and_scores_as_well(tmp_path):
    """A 0.04 m DSM (5,000 x 5,000 cells) against a 0.5 m ground truth: read averaged by 6 to
    about half the GT's cell (a DSM at the validator's finest resolution was read whole: 21 GB),
    scored as the same surface at 0.25 m is, and said."""
    gt = _grid(tmp_path / "gt.tif", 0.5, 400)
    fine = evaluate_dsm(_grid(tmp_path / "fine.tif", 0.04, 5000, SHIFT), gt)
    quarter = evaluate_dsm(_grid(tmp_path / "quarter.tif", 0.25, 800, SHIFT), gt)
    assert fine["read_averaged"] == {"dsm": 6, "gt": 1} and "read_averaged" not in quarter
    assert any("read averaged by 6" in w for w in fine["warnings"])
    for k in ("dx_m", "dy_m", "dz_m"):
        assert fine["alignment"][k] == pytest.approx(quarter["alignment"][k], abs=0.3)
    assert abs(fine["aligned"]["completeness_pct"] - quarter["aligned"]["completeness_pct"]) < 2.0


def test_a_fine_ground_truth_is_searched_coarse_first(tmp_path):
    """A 0.1 m ground truth: shifts of one of its cells over +-10 m were 40,000 candidates (a
    0.05 m one ran for more than 10 minutes); the search starts coarse and still finds the
    shift to a fraction of a cell."""
    import time

    gt = _grid(tmp_path / "gt.tif", 0.1, 1500)
    t0 = time.time()
    r = evaluate_dsm(_grid(tmp_path / "dsm.tif", 0.5, 300, SHIFT), gt)
    assert time.time() - t0 < 60
    assert r["alignment"]["dx_m"] == pytest.approx(SHIFT[0], abs=0.1)
    assert r["alignment"]["dy_m"] == pytest.approx(SHIFT[1], abs=0.1)
